"""Decoders of the ROS messages gtgen reads into numpy arrays in gtgen's layouts."""
