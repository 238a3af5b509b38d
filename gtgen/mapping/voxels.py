"""The voxel map made from lidar (``topics.voxel_map: null``): the voxels of edge
``mapping.voxel_m`` that a point fell in during the last ``memory_s``, kept as a sorted
array of packed voxel keys with the stamp each was last seen; voxels beyond the short
grid around the vehicle are dropped, so the set stays bounded whatever the drive's length."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.geometry import all_columns

WINDOW_EVERY = 10  # sweeps between the checks of which voxels left the window
BIAS = 1 << 20  # keys are offset by this before packing: +-2^20 voxels (420 km at 0.4 m) per axis


def pack3(k: NDArray[np.int64]) -> NDArray[np.int64]:
    """Return one int64 key per voxel index row (kx, ky, kz), each within +-2^20."""
    b = k + BIAS
    return (b[:, 0] << 42) | (b[:, 1] << 21) | b[:, 2]


def unpack3(key: NDArray[np.int64]) -> NDArray[np.int64]:
    """Return the voxel index rows (N, 3) of packed keys."""
    m = (1 << 21) - 1
    return np.column_stack([key >> 42, (key >> 21) & m, key & m]) - BIAS


class VoxelMemory:
    """The voxels seen in the last ``memory_s`` within ``half_m`` of the vehicle."""

    def __init__(self, voxel_m: float, memory_s: float, half_m: float) -> None:
        self.voxel_m, self.memory_ns, self.half_m = voxel_m, int(memory_s * 1e9), half_m
        self.key = np.zeros(0, np.int64)
        self.t = np.zeros(0, np.int64)
        self._adds = 0

    def add(self, pts_odom: NDArray, center_xy: NDArray, t_ns: int) -> None:
        """Add one sweep's points (N, 3) in odom, taken with the vehicle at ``center_xy``:
        voxels seen again get the new stamp, new ones are inserted in key order (no sort of
        the whole set); voxels older than ``memory_s`` or out of the window are dropped."""
        near = all_columns(np.abs(pts_odom[:, :2] - center_xy[:2]) < self.half_m)
        k = np.floor(pts_odom[near] / self.voxel_m).astype(np.int64)
        if np.any(np.abs(k) >= BIAS):
            raise ValueError(f"a point lies beyond {BIAS * self.voxel_m / 1000:.0f} km of the odom origin")
        new = np.unique(pack3(k))
        at = np.searchsorted(self.key, new)
        hit = np.zeros(len(new), bool)
        if len(self.key):
            hit = self.key[np.minimum(at, len(self.key) - 1)] == new
        self.t[at[hit]] = t_ns
        self.key = np.insert(self.key, at[~hit], new[~hit])
        self.t = np.insert(self.t, at[~hit], t_ns)
        keep = t_ns - self.t <= self.memory_ns
        self._adds += 1
        if self._adds % WINDOW_EVERY == 0:  # out of the window: checked now and then (points() checks always)
            keep &= self._inside(center_xy)
        if not keep.all():
            self.key, self.t = self.key[keep], self.t[keep]

    def _inside(self, center_xy: NDArray) -> NDArray[np.bool_]:
        c = (unpack3(self.key)[:, :2] + 0.5) * self.voxel_m
        return all_columns(np.abs(c - center_xy[:2]) < self.half_m)

    def points(self, t_ns: int, center_xy: NDArray) -> NDArray[np.float32]:
        """Return the centres (N, 3) in odom of the voxels seen in the ``memory_s`` before
        ``t_ns`` within the window around ``center_xy``."""
        live = (t_ns - self.t <= self.memory_ns) & (self.t <= t_ns) & self._inside(center_xy)
        return ((unpack3(self.key[live]) + 0.5) * self.voxel_m).astype(np.float32)
