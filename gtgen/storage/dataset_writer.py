"""Writing the dataset store: :class:`ShardWriter` creates its arrays (packed ones with
their CF attributes, ``storage/packing.py``) and keeps the flat voxel points and the
rejection list; :func:`write_block` writes one shard of samples, packing float values at
the steps the arrays state."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.config import RANGES, PrecisionConfig, stored_config
from gtgen.errors import StoreError
from gtgen.runtime.progress import track
from gtgen.storage.chunks import Encoded, RowAppender, encode_row
from gtgen.storage.codecs import codec_of
from gtgen.storage.dataset import DatasetSample, DatasetStore
from gtgen.storage.packing import Packing, packing_for, packing_of
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
    qa_paths,
)
from gtgen.storage.shards import chunks_like_gtgen, copy_samples, sample_layout, samples_per_shard, shard_file, write_shard
from gtgen.storage.specs import row_shape
from gtgen.storage.stores import StoreWriter

REJECTED = tuple(s for s in DATASET.arrays if s.path.startswith("rejected/"))  # one row per rejected sample


class ShardWriter(StoreWriter):
    """Creates a dataset's arrays and keeps its flat voxel points and rejection list;
    per-sample arrays arrive as whole shards, from ``write_block`` (then ``add_block``)
    or from another dataset (``append_dataset``), so no shard is written twice.

    Arrays are created at ``max_samples``, grown if more come, and shrunk to the samples
    written on close. Packed arrays store their values at the steps of ``precision``
    (``shards.precision``); the QA grids (``schema.QA_GRIDS``) exist only for ``qa_ranges``
    (``shards.qa_ranges``).
    """

    fmt = DATASET

    def __init__(self, path: Path, max_samples: int, micro: int, short: int, cameras: int, jpeg_capacity: int,
                 scans: tuple[int, int] | None = None, precision: PrecisionConfig | None = None, qa_ranges: Any = ()) -> None:
        super().__init__(path)
        precision = precision or PrecisionConfig()
        self.packings: dict[str, Packing | None] = {}
        self.qa_ranges = tuple(qa_ranges)
        _LAYOUT.pop(str(path), None)  # a store made anew at a path seen before
        dims = {"n_m": micro, "n_s": short, "C": cameras, "B": jpeg_capacity}
        self.jpeg_capacity = jpeg_capacity
        if scans is not None:
            dims.update({"P_s": scans[0], "N_s": scans[1]})
        self.arrays: dict[str, Any] = {}
        K = SAMPLES_PER_SHARD
        left_out = set(qa_paths(tuple(r for r in RANGES if r not in qa_ranges)))
        for s in SAMPLE_ARRAYS + (CAMERA_ARRAYS if cameras else ()) + (SCAN_ARRAYS if scans is not None else ()):
            if s.path in left_out:
                continue
            inner = row_shape(s, dims)
            self.packings[s.path] = pk = packing_for(s, precision)
            self.arrays[s.path] = self.create(s.path, (max(max_samples, 1), *inner), chunks=(1, *inner), shards=(K, *inner), packing=pk)
        self._scan_dims = scans
        self.point_packing = packing_for(self.spec("inputs/voxel_points_m"), precision)
        self.points = self.create("inputs/voxel_points_m", (POINTS_PER_CHUNK, 3), chunks=(POINTS_PER_CHUNK, 3), packing=self.point_packing)
        self.rows = RowAppender(self.points)
        self.offsets = [0]
        self.n = 0
        self.rejected: list[dict[str, Any]] = []  # rows of the rejected/ arrays, by name

    def add_block(self, points: list[NDArray[np.float32]]) -> None:
        """Account for a whole shard of samples already written by ``write_block`` (in order)."""
        self._ensure(self.n + len(points))
        for p in points:
            self._append_points(np.asarray(p, np.float32).reshape(-1, 3))
            self.offsets.append(self.offsets[-1] + len(p))
        self.n += len(points)

    def _append_points(self, points: NDArray) -> None:
        """Append voxel points in the target frame [m] (packed as the array states)."""
        self.rows.append(points if self.point_packing is None else self.point_packing.pack(points, "inputs/voxel_points_m"))

    def _stored(self, path: str, values: NDArray) -> NDArray:
        """Return values of array ``path`` as it stores them (packed where it is)."""
        pk = self.packings.get(path)
        return values if pk is None else pk.pack(values, path)

    def append_dataset(self, src: DatasetStore, drive: int, label: str, split: int | None = None) -> int:
        """Append every sample of dataset ``src`` as drive index ``drive`` (all in split
        code ``split`` if given, else in the splits they have); return how many.

        Per-sample arrays move as encoded shard bytes where both layouts agree (see
        ``storage.shards.copy_samples``, which checks each shard file against ``src``'s
        manifest; a few arrays at a time, as file I/O releases the GIL), else they are
        decoded and re-encoded (packed ones unpacked with ``src``'s steps and packed with
        this store's). Voxel points go through the chunk appender, rejected
        samples into the rejection list.
        """
        from concurrent.futures import ThreadPoolExecutor

        S = src.n_samples
        off = self.n
        self._ensure(off + S)

        def one(p: str) -> None:
            if p.startswith("inputs/scan_") and src.scan_dims != self._scan_dims:
                return  # a drive without raw scans (or with another N-scan layout): its samples have none
            if p not in src.group:
                raise StoreError(f"dataset '{src.path}' has no array '{p}' (its shards.qa_ranges differ from this build's "
                                 f"{list(self.qa_ranges)}): rebuild it with the build's config")
            if not copy_samples(src.array(p), src.path, self.root, self.path, p, off, S, check=src.manifest.check):
                for a0 in range(0, S, SAMPLES_PER_SHARD):
                    self.arrays[p][off + a0 : off + min(a0 + SAMPLES_PER_SHARD, S)] = self._stored(p, src.read(p, slice(a0, a0 + SAMPLES_PER_SHARD)))

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
            self._append_points(pts(p0, min(p0 + step, n_pts)))
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
    they are. Values of packed arrays are floats, packed here at the steps the arrays'
    attributes state. Each shard file is assembled here (``direct``, see ``storage.shards``);
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
            write_shard(shard_file(path, p, start // K, 1 + len(m.row_shape)), [_inner_chunk(v, m, p) for v in values] + [None] * (K - len(values)))
            continue
        root = root or zarr.open_group(str(path), mode="r+")
        rows = np.stack([v.decode()[0] if isinstance(v, Encoded) else v for v in values])
        root[p][start : start + len(values)] = rows if m.packing is None else m.packing.pack(rows, p)


@dataclass(frozen=True)
class _Meta:
    dtype: np.dtype
    fill: object
    row_shape: tuple[int, ...]
    packing: Packing | None
    codec: str


_LAYOUT: dict[str, dict[str, tuple[_Meta, bool]]] = {}


def _block_layout(path: str) -> dict[str, tuple[_Meta, bool]]:
    """{array: (its dtype, fill, sample shape and packing, whether its shards can be assembled
    here)} for the per-sample arrays of the dataset at ``path`` (read once per process)."""
    if path not in _LAYOUT:
        import zarr

        _LAYOUT.clear()
        root = zarr.open_group(path, mode="r")
        layout = {}
        for s in tuple(sp for sp in SAMPLE_ARRAYS + CAMERA_ARRAYS + SCAN_ARRAYS if sp.path in root):
            arr = root[s.path]
            meta = sample_layout(arr)
            ok = meta is not None and samples_per_shard(meta) == SAMPLES_PER_SHARD and chunks_like_gtgen(meta, arr.dtype)
            meta_ = _Meta(np.dtype(arr.dtype), arr.fill_value, tuple(int(n) for n in arr.shape[1:]), packing_of(arr.attrs, arr.dtype),
                          (codec_of(meta["codecs"][0]["configuration"]["codecs"], arr.dtype) if meta else None) or "zstd")
            layout[s.path] = (meta_, ok)
        _LAYOUT[path] = layout
    return _LAYOUT[path]


def _inner_chunk(value: NDArray | Encoded, m: _Meta, path: str = "") -> bytes | memoryview | None:
    """Return the encoded inner chunk of one sample (None where it is all fill); a packed
    array's values are floats, packed here."""
    if isinstance(value, Encoded):
        if m.packing is None and value.shape == (1, *m.row_shape) and value.same_layout(m.dtype, m.fill, m.codec):
            return value.data
        value = value.decode()[0]
    if m.packing is not None:
        value = m.packing.pack(value, path)
    return encode_row(value, m.dtype, m.row_shape, m.fill, m.codec)
