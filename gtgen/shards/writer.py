"""Write a dataset store shard by shard (whole shards, so no shard is rewritten)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen.format import compressors, dimension_names
from gtgen.shards import schema as sc


class ShardWriter:
    """Buffers samples and writes each shard of ``SAMPLES_PER_SHARD`` samples once.

    Arrays are created at ``max_samples``, grown if more come, and shrunk to the samples
    written on close.
    """

    def __init__(self, path: Path, max_samples: int, micro: int, short: int, image_hw: tuple[int, int]) -> None:
        import zarr

        self.root = zarr.open_group(str(path), mode="w")
        self.path = path
        dims = {"S": max(max_samples, 1), "n_m": micro, "n_s": short, "H": image_hw[0], "W": image_hw[1]}
        self.arrays: dict[str, Any] = {}
        K = sc.SAMPLES_PER_SHARD
        for s in sc.DATASET_ARRAYS:
            if s.path.startswith(("rejected/", "inputs/voxel_")):
                continue
            inner = [int(dims[d.strip()]) if d.strip() in dims else int(d) for d in s.shape.strip("()").split(",") if d.strip()][1:]
            shape = (dims["S"], *inner)
            self.arrays[s.path] = self.root.create_array(
                s.path, shape=shape, dtype=s.dtype, chunks=(1, *inner), shards=(K, *inner), fill_value=s.fill_value(), compressors=compressors(),
                dimension_names=dimension_names(s),
            )
        self.points = self.root.create_array("inputs/voxel_points_m", shape=(0, 3), dtype="float32",
                                             chunks=(sc.POINTS_PER_CHUNK, 3), fill_value=0.0, compressors=compressors(),
                                             dimension_names=dimension_names(sc.spec("inputs/voxel_points_m")))
        self.offsets = [0]
        self.buffer: list[dict[str, NDArray]] = []
        self.n = 0
        self.rejected: list[tuple[int, int, int, float, float]] = []

    def add(self, sample: dict[str, NDArray], points: NDArray[np.float32]) -> None:
        """Queue one sample (every non-voxel per-sample array) and its voxel points."""
        missing = set(self.arrays) - set(sample)
        if missing:
            raise KeyError(f"sample lacks arrays {sorted(missing)}")
        self.buffer.append(sample)
        if len(points):
            self.points.append(np.asarray(points, np.float32).reshape(-1, 3), axis=0)
        self.offsets.append(self.offsets[-1] + len(points))
        if len(self.buffer) == sc.SAMPLES_PER_SHARD:
            self._flush()

    def add_block(self, points: list[NDArray[np.float32]]) -> None:
        """Account for a whole shard of samples already written by ``write_block`` (in order)."""
        if self.buffer:
            raise RuntimeError("add_block after add: blocks must stay shard-aligned")
        self._ensure(self.n + len(points))
        for p in points:
            if len(p):
                self.points.append(np.asarray(p, np.float32).reshape(-1, 3), axis=0)
            self.offsets.append(self.offsets[-1] + len(p))
        self.n += len(points)

    def reject(self, t_ns: int, drive: int, reason: int, fitness: float = float("nan"), rmse: float = float("nan")) -> None:
        """Record a rejected sample."""
        self.rejected.append((t_ns, drive, reason, fitness, rmse))

    def _ensure(self, n: int) -> None:
        """Grow the sample axis (metadata only) when more samples come than were expected."""
        cap = next(iter(self.arrays.values())).shape[0]
        if n > cap:
            new = max(n, 2 * cap)
            for arr in self.arrays.values():
                arr.resize((new, *arr.shape[1:]))

    def _flush(self) -> None:
        if not self.buffer:
            return
        a, b = self.n, self.n + len(self.buffer)
        self._ensure(b)
        for name, arr in self.arrays.items():
            arr[a:b] = np.stack([s[name] for s in self.buffer])
        self.n = b
        self.buffer = []

    def close(self, attrs: dict[str, Any]) -> int:
        """Write what is buffered, shrink to the samples written, store attributes; return S."""
        self._flush()
        for arr in self.arrays.values():
            arr.resize((self.n, *arr.shape[1:]))
        off = self.root.create_array("inputs/voxel_offsets", shape=(self.n + 1,), dtype="int64",
                                     chunks=(max(self.n + 1, 1),), fill_value=0,
                                     dimension_names=dimension_names(sc.spec("inputs/voxel_offsets")))
        off[:] = np.asarray(self.offsets, np.int64)
        R = len(self.rejected)
        rej = list(zip(*self.rejected)) if R else [[] for _ in range(5)]
        for (name, dtype), col in zip((("t_ns", "int64"), ("drive", "uint16"), ("reason", "uint8"), ("icp_fitness", "float32"), ("icp_rmse_m", "float32")), rej):
            s = sc.spec(f"rejected/{name}")
            arr = self.root.create_array(s.path, shape=(R,), dtype=dtype, chunks=(max(R, 1),), fill_value=s.fill_value(),
                                         dimension_names=dimension_names(s))
            if R:
                arr[:] = np.asarray(col, dtype=dtype)
        self.root.attrs.update(attrs)
        return self.n


def write_block(path: Path, start: int, samples: list[dict[str, NDArray]]) -> None:
    """Write consecutive samples from index ``start`` (a whole shard) into the store at ``path``.

    Workers call this on their own shards, so no shard is written twice or concurrently.
    """
    import zarr

    if start % sc.SAMPLES_PER_SHARD:
        raise ValueError(f"block start {start} is not shard-aligned ({sc.SAMPLES_PER_SHARD})")
    root = zarr.open_group(str(path), mode="r+")
    for s in sc.DATASET_ARRAYS:
        if s.path.startswith(("rejected/", "inputs/voxel_")):
            continue
        root[s.path][start : start + len(samples)] = np.stack([x[s.path] for x in samples])
