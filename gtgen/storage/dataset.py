"""The dataset store (``gtgen dem-align``, ``gtgen build``): read by name through
:class:`DatasetStore` (packed arrays as floats), one sample as :class:`DatasetSample`;
written by ``storage/dataset_writer.py``. Arrays and units: ``schema.DATASET`` and
data_schema.md."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.config import RANGES, GtgenConfig, stored_config
from gtgen.errors import StoreError
from gtgen.storage.schema import DATASET, DatasetAttrs, qa_paths
from gtgen.storage.stores import Rows, Store

GRID_KINDS = {"labels": ("elevation_m", "risk", "confidence", "region", "count", "last_dt_s"),
              "xracer": ("elevation_m", "risk", "confidence"), "dem": ("elevation_m",)}
SAMPLE_INPUTS = ("jpeg", "jpeg_nbytes", "K", "T_base_cam", "T_target_base", "raw_elevation_m")


def _grid_path(kind: str, rng: str, layer: str) -> str:
    if kind not in GRID_KINDS or layer not in GRID_KINDS[kind] or rng not in RANGES:
        raise KeyError(f"no dataset grid {kind}/{rng}/{layer}; kinds and layers: {GRID_KINDS}, ranges {list(RANGES)}")
    return f"{kind}/{rng}/{layer}"


def _leaf(group: str, name: str) -> str:
    path = f"{group}/{name}"
    DATASET.spec(path)  # KeyError for a name the format does not have
    return path


def jpeg_files(rows: NDArray[np.uint8], nbytes: NDArray) -> list[bytes]:
    """Return the JPEG files of one sample's padded rows (C, B) and lengths (C,)."""
    return [rows[c, : int(n)].tobytes() for c, n in enumerate(nbytes)]


