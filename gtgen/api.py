"""The dataset as users' own code opens it: ``gtgen.open_dataset(path)``. It sits above
the stages (storage below, the trainer's torch view reached lazily), so no stage imports a later one.

    ds = gtgen.open_dataset("gtgen_ws/dataset.zarr")
    ds.splits["val"]                       # sample indices of the val split
    ds.schema["labels/micro/elevation_m"]  # dtype, shape, units, frame, fill, meaning
    ds.read("labels/micro/elevation_m", slice(0, 4))  # floats [m] (stored as packed integers)
    labels = ds.xarray("labels/micro")     # xarray.Dataset: sample (time) x x_m x y_m
    ds.cameras                             # the camera names, in the order of the images
    front, left, right, back = ds.images(0)  # sample 0's images decoded (H, W, 3) RGB (an X-Racer rig)
    ds.jpeg_files(0)                       # ... or their JPEG files as stored
    torch_ds = ds.torch("train")           # a PyTorch Dataset (gtgen.train.data.ShardDataset)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gtgen.storage.dataset import DatasetStore
from gtgen.storage.schema import DATASET, DatasetAttrs
from gtgen.storage.specs import ArraySpec


class Dataset:
    """A complete dataset store: its attributes, schema, splits, an xarray view per group
    and a PyTorch view; every read checked (a missing or damaged chunk is a GtgenError
    naming the array, its samples and the command that rebuilds the dataset)."""

    def __init__(self, store: DatasetStore) -> None:
        self.store = store
        self.path: Path = store.path
        self.attrs: DatasetAttrs = store.info
        self.n_samples: int = store.n_samples

    @property
    def zarr(self) -> Any:
        """The zarr group of the dataset, read through gtgen's checked store (packed arrays
        as their stored integers: ``scale_factor``, ``add_offset`` and ``_FillValue`` in
        their attributes; ``read`` and ``xarray`` give the floats)."""
        return self.store.group

    def read(self, path: str, rows: Any = None) -> np.ndarray:
        """Return array ``path`` whole or its ``rows`` (a slice or sorted indices), packed
        arrays as floats in their units (NaN where unset)."""
        return self.store.read(path, rows)

    @property
    def schema(self) -> dict[str, ArraySpec]:
        """Every array of the format by path: dtype, shape symbols, units, frame, fill, meaning
        (the tables of data_schema.md)."""
        return {s.path: s for s in DATASET.arrays}

    @property
    def splits(self) -> dict[str, np.ndarray]:
        """Sample indices per split name (``train``, ``val``, ``test``)."""
        return self.store.splits

    @property
    def cameras(self) -> list[str]:
        """The cameras' names, in the order of ``images`` and of the camera axis of
        ``inputs/*`` (empty: the drives had no camera, and the dataset holds no image)."""
        return self.store.cameras

    def images(self, k: int) -> list[np.ndarray]:
        """Return sample ``k``'s images decoded, one per camera (``cameras``' order), (H, W, 3)
        RGB uint8 at their stored size: rectified, so ``inputs/K`` of the sample projects
        into them as a pinhole."""
        return self.store.images(k)

    def jpeg_files(self, k: int) -> list[bytes]:
        """Return sample ``k``'s JPEG files as stored, one per camera (``cameras``' order)."""
        return self.store.jpeg_files(k)

    def xarray(self, group: str = "labels/micro") -> Any:
        """Return one group (``labels/micro``, ``labels/short``, ``xracer/<range>``,
        ``dem/<range>``, ``inputs``, ``meta``) as a lazy ``xarray.Dataset`` with coordinates:
        ``sample`` (time), ``x_m`` and ``y_m`` (cell centres of the target frame [m])."""
        return self.store.xarray(group)

    def torch(self, split: str | None = "train", preset: str = "tiny", config: dict | None = None, baselines: bool = True) -> Any:
        """Return a PyTorch ``Dataset`` of ``split`` (None: every sample) at the model sizes of
        ``preset`` (and a config layer over it), with the evaluation's baselines (X-Racer at t,
        the raw min-z grid) unless ``baselines`` is off: see ``gtgen.train.data.ShardDataset``."""
        from gtgen.config import load_config
        from gtgen.train.data import ShardDataset
        from gtgen.train.presets import preset_overrides

        cfg = load_config(None, preset_overrides(preset), *([config] if config else []))
        return ShardDataset(self.path, cfg.train, split=split, baselines=baselines)

    def __len__(self) -> int:
        return self.n_samples

    def __repr__(self) -> str:
        counts = ", ".join(f"{k} {len(v)}" for k, v in self.splits.items())
        return f"gtgen.Dataset('{self.path}', {self.n_samples} samples ({counts}), {len(self.attrs.drives)} drive(s))"


def open_dataset(path: str | Path) -> Dataset:
    """Open a complete dataset store, or raise ``gtgen.GtgenError`` saying why not."""
    return Dataset(DatasetStore(Path(path)))
