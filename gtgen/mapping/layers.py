"""The stack's layers from a window of cell statistics: ground elevation, risk, confidence, top.

Risk is geometric, as elevation_mapping's traversability filters and X-Racer-style stacks
compute it, from ratios to their limits (``mapping.*``), on two surfaces: the cells' ground,
and the local ground under it, the ground with whatever stands on it narrower than
``ground_window_m`` taken away (a grey opening: the highest surface a window of that edge
can be pushed up under the ground, which keeps planes and slopes and removes rocks). The
local ground is what the wheels roll on: its step within ``neighbourhood_m`` (the higher
side of a step only: where a wheel meets the edge or drops off it), its slope and its
roughness (std about the local plane). What stands on it is an obstacle by its own height:
the cell's ground above the local ground (a rock, against ``max_step_m``), and the cell's top
above its ground, less what the local slope spans across the cell (a bush, a trunk, against
the ground clearance; of a cell coarser than ``cover_cell_m``, the top that half of its seen
sub-cells reach, so a 0.8 m cell whose corner a crown or a rock's side crosses is judged
by what covers it, as the cell's centre would be). So a rock's cells are fatal and the ground around it is not: the old
rule measured each cell's step against its neighbours both ways, and the ring of cells
below a rock's edge read fatal too (``tests/test_mapping.py`` keeps it as an oracle).
Risk is half the largest ratio, clipped to [0, 1]: 0.5, the fatal threshold of
``train.fatal_risk``, is a limit reached. Confidence is density x range x age, each in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from gtgen.config import MappingConfig


@dataclass
class MapLayers:
    """One map of a range: (size, size) float32 layers, axis 0 along odom x from the lowest x,
    centred at ``center`` (odom x, y), axes along odom's."""

    center: NDArray[np.float64]
    elevation: NDArray[np.float32]
    risk: NDArray[np.float32]
    confidence: NDArray[np.float32]
    top: NDArray[np.float32]


def neighbourhood_cells(cfg: MappingConfig, res: float) -> int:
    """Return the odd neighbourhood edge in cells (at least 3) of ``neighbourhood_m``."""
    return window_cells(cfg.neighbourhood_m, res)


def window_cells(window_m: float, res: float) -> int:
    """Return the odd window edge in cells (at least 3) of ``window_m`` at cells of ``res``."""
    k = int(round(window_m / res))
    return max(3, k + 1 - k % 2)


def local_ground(ground: NDArray, k: int) -> NDArray:
    """Return the grey opening of ``ground`` (NaN: no ground) by a k x k window: at each cell
    the highest of the minima of the k x k windows that hold it, over the cells with ground.
    Never above the ground; equal to it on planes and on any surface whose bumps are wider
    than the window; NaN where no ground."""
    valid = np.isfinite(ground)
    c = k // 2
    # windows reach past the grid's border and the ground's edge: the minimum is over the cells
    # with ground only, so a slope's last cells are not cut below their own height
    low = ndimage.minimum_filter(np.pad(np.where(valid, ground, np.inf), c, constant_values=np.inf), size=k, mode="constant", cval=np.inf)
    base = ndimage.maximum_filter(np.where(np.isfinite(low), low, -np.inf), size=k, mode="constant", cval=-np.inf)
    return np.where(valid, base[c:c + ground.shape[0], c:c + ground.shape[1]], np.nan)


