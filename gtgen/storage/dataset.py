"""The dataset store (``gtgen dem-align``, ``gtgen build``): read by name through
:class:`DatasetStore`, written shard by shard through :class:`ShardWriter` and
:func:`write_block`. Arrays and units: ``schema.DATASET`` and data_schema.md."""

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
from gtgen.runtime.progress import track
from gtgen.storage.chunks import Encoded, RowAppender, encode_row
from gtgen.storage.schema import (
    CAMERA_ARRAYS,
    COORDS,
    DATASET,
    POINTS_PER_CHUNK,
    SAMPLE_ARRAYS,
    SAMPLES_PER_SHARD,
    SCAN_ARRAYS,
    TIME_ATTRS,
    DatasetAttrs,
)
from gtgen.storage.shards import chunks_like_gtgen, copy_samples, sample_layout, samples_per_shard, shard_file, write_shard
from gtgen.storage.specs import row_shape
from gtgen.storage.stores import Rows, Store, StoreWriter

GRID_KINDS = {"labels": ("elevation_m", "risk", "confidence", "region", "count", "last_dt_s"),
              "xracer": ("elevation_m", "risk", "confidence"), "dem": ("elevation_m",)}
SAMPLE_INPUTS = ("jpeg", "jpeg_nbytes", "K", "T_base_cam", "T_target_base", "raw_elevation_m")
REJECTED = tuple(s for s in DATASET.arrays if s.path.startswith("rejected/"))  # one row per rejected sample


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

    def grid(self, kind: str, rng: str, layer: str) -> Rows:
        """Return the reader of grid ``kind/rng/layer`` (``labels``, ``xracer``, ``dem``;
        ``reader[k]``: sample k's grid in its target frame)."""
        return self._rows(_grid_path(kind, rng, layer))

    def grids(self, kind: str, rng: str, layer: str, rows: Any) -> NDArray:
        """Return grid ``kind/rng/layer`` of samples ``rows`` (sorted) in one read."""
        return self.read(_grid_path(kind, rng, layer), rows)

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


