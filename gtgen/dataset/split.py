"""The train / val split, by geography: never random per sample, since the overlapping
windows of neighbouring samples would leak labels between the splits."""

from __future__ import annotations

import zlib

import numpy as np

from gtgen import codes
from gtgen.config import ShardsConfig


def split_of(easting_m: float, northing_m: float, sc: ShardsConfig) -> int:
    """Return the split code of a sample at (easting, northing): its ``split_block_m``
    block is held out (val) for a ``val_fraction`` of blocks, by a hash of the block."""
    B = sc.split_block_m
    key = f"{int(np.floor(easting_m / B))},{int(np.floor(northing_m / B))}".encode()
    return codes.VAL if (zlib.crc32(key) / 2**32) < sc.val_fraction else codes.TRAIN


def split_counts(split: np.ndarray) -> dict[str, int]:
    """Return {split name: samples} of a ``meta/split`` array."""
    return {codes.SPLITS[int(v)]: int((split == v).sum()) for v in np.unique(split)}
