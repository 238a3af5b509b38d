"""Sweeps in, maps out: the mapping of one drive's lidar, in time order.

``Mapper.add`` takes one sweep (points in the base frame at its stamp, with the sensor's
origin and the base's pose in odom): it masks the vehicle's own body, puts the points in
odom and adds them to each range's rolling cells. ``Mapper.map`` makes a range's map at a
time, centred on the vehicle and aligned with odom (yaw 0), as the stack's GridMaps are
read by extract (``GridMapData``'s layout).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.config import RANGES, GtgenConfig
from gtgen.geometry import all_columns
from gtgen.mapping.cells import RollingCells
from gtgen.mapping.layers import MapLayers, layers
from gtgen.mapping.voxels import VoxelMemory


def body_mask(points_base: NDArray, cfg: GtgenConfig) -> NDArray[np.bool_]:
    """Return which points (N, 3) in the base frame lie on the vehicle's body box."""
    m = cfg.mapping
    inside = np.ones(len(points_base), bool)
    for a, (lo, hi) in enumerate((m.body_x_m, m.body_y_m, m.body_z_m)):
        inside &= (points_base[:, a] >= lo) & (points_base[:, a] <= hi)
    return inside


class Mapper:
    """The rolling cells of every range, fed sweep by sweep."""

    def __init__(self, cfg: GtgenConfig, ranges: tuple[str, ...] = RANGES, voxels: bool = False) -> None:
        self.cfg = cfg
        self.cells = {r: RollingCells(cfg.grids.get(r).size, cfg.grids.get(r).resolution_m, cfg.mapping) for r in ranges}
        half = 0.5 * max(cfg.grids.micro.length_m, cfg.grids.short.length_m)
        self.voxels = VoxelMemory(cfg.mapping.voxel_m, cfg.mapping.memory_s, half) if voxels else None
        self.t_ns = np.iinfo(np.int64).min

    def add(self, points_base: NDArray, origin_base: NDArray, T_odom_base: NDArray, t_ns: int) -> None:
        """Add a sweep: ``points_base`` (N, 3) in the base frame at ``t_ns``, the sensor at
        ``origin_base`` (3,), the base at ``T_odom_base`` (4, 4). Sweeps come in time order."""
        self.add_odom(*self.to_odom(points_base, origin_base, T_odom_base), T_odom_base[:2, 3], t_ns)

    def to_odom(self, points_base: NDArray, origin_base: NDArray, T_odom_base: NDArray) -> tuple[NDArray, NDArray]:
        """Return a sweep's points in odom (the body masked out, and those higher above the
        base than ``mapping.max_height_m``) and their ranges from the sensor."""
        p = np.asarray(points_base, np.float64)
        p = np.compress(~body_mask(p, self.cfg) & all_columns(np.isfinite(p)), p, axis=0)
        rng = np.linalg.norm(p - np.asarray(origin_base, np.float64)[None, :], axis=1).astype(np.float32)
        odom = p @ T_odom_base[:3, :3].T + T_odom_base[:3, 3]
        top = self.cfg.mapping.max_height_m
        if top is not None:  # above the base in odom's z (up), whatever the base's roll and pitch
            low = odom[:, 2] - T_odom_base[2, 3] <= top
            odom, rng = odom[low], rng[low]
        return odom, rng

    def add_odom(self, odom: NDArray, rng: NDArray, center_xy: NDArray, t_ns: int) -> None:
        """Add points already in odom (``to_odom`` of one sweep or of several merged, stamped
        ``t_ns``), taken with the vehicle at ``center_xy``."""
        if t_ns < self.t_ns:
            raise ValueError(f"sweep at {t_ns} ns comes after one at {self.t_ns} ns; sweeps must come in time order")
        self.t_ns = t_ns
        for c in self.cells.values():
            c.add(odom, rng, center_xy, t_ns)
        if self.voxels is not None:
            self.voxels.add(odom, center_xy, t_ns)

    def map(self, rng: str, center_xy: NDArray, t_ns: int) -> MapLayers:
        """Return range ``rng``'s map at ``t_ns``: the grid's cells around ``center_xy`` (snapped
        to the cells), from what the sweeps up to then saw."""
        c = self.cells[rng]
        crop = c.crop(center_xy, c.n, t_ns)
        center = (crop["origin"] + c.n / 2) * c.res
        return layers(crop, self.cfg.mapping, c.res, center)

    def voxel_points(self, t_ns: int, center_xy: NDArray) -> NDArray[np.float32]:
        """Return the voxel map at ``t_ns`` around ``center_xy``: voxel centres (N, 3) in odom."""
        if self.voxels is None:
            raise ValueError("this Mapper keeps no voxels (voxels=False)")
        return self.voxels.points(t_ns, center_xy)


def map_scan(points: NDArray, origin: NDArray, sensor_height_m: float, cfg: GtgenConfig, t_ns: int = 0) -> dict[str, MapLayers]:
    """Return every range's map of one scan without poses: ``points`` (N, 3) in a local
    frame, the sensor at ``origin`` (x, y, z) in it, mounted ``sensor_height_m`` above the
    vehicle's base (the body box of ``mapping`` is about the base). A bag with one scan and
    no TF maps this way; a drive needs poses (odometry or TF odom -> base) to be mapped."""
    mp = Mapper(cfg)
    o = np.asarray(origin, np.float64)
    base = o - np.array([0.0, 0.0, sensor_height_m])
    T = np.eye(4)
    T[:3, 3] = base
    mp.add(np.asarray(points, np.float64) - base, o - base, T, t_ns)
    return {r: mp.map(r, base[:2], t_ns) for r in mp.cells}
