"""Dataset jobs that compose gtgen's stages over many drives (process pool or Dask)."""
