"""The dataset as users' own code opens it: ``gtgen.open_dataset(path)``.

    ds = gtgen.open_dataset("gtgen_ws/dataset.zarr")
    ds.splits["val"]                       # sample indices of the val split
    ds.schema["labels/micro/elevation_m"]  # dtype, shape, units, frame, fill, meaning
    labels = ds.xarray("labels/micro")     # xarray.Dataset: sample (time) x x_m x y_m
    torch_ds = ds.torch("train")           # a PyTorch Dataset (gtgen.train.data.ShardDataset)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gtgen import codes
from gtgen.storage.schema import DATASET, DatasetAttrs
from gtgen.storage.specs import ArraySpec
from gtgen.storage.stores import open_dataset as _open


@dataclass(frozen=True)
class Dataset:
    """A complete dataset store: its arrays (``zarr``), attributes, schema and splits."""

    path: Path
    zarr: Any
    attrs: DatasetAttrs
    n_samples: int

    @property
    def schema(self) -> dict[str, ArraySpec]:
        """Every array of the format by path: dtype, shape symbols, units, frame, fill, meaning
        (the tables of data_schema.md)."""
        return {s.path: s for s in DATASET.arrays}

    @property
    def splits(self) -> dict[str, np.ndarray]:
        """Sample indices per split name (``train``, ``val``)."""
        split = self.zarr["meta/split"][:] if self.n_samples else np.zeros(0, np.uint8)
        return {name: np.nonzero(split == code)[0] for code, name in codes.SPLITS.items()}

    def xarray(self, group: str = "labels/micro") -> Any:
        """Return one group (``labels/micro``, ``labels/short``, ``xracer/<range>``,
        ``dem/<range>``, ``inputs``, ``meta``) as a lazy ``xarray.Dataset`` with coordinates:
        ``sample`` (time), ``x_m`` and ``y_m`` (cell centres of the target frame [m])."""
        import xarray as xr

        return xr.open_zarr(str(self.path), group=group, consolidated=False, zarr_format=3)

    def torch(self, split: str | None = "train", preset: str = "tiny", config: dict | None = None) -> Any:
        """Return a PyTorch ``Dataset`` of ``split`` (None: every sample) at the model sizes of
        ``preset`` (and a config layer over it): see ``gtgen.train.data.ShardDataset``."""
        from gtgen.config import load_config
        from gtgen.train.data import ShardDataset
        from gtgen.train.presets import preset_overrides

        cfg = load_config(None, preset_overrides(preset), *([config] if config else []))
        return ShardDataset(self.path, cfg.train, split=split)

    def __len__(self) -> int:
        return self.n_samples

    def __repr__(self) -> str:
        counts = ", ".join(f"{k} {len(v)}" for k, v in self.splits.items())
        return f"gtgen.Dataset('{self.path}', {self.n_samples} samples ({counts}), {len(self.attrs.drives)} drive(s))"


def open_dataset(path: str | Path) -> Dataset:
    """Open a complete dataset store, or raise ``gtgen.GtgenError`` saying why not."""
    g, info = _open(Path(path))
    return Dataset(Path(path), g, info.attrs, info.n_samples)
