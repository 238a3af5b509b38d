"""Reading robot logs: bag flavours, message decoding, poses, and the extract stage."""
