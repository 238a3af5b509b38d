"""Where gtgen's stores live on disk: the formats (``schema``), the one opener per store
kind (``stores``), and the two hand-written Zarr v3 codecs that move whole chunks and
shards as bytes (``chunks``, ``shards``)."""