def geometry(ground: NDArray, res: float, k: int) -> dict[str, NDArray]:
    """Return the step [m], slope [deg], roughness [m] and rise [m] of ``ground`` (NaN: no
    ground) per cell, from the plane fitted (least squares) through the k x k
    neighbourhood's cells that have ground: slope is the plane's, roughness the std of the
    cells about it, step the most the cell stands above a neighbour beyond what the
    plane's slope explains (a step belongs to its higher side), and rise what the plane
    climbs across one cell (corner to corner), which the points of a cell span on a slope
    without anything standing on it.
    So a smooth slope is slope, not step, roughness or height, at any cell size. NaN where
    no ground.

    The sums of the fit are separable filters and the 3 x 3 normal equations are solved by
    Cramer's rule, cell-wise (``geometry_naive`` solves them one by one: the oracle)."""
    valid = np.isfinite(ground)
    ref = float(np.median(ground[valid])) if valid.any() else 0.0
    g = np.where(valid, ground - ref, 0.0)
    v = valid.astype(np.float64)
    c = k // 2
    off = (np.arange(k) - c) * res
    one = np.ones(k)

    def corr(a: NDArray, kx: NDArray, ky: NDArray) -> NDArray:  # sum over the neighbourhood of a * kx[dx] * ky[dy]
        return ndimage.correlate1d(ndimage.correlate1d(a, kx, axis=0, mode="constant"), ky, axis=1, mode="constant")

    Sw, Sx, Sy = corr(v, one, one), corr(v, off, one), corr(v, one, off)
    Sxx, Syy, Sxy = corr(v, off * off, one), corr(v, one, off * off), corr(v, off, off)
    Sg, Sxg, Syg, Sgg = corr(g, one, one), corr(g, off, one), corr(g, one, off), corr(g * g, one, one)
    # Cramer's rule on [[Sw, Sx, Sy], [Sx, Sxx, Sxy], [Sy, Sxy, Syy]] p = [Sg, Sxg, Syg]
    c00, c01, c02 = Sxx * Syy - Sxy * Sxy, Sxy * Sy - Sx * Syy, Sx * Sxy - Sxx * Sy
    det = Sw * c00 + Sx * c01 + Sy * c02
    fit = valid & (Sw >= 4) & (np.abs(det) > 1e-9 * res**4 * np.maximum(Sw, 1) ** 3)
    inv = np.where(fit, 1.0 / np.where(fit, det, 1.0), 0.0)
    a0 = np.where(fit, (Sg * c00 + Sxg * c01 + Syg * c02) * inv, Sg / np.maximum(Sw, 1e-9))  # no plane: the mean, level
    bx = (Sg * c01 + Sxg * (Sw * Syy - Sy * Sy) + Syg * (Sx * Sy - Sw * Sxy)) * inv
    by = (Sg * c02 + Sxg * (Sy * Sx - Sw * Sxy) + Syg * (Sw * Sxx - Sx * Sx)) * inv
    var = (Sgg - (a0 * Sg + bx * Sxg + by * Syg)) / np.maximum(Sw, 1e-9)
    rough = np.sqrt(np.maximum(var, 0.0))
    slope = np.degrees(np.arctan(np.hypot(bx, by)))
    H, W = g.shape
    gp = np.pad(g.astype(np.float32), c)
    vp = np.pad(valid, c)
    g32, bx32, by32 = g.astype(np.float32), (bx * res).astype(np.float32), (by * res).astype(np.float32)
    step = np.zeros((H, W), np.float32)
    for di in range(-c, c + 1):  # a loop over the k x k offsets, each a whole-grid operation
        for dj in range(-c, c + 1):
            if di == 0 and dj == 0:
                continue
            gn = gp[c + di: c + di + H, c + dj: c + dj + W]
            vn = vp[c + di: c + di + H, c + dj: c + dj + W]
            jump = g32 - gn + (bx32 * di + by32 * dj)
            np.maximum(step, np.where(vn, jump, 0.0), out=step)
    nan = ~valid
    rise = np.where(fit, (np.abs(bx) + np.abs(by)) * res, 0.0)
    return {"step": np.where(nan, np.nan, step), "slope": np.where(nan, np.nan, slope), "roughness": np.where(nan, np.nan, rough),
            "rise": np.where(nan, np.nan, rise)}


