"""Per-cell statistics of the recent lidar points on a world-fixed grid that rolls with the vehicle.

The grid's cells are fixed in odom (cell ``(kx, ky)`` spans ``[kx r, (kx + 1) r)`` in x);
their statistics live in a ring buffer of ``n x n`` slots, slot ``(kx mod n, ky mod n)``,
each tagged with the cell it holds. A point beyond the ``n x n`` window centred on the
vehicle is not added, so a window never holds two cells in one slot; a slot is reset when
a point of another cell, or the first point after ``memory_s`` of silence, lands in it
(elevation_mapping's circular buffer, with lazy resets instead of a shift).

A cell keeps: its lowest point ``zmin``; the sum and count of its points within
``ground_band_m`` of ``zmin`` (the ground: vegetation and overhangs above the band stay
out, a lower surface seen later, through a gap in the leaves, restarts the band); the
highest point at most ``overhang_m`` above ``zmin`` (the top: obstacles and vegetation,
not the branches the vehicle passes under); its closest view range and its latest stamp.
A cell coarser than ``cover_cell_m`` also keeps that top per sub-cell of about that edge
(``subtop``, -inf where unseen), so its layers can tell an obstacle that covers the cell
from one that only crosses its corner.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.config import MappingConfig

NO_CELL = np.iinfo(np.int64).min


def cell_keys(xy: NDArray, res: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Return the integer cell indices (kx, ky) of points ``xy`` (N, 2) on a grid of edge ``res``."""
    k = np.floor(xy / res).astype(np.int64)
    return k[:, 0], k[:, 1]


def pack(kx: NDArray[np.int64], ky: NDArray[np.int64]) -> NDArray[np.int64]:
    """Return one int64 key per cell (kx, ky), both within +-2^31."""
    return (kx << 32) ^ (ky & 0xFFFFFFFF)


