"""The stack's layers from a window of cell statistics: ground elevation, risk, confidence, top.

Risk is geometric, as elevation_mapping's traversability filters and X-Racer-style stacks
compute it, from four ratios to their limits (``mapping.*``): the ground's step within
``neighbourhood_m``, its slope, its roughness (std within ``neighbourhood_m``) and the
height of what stands on it (top - ground) against the ground clearance. Risk is half the
largest ratio, clipped to [0, 1]: 0.5, the fatal threshold of ``train.fatal_risk``, is a
limit reached. Confidence is density x range x age, each in [0, 1].
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
    k = int(round(cfg.neighbourhood_m / res))
    return max(3, k + 1 - k % 2)


def geometry(ground: NDArray, res: float, k: int) -> dict[str, NDArray]:
    """Return the step [m], slope [deg] and roughness [m] of ``ground`` (NaN: no ground) per
    cell, from the plane fitted (least squares) through the k x k neighbourhood's cells that
    have ground: slope is the plane's, roughness the std of the cells about it, and step the
    largest jump from the cell to a neighbour beyond what the plane's slope explains. So a
    smooth slope is slope, not step or roughness, at any cell size. NaN where no ground."""
    valid = np.isfinite(ground)
    ref = float(np.median(ground[valid])) if valid.any() else 0.0
    g = np.where(valid, ground - ref, 0.0)
    v = valid.astype(np.float64)
    c = k // 2
    off = (np.arange(k) - c) * res
    KX, KY = np.meshgrid(off, off, indexing="ij")  # axis 0 = x

    def corr(a: NDArray, kern: NDArray) -> NDArray:
        return ndimage.correlate(a, kern, mode="constant", cval=0.0)

    one = np.ones((k, k))
    Sw, Sx, Sy = corr(v, one), corr(v, KX), corr(v, KY)
    Sxx, Syy, Sxy = corr(v, KX * KX), corr(v, KY * KY), corr(v, KX * KY)
    Sg, Sxg, Syg, Sgg = corr(g, one), corr(g, KX), corr(g, KY), corr(g * g, one)
    A = np.stack([np.stack([Sw, Sx, Sy], -1), np.stack([Sx, Sxx, Sxy], -1), np.stack([Sy, Sxy, Syy], -1)], -2)
    rhs = np.stack([Sg, Sxg, Syg], -1)
    fit = valid & (Sw >= 4)
    det = np.zeros_like(Sw)
    det[fit] = np.linalg.det(A[fit])
    fit &= np.abs(det) > 1e-9 * res**4 * np.maximum(Sw, 1) ** 3
    p = np.zeros((*g.shape, 3))
    p[..., 0] = np.where(Sw > 0, Sg / np.maximum(Sw, 1e-9), 0.0)  # no plane: the mean, level
    if fit.any():
        p[fit] = np.linalg.solve(A[fit], rhs[fit][..., None])[..., 0]
    a0, bx, by = p[..., 0], p[..., 1], p[..., 2]
    var = (Sgg - (a0 * Sg + bx * Sxg + by * Syg)) / np.maximum(Sw, 1e-9)
    rough = np.sqrt(np.maximum(var, 0.0))
    slope = np.degrees(np.arctan(np.hypot(bx, by)))
    step = np.zeros_like(g)
    H, W = g.shape
    for i in range(k):  # a loop over the k x k offsets, each a whole-grid operation
        for j in range(k):
            di, dj = i - c, j - c
            if di == 0 and dj == 0:
                continue
            gn = np.zeros_like(g)
            vn = np.zeros_like(valid)
            src = (slice(max(di, 0), H + min(di, 0)), slice(max(dj, 0), W + min(dj, 0)))
            dst = (slice(max(-di, 0), H + min(-di, 0)), slice(max(-dj, 0), W + min(-dj, 0)))
            gn[dst], vn[dst] = g[src], valid[src]
            jump = np.abs(gn - g - (bx * di * res + by * dj * res))
            step = np.maximum(step, np.where(vn, jump, 0.0))
    nan = ~valid
    return {"step": np.where(nan, np.nan, step), "slope": np.where(nan, np.nan, slope), "roughness": np.where(nan, np.nan, rough)}


def layers(cells: dict[str, NDArray], cfg: MappingConfig, res: float, center: NDArray) -> MapLayers:
    """Return the layers of a crop of cell statistics (``RollingCells.crop``)."""
    ground, top = cells["ground"], cells["top"]
    geo = geometry(ground, res, neighbourhood_cells(cfg, res))
    height = np.where(np.isfinite(ground), top - ground, np.nan)
    ratio = np.fmax.reduce([geo["step"] / cfg.max_step_m, geo["slope"] / cfg.max_slope_deg,
                            geo["roughness"] / cfg.max_roughness_m, height / cfg.clearance_m])
    risk = np.clip(0.5 * ratio, 0.0, 1.0)
    conf = (-np.expm1(-cells["n"] / cfg.full_points)) * np.exp2(-cells["range"] / cfg.range_half_m) * np.exp2(-cells["age_s"] / cfg.age_half_s)
    conf = np.where(np.isfinite(ground), np.clip(conf, 0.0, 1.0), 0.0)
    f4 = np.float32
    return MapLayers(center=np.asarray(center, np.float64), elevation=ground.astype(f4), risk=risk.astype(f4),
                     confidence=conf.astype(f4), top=top.astype(f4))