def geometry_naive(ground: NDArray, res: float, k: int) -> dict[str, NDArray]:
    """``geometry`` cell by cell: the plane fitted with lstsq on each neighbourhood (the test oracle)."""
    H, W = ground.shape
    c = k // 2
    out = {n: np.full((H, W), np.nan) for n in ("step", "slope", "roughness", "rise")}
    for i in range(H):
        for j in range(W):
            if not np.isfinite(ground[i, j]):
                continue
            pts = [(di * res, dj * res, ground[i + di, j + dj]) for di in range(-c, c + 1) for dj in range(-c, c + 1)
                   if 0 <= i + di < H and 0 <= j + dj < W and np.isfinite(ground[i + di, j + dj])]
            P = np.array(pts)
            A = np.column_stack([np.ones(len(P)), P[:, 0], P[:, 1]])
            if len(P) >= 4 and np.linalg.matrix_rank(A) == 3:
                a0, bx, by = np.linalg.lstsq(A, P[:, 2], rcond=None)[0]
            else:
                a0, bx, by = P[:, 2].mean(), 0.0, 0.0
            out["rise"][i, j] = (abs(bx) + abs(by)) * res
            out["roughness"][i, j] = np.sqrt(max(np.mean((P[:, 2] - (a0 + bx * P[:, 0] + by * P[:, 1])) ** 2), 0.0))
            out["slope"][i, j] = np.degrees(np.arctan(np.hypot(bx, by)))
            out["step"][i, j] = max([ground[i, j] - z + bx * x + by * y for x, y, z in P if (x, y) != (0, 0)] + [0.0])
    return out


def half_cover_top(subtop: NDArray) -> NDArray:
    """Return, per cell, the top that at least half of its seen sub-cells reach: the
    ceil(n / 2)-th highest of the n finite values along the last axis (-inf: unseen; NaN
    where none is seen). Of one seen sub-cell, its top; of 16, the 8th highest."""
    srt = np.sort(subtop, axis=-1)
    s = subtop.shape[-1]
    seen = np.isfinite(subtop).sum(axis=-1)
    at = np.take_along_axis(srt, np.clip(s - (seen + 1) // 2, 0, s - 1)[..., None], axis=-1)[..., 0]
    return np.where(seen > 0, at, np.nan)


def half_cover_top_naive(subtop: NDArray) -> NDArray:
    """``half_cover_top`` cell by cell (the test oracle)."""
    out = np.full(subtop.shape[:-1], np.nan)
    for idx in np.ndindex(*subtop.shape[:-1]):
        v = sorted((float(x) for x in subtop[idx] if np.isfinite(x)), reverse=True)
        if v:
            out[idx] = v[(len(v) + 1) // 2 - 1]
    return out


def layers(cells: dict[str, NDArray], cfg: MappingConfig, res: float, center: NDArray) -> MapLayers:
    """Return the layers of a crop of cell statistics (``RollingCells.crop``)."""
    ground, top = cells["ground"], cells["top"]
    # a coarse cell stands as high as what covers half of it (RollingCells keeps its sub-cells' tops)
    cover = np.fmax(half_cover_top(cells["subtop"]), ground) if "subtop" in cells else top
    base = local_ground(ground, window_cells(cfg.ground_window_m, res))
    geo = geometry(base, res, neighbourhood_cells(cfg, res))
    # what stands on the local ground: the cell's own ground above it (a rock), and the cell's
    # top above its ground, less what the local slope spans across the cell (a bush, a trunk)
    valid = np.isfinite(ground)
    standing = np.where(valid, ground - base, np.nan)
    height = np.where(valid, np.maximum(cover - ground - geo["rise"], 0.0), np.nan)
    ratio = np.fmax.reduce([geo["step"] / cfg.max_step_m, geo["slope"] / cfg.max_slope_deg,
                            geo["roughness"] / cfg.max_roughness_m, standing / cfg.max_step_m, height / cfg.clearance_m])
    risk = np.clip(0.5 * ratio, 0.0, 1.0)
    conf = (-np.expm1(-cells["n"] / cfg.full_points)) * np.exp2(-cells["range"] / cfg.range_half_m) * np.exp2(-cells["age_s"] / cfg.age_half_s)
    conf = np.where(np.isfinite(ground), np.clip(conf, 0.0, 1.0), 0.0)
    f4 = np.float32
    return MapLayers(center=np.asarray(center, np.float64), elevation=ground.astype(f4), risk=risk.astype(f4),
                     confidence=conf.astype(f4), top=top.astype(f4))
