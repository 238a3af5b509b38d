"""The dataset store: Zarr v3, sharded along samples, one sample per chunk."""

from gtgen.shards.schema import DATASET_ARRAYS, SCHEMA_VERSION

__all__ = ["DATASET_ARRAYS", "SCHEMA_VERSION"]
