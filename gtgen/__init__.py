"""gtgen: pseudo ground truth for BEV elevation and traversability learning.

Data flow: ``bag/`` (read bags) -> ``extract/`` (per-drive store) -> ``fuse/``
(hindsight fusion) -> ``dem/`` (DEM placement) -> ``dataset/`` (Zarr v3 shards) ->
``train/`` (M&M-lite). For users' own code: ``gtgen.open_dataset(path)``.
"""

from __future__ import annotations

from typing import Any

from gtgen.errors import GtgenError

__version__ = "0.1.0"

__all__ = ["GtgenError", "ShardDataset", "__version__", "open_dataset"]


def open_dataset(path: Any) -> Any:
    """Open a dataset store: a :class:`gtgen.api.Dataset` with its schema, splits,
    an xarray view per group and a PyTorch Dataset (see that module)."""
    from gtgen.api import open_dataset as _open

    return _open(path)


def __getattr__(name: str) -> Any:
    # ``gtgen.ShardDataset`` without importing torch for every ``import gtgen``
    if name == "ShardDataset":
        from gtgen.train.data import ShardDataset

        return ShardDataset
    raise AttributeError(f"module 'gtgen' has no attribute {name!r}")
