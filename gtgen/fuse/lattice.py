"""The odom lattice: maps resampled onto it, and a sparse tiled accumulator over it.

Every range fuses on a lattice of square cells of the range's resolution ``r`` fixed
in the odom frame: lattice cell (I, J) covers [I r, (I + 1) r) x [J r, (J + 1) r).
A GridMap that moves by whole cells (as grid_map does) is already a window of this
lattice, so resampling it is a copy; any other map is resampled by nearest neighbour.

``top_layer`` splits one map's confident cells into ground and a top layer (crowns,
bushes) for the ``ground`` elevation rule (gtgen/fuse/fusion.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen.grids import cell_centers, grid_xy

ALIGN_TOL = 1e-6


@dataclass
class LatticeMap:
    """A map as a window of the lattice: layers (nx, ny) starting at lattice cell (i0, j0)."""

    t_ns: int
    i0: int
    j0: int
    elevation: NDArray[np.float32]
    risk: NDArray[np.float32]
    confidence: NDArray[np.float32]
    res: float = 1.0  # lattice resolution [m]
    top: NDArray[np.bool_] | None = None  # top-layer cells (``top_layer``), set when a rule needs them

    @property
    def shape(self) -> tuple[int, int]:
        return self.elevation.shape


def to_lattice(
    t_ns: int,
    layers: tuple[NDArray, NDArray, NDArray],
    center: NDArray,
    yaw: float,
    map_res: float,
    res: float,
) -> LatticeMap:
    """Return a map (elevation, risk, confidence in gtgen layout) on the lattice of ``res``."""
    elev, risk, conf = layers
    nx, ny = elev.shape
    x0 = center[0] - 0.5 * nx * map_res
    y0 = center[1] - 0.5 * ny * map_res
    fi, fj = x0 / res, y0 / res
    aligned = (
        abs(np.sin(yaw)) < ALIGN_TOL and np.cos(yaw) > 0 and abs(map_res - res) < ALIGN_TOL * res
        and abs(fi - round(fi)) < 1e-4 and abs(fj - round(fj)) < 1e-4
    )
    if aligned:
        return LatticeMap(t_ns, int(round(fi)), int(round(fj)), elev, risk, conf, res)
    # general case: gather the map cell under each lattice cell centre of the bounding box
    c, s = np.cos(yaw), np.sin(yaw)
    hx, hy = 0.5 * nx * map_res, 0.5 * ny * map_res
    corners = np.array([[-hx, -hy], [hx, -hy], [-hx, hy], [hx, hy]]) @ np.array([[c, s], [-s, c]]) + center[:2]
    i0 = int(np.floor(corners[:, 0].min() / res))
    j0 = int(np.floor(corners[:, 1].min() / res))
    i1 = int(np.floor(corners[:, 0].max() / res)) + 1
    j1 = int(np.floor(corners[:, 1].max() / res)) + 1
    X, Y = np.meshgrid((np.arange(i0, i1) + 0.5) * res - center[0], (np.arange(j0, j1) + 0.5) * res - center[1], indexing="ij")
    lx = c * X + s * Y
    ly = -s * X + c * Y
    mi = np.floor((lx + hx) / map_res).astype(np.int64)
    mj = np.floor((ly + hy) / map_res).astype(np.int64)
    ok = (mi >= 0) & (mi < nx) & (mj >= 0) & (mj < ny)
    mi, mj = np.where(ok, mi, 0), np.where(ok, mj, 0)
    out = [np.where(ok, a[mi, mj], np.nan).astype(np.float32) for a in (elev, risk, conf)]
    return LatticeMap(t_ns, i0, j0, *out, res)


def top_layer(m: LatticeMap, min_conf: float, footprint_m: float, height_m: float) -> NDArray[np.bool_]:
    """Return the confident cells of map ``m`` that stand more than ``height_m`` above the
    map's grey opening by a square of ``footprint_m`` (the lowest surface that a square of
    that size fits under: crowns and bushes narrower than it are cut off, slopes are not),
    in blobs of at least 2 x 2 cells (noise spikes come alone)."""
    from scipy.ndimage import binary_opening, maximum_filter, minimum_filter

    e, c = m.elevation, m.confidence
    obs = np.isfinite(e) & (c > min_conf)
    k = max(3, int(round(footprint_m / m.res)) | 1)
    low = minimum_filter(np.where(obs, e, np.inf), size=k, mode="constant", cval=np.inf)
    opened = maximum_filter(np.where(np.isfinite(low), low, -np.inf), size=k, mode="constant", cval=-np.inf)
    with np.errstate(invalid="ignore"):
        high = obs & (e - opened > height_m)
    return binary_opening(high, np.ones((2, 2), bool)) & obs


def target_lattice_index(size: int, grid_res: float, lattice_res: float, pos: NDArray, yaw: float) -> tuple[NDArray, NDArray]:
    """Return lattice indices (I, J) (size, size) of the cell centres of a sample's target grid.

    The target grid is vehicle-centric and gravity-aligned: centre at ``pos`` (odom),
    x along ``yaw``; axis 0 is x, index 0 at -L/2 (data_schema.md, 'Grids').
    """
    x = cell_centers(size, grid_res)  # the grid's x and y axes (grid_xy's meshgrid)
    c, s = np.cos(yaw), np.sin(yaw)
    # (pos_x + c X) - s Y and (pos_y + s X) + c Y as sums of a column and a row: each cell
    # the same products and sums as on the meshgrid (target_lattice_index_naive), in a third of the operations
    px = (pos[0] + c * x)[:, None] - (s * x)[None, :]
    py = (pos[1] + s * x)[:, None] + (c * x)[None, :]
    px /= lattice_res
    py /= lattice_res
    return np.floor(px).astype(np.int64), np.floor(py).astype(np.int64)


def target_lattice_index_naive(size: int, grid_res: float, lattice_res: float, pos: NDArray, yaw: float) -> tuple[NDArray, NDArray]:
    """:func:`target_lattice_index` on the meshgrid of the cell centres: the test oracle."""
    X, Y = grid_xy(size, grid_res)
    c, s = np.cos(yaw), np.sin(yaw)
    px = pos[0] + c * X - s * Y
    py = pos[1] + s * X + c * Y
    return np.floor(px / lattice_res).astype(np.int64), np.floor(py / lattice_res).astype(np.int64)


def gather_map(m: LatticeMap, I: NDArray, J: NDArray, layer: NDArray | None = None) -> tuple[NDArray, ...]:
    """Return the map's (elevation, risk, confidence) at lattice cells (I, J), NaN outside;
    with ``layer`` (an array of the map's shape), that layer alone (as float, NaN outside)."""
    a, b = I - m.i0, J - m.j0
    nx, ny = m.shape
    ok = (a >= 0) & (a < nx) & (b >= 0) & (b < ny)
    flat = np.where(ok, a * ny + b, 0)  # one flat index, taken from each layer (a 1-D take is the cheap gather)
    layers = (m.elevation, m.risk, m.confidence) if layer is None else (layer,)
    return tuple(np.where(ok, np.take(np.ascontiguousarray(arr).reshape(-1), flat), np.nan) for arr in layers)


class Atlas:
    """Sparse accumulators on the lattice, stored as square tiles in slot arrays.

    ``fields`` maps a name to (dtype, fill). Tiles are created on first write and can
    be released; memory follows the area touched by the maps currently accumulated.
    """

    def __init__(self, tile: int, fields: dict[str, tuple[str, object]]) -> None:
        self.tile = tile
        self.fields = fields
        self.slots: dict[tuple[int, int], int] = {}
        self.free: list[int] = []
        self.cap = 0
        self.data: dict[str, NDArray] = {k: np.empty((0, tile, tile), dtype=dt) for k, (dt, _) in fields.items()}
        self.touched: NDArray[np.int64] = np.empty(0, np.int64)

    def _alloc(self, key: tuple[int, int], stamp: int) -> int:
        if self.free:
            slot = self.free.pop()
        else:
            if len(self.slots) >= self.cap:
                new = max(16, 2 * self.cap)
                for k, (dt, _) in self.fields.items():
                    grown = np.empty((new, self.tile, self.tile), dtype=dt)
                    grown[: self.cap] = self.data[k]
                    self.data[k] = grown
                self.touched = np.concatenate([self.touched, np.zeros(new - self.cap, np.int64)])
                self.free = list(range(new - 1, self.cap, -1))
                slot = self.cap
                self.cap = new
            else:
                slot = self.free.pop()
        for k, (_, fill) in self.fields.items():
            self.data[k][slot] = fill
        self.slots[key] = slot
        self.touched[slot] = stamp
        return slot

    def windows(self, i0: int, j0: int, nx: int, ny: int, stamp: int, create: bool = True):
        """Yield (slot, tile slices, source slices) covering the lattice rectangle."""
        T = self.tile
        for ti in range(i0 // T, (i0 + nx - 1) // T + 1):
            for tj in range(j0 // T, (j0 + ny - 1) // T + 1):
                a0, a1 = max(i0, ti * T), min(i0 + nx, (ti + 1) * T)
                b0, b1 = max(j0, tj * T), min(j0 + ny, (tj + 1) * T)
                slot = self.slots.get((ti, tj))
                if slot is None:
                    if not create:
                        continue
                    slot = self._alloc((ti, tj), stamp)
                self.touched[slot] = max(self.touched[slot], stamp)
                yield slot, (slice(a0 - ti * T, a1 - ti * T), slice(b0 - tj * T, b1 - tj * T)), (slice(a0 - i0, a1 - i0), slice(b0 - j0, b1 - j0))

    def gather(self, I: NDArray, J: NDArray, names: tuple[str, ...]) -> list[NDArray]:
        """Return the named fields at lattice cells (I, J); cells of absent tiles get the fill."""
        T = self.tile
        if T & (T - 1) == 0:  # a power of two: shifts and masks (floor division of int64 costs twice as much)
            sh = T.bit_length() - 1
            ti, tj, li, lj = I >> sh, J >> sh, I & (T - 1), J & (T - 1)
        else:
            ti, tj = I // T, J // T
            li, lj = I - ti * T, J - tj * T
        ti0, tj0 = int(ti.min()), int(tj.min())
        table = np.full((int(ti.max()) - ti0 + 1, int(tj.max()) - tj0 + 1), -1, np.int64)
        for (a, b), slot in self.slots.items():
            if 0 <= a - ti0 < table.shape[0] and 0 <= b - tj0 < table.shape[1]:
                table[a - ti0, b - tj0] = slot
        slot = table[ti - ti0, tj - tj0]
        ok = slot >= 0
        # one flat index into the slot arrays, taken from each field (a 1-D take is the cheap gather)
        flat = np.where(ok, slot * (T * T) + li * T + lj, 0)
        out = []
        for n in names:
            fill = self.fields[n][1]
            if self.cap == 0:
                out.append(np.full(I.shape, fill, dtype=self.fields[n][0]))
                continue
            out.append(np.where(ok, np.take(self.data[n].reshape(-1), flat), fill))
        return out

    def release_older_than(self, stamp: int) -> int:
        """Release tiles last written before ``stamp``; return how many were released."""
        old = [k for k, s in self.slots.items() if self.touched[s] < stamp]
        for k in old:
            self.free.append(self.slots.pop(k))
        return len(old)

