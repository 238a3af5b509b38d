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
    """Return the step [m], slope [deg] and roughness [m] of ``ground`` (NaN: no ground) per cell,
    each over the k x k neighbourhood's cells that have ground; NaN where the cell has none."""
    valid = np.isfinite(ground)
    ref = float(np.median(ground[valid])) if valid.any() else 0.0
    g = np.where(valid, ground - ref, 0.0)
    hi = ndimage.maximum_filter(np.where(valid, g, -np.inf), size=k, mode="nearest")
    lo = ndimage.minimum_filter(np.where(valid, g, np.inf), size=k, mode="nearest")
    w = ndimage.uniform_filter(valid.astype(np.float64), size=k, mode="constant")
    m1 = ndimage.uniform_filter(g, size=k, mode="constant") / np.maximum(w, 1e-9)
    m2 = ndimage.uniform_filter(g * g, size=k, mode="constant") / np.maximum(w, 1e-9)
    rough = np.sqrt(np.maximum(m2 - m1 * m1, 0.0))
    # slope from the plane through the neighbourhood's mean gradient: central differences
    # where both neighbours have ground, one-sided where one has
    gx = _derivative(g, valid, 0) / res
    gy = _derivative(g, valid, 1) / res
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    nan = ~valid
    return {"step": np.where(nan, np.nan, hi - lo), "slope": np.where(nan, np.nan, slope), "roughness": np.where(nan, np.nan, rough)}


def _derivative(g: NDArray, valid: NDArray, axis: int) -> NDArray:
    """Return d g / d index along ``axis`` from the neighbours that have ground (0 where neither has)."""
    def shifted(a: NDArray, d: int, fill: float | bool) -> NDArray:
        out = np.full_like(a, fill)
        src = [slice(None)] * 2
        dst = [slice(None)] * 2
        src[axis], dst[axis] = (slice(1, None), slice(None, -1)) if d > 0 else (slice(None, -1), slice(1, None))
        out[tuple(dst)] = a[tuple(src)]
        return out

    up, vu = shifted(g, 1, 0.0), shifted(valid, 1, False)
    dn, vd = shifted(g, -1, 0.0), shifted(valid, -1, False)
    both = vu & vd
    return np.where(both, (up - dn) / 2, np.where(vu, up - g, np.where(vd, g - dn, 0.0)))


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