class DatasetStore(Store):
    """A complete dataset store, read by name (see data_schema.md for every array)."""

    fmt = DATASET

    def __init__(self, path: Path) -> None:
        from pydantic import ValidationError

        super().__init__(path)
        try:
            self.info = DatasetAttrs.model_validate(self.attrs)
        except ValidationError as err:
            raise self.where.damaged(f"its attributes are not a dataset's ({err.errors()[0]['loc']})") from err

    @property
    def n_samples(self) -> int:
        """Samples (kept) of the dataset."""
        return self.shape("meta/t_ns")[0]

    @cached_property
    def config(self) -> GtgenConfig:
        """The config the dataset was built with (its train section left out)."""
        return stored_config(self.info.config, f"dataset '{self.path}'")

    def size(self, rng: str) -> int:
        """Return the cells per side of range ``rng``'s grids."""
        return self.shape(_grid_path("labels", rng, "region"))[1]

    @property
    def cameras(self) -> list[str]:
        """The cameras' names, in the order of the image axis (none: the drives had no camera)."""
        return list(self.info.cameras)

    @property
    def jpeg_capacity(self) -> int:
        """Bytes of the zero-padded row holding each stored JPEG file (B; 0 without cameras)."""
        return self.shape("inputs/jpeg")[2] if self.cameras else 0

    def jpeg_bytes(self) -> NDArray[np.int64]:
        """Return the length of every stored JPEG file (S, C) [bytes]."""
        if not self.n_samples or not self.cameras:
            return np.zeros((self.n_samples if self.cameras else 0, len(self.cameras)), np.int64)
        return self.read("inputs/jpeg_nbytes").astype(np.int64)

    def jpeg_files(self, k: int) -> list[bytes]:
        """Return sample ``k``'s JPEG files as stored, one per camera (``cameras``' order)."""
        if not self.cameras:
            return []
        return jpeg_files(self.inputs("jpeg")[k], self.inputs("jpeg_nbytes")[k])

    def images(self, k: int) -> list[NDArray[np.uint8]]:
        """Return sample ``k``'s images decoded (H, W, 3) RGB, one per camera, at the size of
        their JPEG (the size ``inputs/K`` is for)."""
        from gtgen.bag.decode.image import decode_file

        return [decode_file(f) for f in self.jpeg_files(k)]

    def meta(self, name: str, rows: Any = None) -> NDArray:
        """Return per-sample metadata ``name`` (``meta/<name>`` of data_schema.md), whole or ``rows``."""
        path = _leaf("meta", name)
        if not self.n_samples:  # an empty sharded array has no chunk to read
            return np.zeros((0, *self.shape(path)[1:]), self.array(path).dtype)
        return self.read(path, rows)

    def rejected(self, name: str) -> NDArray:
        """Return column ``name`` of the rejected samples (``rejected/<name>``)."""
        return self.read(_leaf("rejected", name))

    @property
    def splits(self) -> dict[str, NDArray[np.int64]]:
        """Sample indices per split name."""
        split = self.meta("split")
        return {name: np.nonzero(split == code)[0] for code, name in codes.SPLITS.items()}

    def has_grid(self, kind: str, rng: str, layer: str) -> bool:
        """Whether the dataset stores grid ``kind/rng/layer`` (a QA grid only for the ranges
        of its ``shards.qa_ranges``)."""
        path = _grid_path(kind, rng, layer)
        return path not in qa_paths() or rng in self.config.shards.qa_ranges

    def _stored_grid(self, kind: str, rng: str, layer: str) -> str:
        path = _grid_path(kind, rng, layer)
        if not self.has_grid(kind, rng, layer):
            raise StoreError(f"dataset '{self.path}' does not store the QA grid '{path}' (shards.qa_ranges: "
                             f"{self.config.shards.qa_ranges}); rebuild it with shards.qa_ranges: [micro, short] in --config "
                             "('gtgen dem-align --overwrite') to have it")
        return path

    def grid(self, kind: str, rng: str, layer: str) -> Rows:
        """Return the reader of grid ``kind/rng/layer`` (``labels``, ``xracer``, ``dem``;
        ``reader[k]``: sample k's grid in its target frame, as floats)."""
        return self._rows(self._stored_grid(kind, rng, layer))

    def grids(self, kind: str, rng: str, layer: str, rows: Any) -> NDArray:
        """Return grid ``kind/rng/layer`` of samples ``rows`` (sorted) in one read."""
        return self.read(self._stored_grid(kind, rng, layer), rows)

    def inputs(self, name: str) -> Rows:
        """Return the reader of per-sample input ``name`` (``SAMPLE_INPUTS``)."""
        if name not in SAMPLE_INPUTS:
            raise KeyError(f"input {name!r} unknown; expected one of {list(SAMPLE_INPUTS)}")
        return self._rows(f"inputs/{name}")

    def input_rows(self, name: str, rows: Any) -> NDArray:
        """Return per-sample input ``name`` of samples ``rows`` (sorted) in one read."""
        if name not in SAMPLE_INPUTS:
            raise KeyError(f"input {name!r} unknown; expected one of {list(SAMPLE_INPUTS)}")
        return self.read(f"inputs/{name}", rows)

    @cached_property
    def has_scans(self) -> bool:
        """Whether the dataset holds raw lidar scans (arrays ``inputs/scan*``): the source of
        the N-scan point input (``train.geometry: scans``)."""
        return any(name.startswith("scan") for name in self.group["inputs"].array_keys())

    @property
    def scan_dims(self) -> tuple[int, int] | None:
        """(P_s points, N_s scans) of the stored N-scan input, None without raw scans."""
        if not self.has_scans:
            return None
        return self.shape("inputs/scan_points_m")[1], self.shape("inputs/scan_counts")[1]

    def scan_input(self) -> tuple[Rows, Rows]:
        """Return the readers of the N-scan input: points (P_s, 3) in the target frame [m]
        (NaN after the last) and, per age a, the points of the scans of age < a + 1 (N_s,)."""
        return self._rows("inputs/scan_points_m"), self._rows("inputs/scan_counts")

    def scan_counts(self) -> NDArray[np.int32]:
        """Return (S, N_s): every sample's points of the scans of age < a + 1, read at once."""
        return self.read("inputs/scan_counts")

    def voxel_offsets(self) -> NDArray[np.int64]:
        """Return (S + 1,): sample s owns voxel points offsets[s]:offsets[s + 1]."""
        return self.read("inputs/voxel_offsets")

    def voxel_points(self) -> Callable[[int, int], NDArray[np.float32]]:
        """Return ``f(a, b)``: voxel points a to b in their sample's target frame (P, 3) [m]."""
        return self.ranges("inputs/voxel_points_m")

    def xarray(self, group: str) -> Any:
        """Return one group as a lazy ``xarray.Dataset`` (coordinates sample, x_m, y_m), read through the checked store."""
        import xarray as xr

        return xr.open_zarr(self.group.store, group=group, consolidated=False, zarr_format=3)

    def _rows(self, path: str) -> Rows:
        cache = self.__dict__.setdefault("_readers", {})
        if path not in cache:
            cache[path] = self.rows(path)
        return cache[path]


@dataclass
class DatasetSample:
    """One sample as the dataset stores it: per range its label layers, X-Racer's layers and
    the aligned DEM (grids as values or as stored chunks, ``chunks.Encoded``), its inputs
    (``SAMPLE_INPUTS``) and metadata (``meta/<name>``), by name."""

    labels: dict[str, dict[str, Any]]
    xracer: dict[str, dict[str, Any]]
    dem: dict[str, NDArray]
    inputs: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def arrays(self) -> dict[str, Any]:
        """Return every per-sample array's value by its path in the store."""
        out: dict[str, Any] = {}
        for r in RANGES:
            out.update({_grid_path("labels", r, k): v for k, v in self.labels[r].items()})
            out.update({_grid_path("xracer", r, k): v for k, v in self.xracer[r].items()})
            out[_grid_path("dem", r, "elevation_m")] = self.dem[r]
        out.update({f"inputs/{k}": v for k, v in self.inputs.items()})
        out.update({_leaf("meta", k): v for k, v in self.meta.items()})
        return out