class ShardWriter(StoreWriter):
    """Creates a dataset's arrays and keeps its flat voxel points and rejection list;
    per-sample arrays arrive as whole shards, from ``write_block`` (then ``add_block``)
    or from another dataset (``append_dataset``), so no shard is written twice.

    Arrays are created at ``max_samples``, grown if more come, and shrunk to the samples
    written on close.
    """

    fmt = DATASET

    def __init__(self, path: Path, max_samples: int, micro: int, short: int, cameras: int, jpeg_capacity: int,
                 scans: tuple[int, int] | None = None) -> None:
        super().__init__(path)
        _LAYOUT.pop(str(path), None)  # a store made anew at a path seen before
        dims = {"n_m": micro, "n_s": short, "C": cameras, "B": jpeg_capacity}
        self.jpeg_capacity = jpeg_capacity
        if scans is not None:
            dims.update({"P_s": scans[0], "N_s": scans[1]})
        self.arrays: dict[str, Any] = {}
        K = SAMPLES_PER_SHARD
        for s in SAMPLE_ARRAYS + (CAMERA_ARRAYS if cameras else ()) + (SCAN_ARRAYS if scans is not None else ()):
            inner = row_shape(s, dims)
            self.arrays[s.path] = self.create(s.path, (max(max_samples, 1), *inner), chunks=(1, *inner), shards=(K, *inner))
        self._scan_dims = scans
        self.points = self.create("inputs/voxel_points_m", (POINTS_PER_CHUNK, 3), chunks=(POINTS_PER_CHUNK, 3))
        self.rows = RowAppender(self.points)
        self.offsets = [0]
        self.n = 0
        self.rejected: list[dict[str, Any]] = []  # rows of the rejected/ arrays, by name

    def add_block(self, points: list[NDArray[np.float32]]) -> None:
        """Account for a whole shard of samples already written by ``write_block`` (in order)."""
        self._ensure(self.n + len(points))
        for p in points:
            self.rows.append(np.asarray(p, np.float32).reshape(-1, 3))
            self.offsets.append(self.offsets[-1] + len(p))
        self.n += len(points)

    def append_dataset(self, src: DatasetStore, drive: int, label: str, split: int | None = None) -> int:
        """Append every sample of dataset ``src`` as drive index ``drive`` (all in split
        code ``split`` if given, else in the splits they have); return how many.

        Per-sample arrays move as encoded shard bytes where both layouts agree (see
        ``storage.shards.copy_samples``, which checks each shard file against ``src``'s
        manifest; a few arrays at a time, as file I/O releases the GIL), else they are
        decoded and re-encoded. Voxel points go through the chunk appender, rejected
        samples into the rejection list.
        """
        from concurrent.futures import ThreadPoolExecutor

        S = src.n_samples
        off = self.n
        self._ensure(off + S)

        def one(p: str) -> None:
            if p.startswith("inputs/scan_") and src.scan_dims != self._scan_dims:
                return  # a drive without raw scans (or with another N-scan layout): its samples have none
            if not copy_samples(src.array(p), src.path, self.root, self.path, p, off, S, check=src.manifest.check):
                for a0 in range(0, S, SAMPLES_PER_SHARD):
                    self.arrays[p][off + a0 : off + min(a0 + SAMPLES_PER_SHARD, S)] = src.read(p, slice(a0, a0 + SAMPLES_PER_SHARD))

        with ThreadPoolExecutor(max_workers=4) as io:
            for _ in track(io.map(one, list(self.arrays)), label, total=len(self.arrays)):
                pass
        if S:
            self.arrays["meta/drive"][off : off + S] = np.full(S, drive, np.uint16)
            if split is not None:
                self.arrays["meta/split"][off : off + S] = np.full(S, split, np.uint8)
        voff = src.voxel_offsets()
        pts = src.voxel_points()
        n_pts, step = (int(voff[-1]) if len(voff) else 0), int(src.array("inputs/voxel_points_m").chunks[0])
        for p0 in range(0, n_pts, step):
            self.rows.append(pts(p0, min(p0 + step, n_pts)))
        self.offsets.extend((self.offsets[-1] + voff[1:]).tolist())
        self.n = off + S
        cols = {s.path.split("/")[1]: src.read(s.path) for s in REJECTED}
        for i in range(len(cols["t_ns"])):
            self.rejected.append({**{name: col[i] for name, col in cols.items()}, "drive": drive})
        return S

    def reject(self, t_ns: int, drive: int, reason: int, **qa: Any) -> None:
        """Record a rejected sample with what is known of it (``qa``: other rejected/ arrays
        by name, such as its ICP fitness and the placement ICP proposed)."""
        self.rejected.append({"t_ns": t_ns, "drive": drive, "reason": reason, **qa})

    def rejected_counts(self) -> dict[str, int]:
        """Return {reason name: rejected samples}."""
        return codes.reason_counts(np.array([r["reason"] for r in self.rejected], np.uint8))

    def split_counts(self) -> dict[str, int]:
        """Return {split name: samples} of the samples written so far."""
        split = self.arrays["meta/split"][: self.n] if self.n else np.zeros(0, np.uint8)
        return {codes.SPLITS[int(v)]: int((split == v).sum()) for v in np.unique(split)}

    def _ensure(self, n: int) -> None:
        """Grow the sample axis (metadata only) when more samples come than were expected."""
        cap = next(iter(self.arrays.values())).shape[0]
        if n > cap:
            new = max(n, 2 * cap)
            for arr in self.arrays.values():
                arr.resize((new, *arr.shape[1:]))

    def close(self, attrs: DatasetAttrs) -> int:
        """Write the last voxel points, shrink to the samples written, store attributes and
        the manifest (the store is complete); return S."""
        self.rows.close()
        for arr in self.arrays.values():
            arr.resize((self.n, *arr.shape[1:]))
        self.write("inputs/voxel_offsets", np.asarray(self.offsets, np.int64))
        rows = sorted(self.rejected, key=lambda r: (int(r["drive"]), int(r["t_ns"])))
        R = len(rows)
        for s in REJECTED:
            name, shape = s.path.split("/")[1], row_shape(s, {})
            fill = s.fill_value()
            col = np.array([np.broadcast_to(np.asarray(r.get(name, fill), s.dtype), shape) for r in rows], s.dtype).reshape((R, *shape))
            self.write(s.path, col)
        self._coordinates(attrs)
        self.root.attrs.update(attrs.model_dump(mode="json"))
        from gtgen.storage.integrity import write_manifest

        write_manifest(self.path)
        return self.n

    def _coordinates(self, attrs: DatasetAttrs) -> None:
        """Write the dimension coordinates (``schema.COORDS``): cell centres of each grid,
        and the sample times."""
        from gtgen.grids import cell_centers

        grids = stored_config(attrs.config, "the dataset being written").grids
        t = self.arrays["meta/t_ns"][:] if self.n else np.zeros(0, np.int64)
        for s in COORDS:
            group, leaf = s.path.rsplit("/", 1)
            if leaf == "sample":
                value, extra = t, TIME_ATTRS
            else:
                g = grids.get("micro" if group.endswith("micro") else "short")
                value, extra = cell_centers(g.size, g.resolution_m), {}
            self.write(s.path, value).attrs.update({"units": s.units, "long_name": s.doc, **extra})


