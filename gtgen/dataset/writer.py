"""Write a dataset store shard by shard (whole shards, so no shard is rewritten)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.runtime.progress import track
from gtgen.storage.chunks import Encoded, RowAppender, compressors, encode_row
from gtgen.storage.schema import (
    COORDS,
    DATASET,
    TIME_ATTRS,
    POINTS_PER_CHUNK,
    SAMPLE_ARRAYS,
    SAMPLES_PER_SHARD,
    DatasetAttrs,
)
from gtgen.storage.shards import (
    chunks_like_gtgen,
    copy_samples,
    sample_layout,
    samples_per_shard,
    shard_file,
    write_shard,
)
from gtgen.storage.specs import dimension_names, row_shape
from gtgen.storage.stores import create_group

REJECTED = tuple(s for s in DATASET.arrays if s.path.startswith("rejected/"))  # one row per rejected sample


class ShardWriter:
    """Creates a dataset's arrays and keeps its flat voxel points and rejection list;
    per-sample arrays arrive as whole shards, from ``write_block`` (then ``add_block``)
    or from another dataset (``append_dataset``), so no shard is written twice.

    Arrays are created at ``max_samples``, grown if more come, and shrunk to the samples
    written on close.
    """

    def __init__(self, path: Path, max_samples: int, micro: int, short: int, image_hw: tuple[int, int]) -> None:
        self.root = create_group(path)
        self.path = path
        _LAYOUT.pop(str(path), None)  # a store made anew at a path seen before
        dims = {"n_m": micro, "n_s": short, "H": image_hw[0], "W": image_hw[1]}
        self.arrays: dict[str, Any] = {}
        K = SAMPLES_PER_SHARD
        for s in SAMPLE_ARRAYS:
            inner = row_shape(s, dims)
            self.arrays[s.path] = self.root.create_array(
                s.path, shape=(max(max_samples, 1), *inner), dtype=s.dtype, chunks=(1, *inner), shards=(K, *inner),
                fill_value=s.fill_value(), compressors=compressors(), dimension_names=dimension_names(s),
            )
        self.points = self.root.create_array("inputs/voxel_points_m", shape=(POINTS_PER_CHUNK, 3), dtype="float32",
                                             chunks=(POINTS_PER_CHUNK, 3), fill_value=0.0, compressors=compressors(),
                                             dimension_names=dimension_names(DATASET.spec("inputs/voxel_points_m")))
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

    def append_dataset(self, src: Any, src_path: Path, drive: int, label: str) -> int:
        """Append every sample of the dataset store ``src`` (a zarr group opened at
        ``src_path``) as drive index ``drive``; return how many.

        Per-sample arrays move as encoded shard bytes where both layouts agree (see
        ``storage.shards.copy_samples``; a few arrays at a time, as file I/O releases the
        GIL), else they are decoded and re-encoded. Voxel points go through the chunk
        appender, rejected samples into the rejection list.
        """
        from concurrent.futures import ThreadPoolExecutor

        S = int(src["meta/t_ns"].shape[0])
        off = self.n
        self._ensure(off + S)

        def one(p: str) -> None:
            if not copy_samples(src, src_path, self.root, self.path, p, off, S):
                for a0 in range(0, S, SAMPLES_PER_SHARD):
                    self.arrays[p][off + a0 : off + min(a0 + SAMPLES_PER_SHARD, S)] = src[p][a0 : a0 + SAMPLES_PER_SHARD]

        with ThreadPoolExecutor(max_workers=4) as io:
            for _ in track(io.map(one, list(self.arrays)), label, total=len(self.arrays)):
                pass
        if S:
            self.arrays["meta/drive"][off : off + S] = np.full(S, drive, np.uint16)
        voff = src["inputs/voxel_offsets"][:]
        pts = src["inputs/voxel_points_m"]
        n_pts, step = (int(voff[-1]) if len(voff) else 0), int(pts.chunks[0])
        for p0 in range(0, n_pts, step):
            self.rows.append(pts[p0 : min(p0 + step, n_pts)])
        self.offsets.extend((self.offsets[-1] + voff[1:]).tolist())
        self.n = off + S
        cols = {s.path.split("/")[1]: src[s.path][:] for s in REJECTED}
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

    def _ensure(self, n: int) -> None:
        """Grow the sample axis (metadata only) when more samples come than were expected."""
        cap = next(iter(self.arrays.values())).shape[0]
        if n > cap:
            new = max(n, 2 * cap)
            for arr in self.arrays.values():
                arr.resize((new, *arr.shape[1:]))

    def close(self, attrs: DatasetAttrs) -> int:
        """Write the last voxel points, shrink to the samples written, store attributes; return S."""
        self.rows.close()
        for arr in self.arrays.values():
            arr.resize((self.n, *arr.shape[1:]))
        off = self.root.create_array("inputs/voxel_offsets", shape=(self.n + 1,), dtype="int64",
                                     chunks=(max(self.n + 1, 1),), fill_value=0,
                                     dimension_names=dimension_names(DATASET.spec("inputs/voxel_offsets")))
        off[:] = np.asarray(self.offsets, np.int64)
        rows = sorted(self.rejected, key=lambda r: (int(r["drive"]), int(r["t_ns"])))
        R = len(rows)
        for s in REJECTED:
            name, shape = s.path.split("/")[1], row_shape(s, {})
            fill = s.fill_value()
            col = np.array([np.broadcast_to(np.asarray(r.get(name, fill), s.dtype), shape) for r in rows], s.dtype).reshape((R, *shape))
            arr = self.root.create_array(s.path, shape=(R, *shape), dtype=s.dtype, chunks=(max(R, 1), *shape), fill_value=fill,
                                         dimension_names=dimension_names(s))
            if R:
                arr[:] = col
        self._coordinates(attrs)
        self.root.attrs.update(attrs.model_dump(mode="json"))
        return self.n

    def _coordinates(self, attrs: DatasetAttrs) -> None:
        """Write the dimension coordinates (``schema.COORDS``): cell centres of each grid,
        and the sample times."""
        from gtgen.config import stored_config
        from gtgen.geometry import cell_centers

        grids = stored_config(attrs.config, "the dataset being written").grids
        t = self.root["meta/t_ns"][:] if self.n else np.zeros(0, np.int64)
        for s in COORDS:
            group, leaf = s.path.rsplit("/", 1)
            if leaf == "sample":
                value, extra = t, TIME_ATTRS
            else:
                g = grids.get("micro" if group.endswith("micro") else "short")
                value, extra = cell_centers(g.size, g.resolution_m), {}
            arr = self.root.create_array(s.path, shape=value.shape, dtype=s.dtype, chunks=(max(len(value), 1),), fill_value=0,
                                         dimension_names=dimension_names(s), attributes={"units": s.units, "long_name": s.doc, **extra})
            if len(value):
                arr[:] = value


def write_block(path: Path, start: int, samples: list[dict[str, NDArray | Encoded]], direct: bool = True) -> None:
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
    for p, (m, ok) in _block_layout(str(path)).items():
        values = [x[p] for x in samples]
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
        for s in SAMPLE_ARRAYS:
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