class RollingCells:
    """The cell statistics of one grid (``n`` cells a side of edge ``res`` [m])."""

    def __init__(self, n: int, res: float, cfg: MappingConfig) -> None:
        self.n, self.res, self.cfg = n, res, cfg
        self.sub = cfg.sub_cells(res)
        m = n * n
        # the top per sub-cell (sub x sub of them, row-major along x then y) of a coarse cell
        self.subtop = np.full((m, self.sub * self.sub), -np.inf, np.float32) if self.sub > 1 else None
        self.key = np.full(m, NO_CELL, np.int64)
        self.zmin = np.full(m, np.inf, np.float64)
        self.gsum = np.zeros(m, np.float64)
        self.gn = np.zeros(m, np.int64)
        self.top = np.full(m, -np.inf, np.float64)
        self.rmin = np.full(m, np.inf, np.float32)
        self.t_last = np.zeros(m, np.int64)

    def window(self, center_xy: NDArray) -> tuple[int, int]:
        """Return the lowest cell indices (kx0, ky0) of the n x n window centred on ``center_xy``."""
        c = np.floor(np.asarray(center_xy, np.float64)[:2] / self.res).astype(np.int64)
        return int(c[0]) - self.n // 2, int(c[1]) - self.n // 2

    def slots(self, kx: NDArray[np.int64], ky: NDArray[np.int64]) -> NDArray[np.int64]:
        """Return the ring-buffer slot of cells (kx, ky)."""
        return np.mod(kx, self.n) * self.n + np.mod(ky, self.n)

    def add(self, pts: NDArray, rng: NDArray, center_xy: NDArray, t_ns: int) -> None:
        """Add one sweep's points ``pts`` (N, 3) in odom, with their ranges from the sensor
        ``rng`` (N,), taken with the vehicle at ``center_xy`` at ``t_ns``."""
        kx, ky = cell_keys(pts[:, :2], self.res)
        x0, y0 = self.window(center_xy)
        inside = (kx >= x0) & (kx < x0 + self.n) & (ky >= y0) & (ky < y0 + self.n)
        if not inside.all():
            pts, rng, kx, ky = pts[inside], rng[inside], kx[inside], ky[inside]
        if not len(pts):
            return
        slot = self.slots(kx, ky)
        order = np.argsort(slot, kind="stable")
        slot, z, rng, key = slot[order], pts[order, 2].astype(np.float64), rng[order], pack(kx, ky)[order]
        sub = None if self.subtop is None else self._sub_index(pts[order, :2], kx[order], ky[order])
        start = np.flatnonzero(np.r_[True, slot[1:] != slot[:-1]])
        s = slot[start]
        # a slot holding another cell, or silent for memory_s, starts afresh
        stale = (self.key[s] != key[start]) | (t_ns - self.t_last[s] > int(self.cfg.memory_s * 1e9))
        self._reset(s[stale], key[start][stale])
        band = self.cfg.ground_band_m
        low = np.minimum.reduceat(z, start)
        old = self.zmin[s]
        # a lower surface restarts the ground band; so does a band too thin to trust under a
        # sweep that sees nothing near it (a lone low outlier must not hold the cell for good)
        restart = (low < old - band) | ((low > old + band) & (self.gn[s] < self.cfg.min_points))
        self.gsum[s[restart]] = 0.0
        self.gn[s[restart]] = 0
        self.top[s[restart]] = -np.inf
        if self.subtop is not None:
            self.subtop[s[restart]] = -np.inf
        zmin = np.where(restart, low, np.minimum(old, low))
        self.zmin[s] = zmin
        per_point = np.repeat(zmin, np.diff(np.r_[start, len(z)]))
        ground = z <= per_point + band
        self.gsum[s] += np.add.reduceat(np.where(ground, z, 0.0), start)
        self.gn[s] += np.add.reduceat(ground.astype(np.int64), start)
        under = np.where(z <= per_point + self.cfg.overhang_m, z, -np.inf)
        self.top[s] = np.maximum(self.top[s], np.maximum.reduceat(under, start))
        if self.subtop is not None:
            np.maximum.at(self.subtop, (slot, sub), under.astype(np.float32))
        self.rmin[s] = np.minimum(self.rmin[s], np.minimum.reduceat(rng, start))
        self.t_last[s] = t_ns

    def _sub_index(self, xy: NDArray, kx: NDArray[np.int64], ky: NDArray[np.int64]) -> NDArray[np.intp]:
        """Return the sub-cell (ix * sub + iy) of points ``xy`` (N, 2) in their cells (kx, ky)."""
        f = self.sub / self.res
        ix = np.clip(np.floor(xy[:, 0] * f - kx * self.sub), 0, self.sub - 1).astype(np.intp)
        iy = np.clip(np.floor(xy[:, 1] * f - ky * self.sub), 0, self.sub - 1).astype(np.intp)
        return ix * self.sub + iy

    def _reset(self, s: NDArray[np.int64], key: NDArray[np.int64]) -> None:
        self.key[s] = key
        if self.subtop is not None:
            self.subtop[s] = -np.inf
        self.zmin[s] = np.inf
        self.gsum[s] = 0.0
        self.gn[s] = 0
        self.top[s] = -np.inf
        self.rmin[s] = np.inf

    def crop(self, center_xy: NDArray, size: int, t_ns: int) -> dict[str, NDArray]:
        """Return the statistics of the ``size`` x ``size`` cells centred on ``center_xy`` as
        (size, size) arrays, axis 0 along x from the lowest x, and the window's lowest cell
        indices: ``ground`` (NaN below ``min_points``), ``top``, ``n``, ``range``, ``age_s``, and
        of a cell coarser than ``cover_cell_m`` ``subtop`` (size, size, sub * sub), -inf unseen."""
        if size > self.n:
            raise ValueError(f"a crop of {size} cells exceeds the ring of {self.n}")
        c = np.floor(np.asarray(center_xy, np.float64)[:2] / self.res).astype(np.int64)
        x0, y0 = int(c[0]) - size // 2, int(c[1]) - size // 2
        kx = np.arange(x0, x0 + size, dtype=np.int64)
        ky = np.arange(y0, y0 + size, dtype=np.int64)
        slot = (np.mod(kx, self.n) * self.n)[:, None] + np.mod(ky, self.n)[None, :]
        want = pack(np.repeat(kx, size), np.tile(ky, size)).reshape(size, size)
        age = (t_ns - self.t_last[slot]) * 1e-9
        held = (self.key[slot] == want) & (age <= self.cfg.memory_s) & (age >= 0)
        ok = held & (self.gn[slot] >= self.cfg.min_points)
        n = np.where(ok, self.gn[slot], 0)
        ground = np.where(ok, self.gsum[slot] / np.maximum(n, 1), np.nan)
        top = np.where(ok, np.maximum(self.top[slot], ground), np.nan)
        out = {"ground": ground, "top": top, "n": n, "range": np.where(ok, self.rmin[slot], np.inf),
               "age_s": np.where(ok, age, np.inf), "origin": np.array([x0, y0], np.int64)}
        if self.subtop is not None:
            out["subtop"] = np.where(ok[..., None], self.subtop[slot], -np.inf)
        return out