def write_block(path: Path, start: int, samples: list[DatasetSample], direct: bool = True) -> None:
    """Write consecutive samples from index ``start`` (a whole shard) into the store at ``path``.

    Workers call this on their own shards, so no shard is written twice or concurrently.
    A value may be an :class:`~gtgen.storage.chunks.Encoded` chunk (for example a fused
    grid passed through unchanged): where the layouts agree its bytes go into the shard as
    they are. Each shard file is assembled here (``direct``, see ``storage.shards``);
    ``direct=False`` writes through zarr (the oracle), with the same values.
    """
    import zarr

    K = SAMPLES_PER_SHARD
    if start % K or len(samples) > K:
        raise ValueError(f"block of {len(samples)} samples at {start} is not one shard ({K} samples, aligned)")
    root = None
    arrays = [x.arrays() for x in samples]
    for p, (m, ok) in _block_layout(str(path)).items():
        values = [x[p] for x in arrays]
        if direct and ok:
            write_shard(shard_file(path, p, start // K, 1 + len(m.row_shape)), [_inner_chunk(v, m) for v in values] + [None] * (K - len(values)))
            continue
        root = root or zarr.open_group(str(path), mode="r+")
        root[p][start : start + len(values)] = np.stack([v.decode()[0] if isinstance(v, Encoded) else v for v in values])


@dataclass(frozen=True)
class _Meta:
    dtype: np.dtype
    fill: object
    row_shape: tuple[int, ...]


_LAYOUT: dict[str, dict[str, tuple[_Meta, bool]]] = {}


def _block_layout(path: str) -> dict[str, tuple[_Meta, bool]]:
    """{array: (its dtype, fill and sample shape, whether its shards can be assembled
    here)} for the per-sample arrays of the dataset at ``path`` (read once per process)."""
    if path not in _LAYOUT:
        import zarr

        _LAYOUT.clear()
        root = zarr.open_group(path, mode="r")
        layout = {}
        for s in SAMPLE_ARRAYS + tuple(sp for sp in CAMERA_ARRAYS + SCAN_ARRAYS if sp.path in root):
            arr = root[s.path]
            meta = sample_layout(arr)
            ok = meta is not None and samples_per_shard(meta) == SAMPLES_PER_SHARD and chunks_like_gtgen(meta, arr.dtype)
            layout[s.path] = (_Meta(np.dtype(arr.dtype), arr.fill_value, tuple(int(n) for n in arr.shape[1:])), ok)
        _LAYOUT[path] = layout
    return _LAYOUT[path]


def _inner_chunk(value: NDArray | Encoded, m: _Meta) -> bytes | memoryview | None:
    """Return the encoded inner chunk of one sample (None where it is all fill)."""
    if isinstance(value, Encoded):
        if value.shape == (1, *m.row_shape) and value.same_layout(m.dtype, m.fill):
            return value.data
        value = value.decode()[0]
    return encode_row(value, m.dtype, m.row_shape, m.fill)
