"""What a DEM tile's borders with its neighbours say of it: the offset that makes it continue their terrain.

A tile where it belongs continues its neighbours' terrain across every border: the height
jump from its edge pixels to theirs is what the local slope predicts, up to the DEM's noise.
A tile whose file is georeferenced off by (dx, dy) and dz does not: along a border its
features are displaced by the offset's along-border part, across it the slope times the
across part adds to the jump, and dz adds to it everywhere. ``border_fit`` searches the
offset that makes the tile continue its neighbours best, on profiles read once per side
(``BorderSide``). A tile where it belongs is best as it is, a shifted one becomes
continuous put back by its offset, and a tile of another place continues its neighbours at
no offset. This needs no drive: neither odometry drift, nor GNSS, nor an ICP chain that
follows the tile it is on enters it.

What limits it: the along-border offset is found from the terrain's features along the
border and the across-border offset from its slope across it; on smooth terrain both are
weakly observed, and ``BorderFit.sigma`` says how weakly (the offsets that continue the
neighbours as well as the best one, within the step's own noise). Both directions are
observed when the tile has neighbours on two sides at right angles.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

COARSE_STEP_M = 0.5  # the search's first grid of horizontal offsets [m]
FINE_STEP_M = 0.1  # and its refinement around the best [m]
MIN_SIDE_SHARE = 0.25  # a side is read when a neighbour lies along this share of it
MIN_SIGMA_M = 0.05  # the least uncertainty claimed per horizontal axis (half the fine step) [m]
STEPS_PER_INDEPENDENT = 4  # neighbouring border pixels are correlated: the steps count as this many times fewer
SLOPE_PIXELS = 9  # the slope across a border is averaged over this many pixels along it: the terrain's slope
#                   varies slowly along a border, and a pixel's noise times the distance a shift extrapolates it over does not


@dataclass(frozen=True)
class BorderSide:
    """One side of a tile that has a neighbour. ``u``: positions along it [m] (pixel
    centres, from the side's start), ``axis``: 0 when the side runs along x (a south or
    north side), 1 along y; ``outward``: +1 when its outward normal points to +x or +y, else
    -1. The tile's heights at its edge pixel line and the next inward (``hi1``, ``hi2``),
    the neighbours' at their first two pixel lines beyond (``ho1``, ``ho2``; NaN where no
    neighbour), ``res`` the pixel size and ``gap_m`` how far beyond the tile's edge the
    neighbours' first line lies less half a pixel (0 for tiles that abut)."""

    u: NDArray[np.float64]
    axis: int
    outward: int
    hi1: NDArray[np.float64]
    hi2: NDArray[np.float64]
    ho1: NDArray[np.float64]
    ho2: NDArray[np.float64]
    res: float
    gap_m: float = 0.0


@dataclass(frozen=True)
class BorderFit:
    """A tile's borders with its neighbours: how many border pixels have a neighbour, the
    height step across them as the tile is read (``step_m``: the steps' median absolute
    deviation about their median) and put back by the best ``offset`` (dx, dy, dz) [m, working CRS, ``TileOffset``'s
    sense] (``best_step_m``), the offset's 1-sigma uncertainty per axis [m], and the
    vertical offset of the tile as it is read (``dz_as_read_m``)."""

    pixels: int
    step_m: float
    best_step_m: float
    offset: NDArray[np.float64]
    sigma: NDArray[np.float64]
    dz_as_read_m: float = 0.0

    @property
    def step_noise_m(self) -> float:
        """The standard error of ``best_step_m``: what a better offset must beat [m]."""
        return 1.2533 * self.best_step_m / np.sqrt(max(self.pixels / STEPS_PER_INDEPENDENT, 1.0))


def _shifted(side: BorderSide, shifts: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Return the tile's two edge lines read ``shifts`` [m] further along the side (one row
    per shift; NaN beyond the tile or next to a NaN pixel), and the interpolation's weight
    on the nearer pixel's neighbour per shift."""
    q = (side.u[None, :] + shifts[:, None]) / side.res - 0.5  # fractional pixel index along the side
    i0 = np.floor(q).astype(np.int64)
    f = q - i0
    n = len(side.u)
    ok = (i0 >= 0) & (i0 + 1 < n)
    a, b = np.clip(i0, 0, n - 1), np.clip(i0 + 1, 0, n - 1)
    out = []
    for h in (side.hi1, side.hi2):
        v = (1 - f) * h[a] + f * h[b]
        out.append(np.where(ok, v, np.nan))
    return out[0], out[1], f[:, 0]


def _steps(sides: list[BorderSide], dx: NDArray, dy: float) -> tuple[NDArray, NDArray]:
    """Return the height steps [m] (len(dx), all border pixels) across every side when the
    tile is read put back by (dx[k], dy): the neighbours' edge height less the tile's, less
    the slope across the border times the distance between the two lines; and the scale
    that makes them as noisy as a step as read. The DEM's noise enters a step through the
    four pixels it reads, by weights that depend on the offset (interpolated along the
    border, extrapolated across it): scaled so, a smaller spread at some offset means a
    better continuation, not pixels that happen to average the noise away."""
    rows, scales = [], []
    for s in sides:
        along, across = (dx, np.full_like(dx, dy)) if s.axis == 0 else (np.full_like(dx, dy), dx)
        a1, a2, f = _shifted(s, along)
        slope = _smooth(0.5 * ((a1 - a2) + (s.ho2 - s.ho1)[None, :])) / s.res
        # put back, the tile's edge recedes by the offset's outward part: the lines lie that much further apart
        dist = s.res + s.gap_m + s.outward * across[:, None]
        step = (s.ho1[None, :] - a1) - slope * dist
        d = dist[:, 0] / s.res
        noise = np.sqrt(1 + (1 - f) ** 2 + f ** 2 + d ** 2 / SLOPE_PIXELS)  # in pixel noise sigmas
        rows.append(step)
        scales.append(np.broadcast_to((np.sqrt(2 + 1 / SLOPE_PIXELS) / noise)[:, None], step.shape))  # a step's noise as read: d = 1, f = 0
    return np.concatenate(rows, axis=1), np.concatenate(scales, axis=1)


def _smooth(v: NDArray) -> NDArray:
    """Return ``v`` (rows of values along a side) averaged over SLOPE_PIXELS along it, NaN-aware."""
    from scipy.ndimage import uniform_filter1d

    ok = np.isfinite(v)
    num = uniform_filter1d(np.where(ok, v, 0.0), SLOPE_PIXELS, axis=1, mode="constant")
    den = uniform_filter1d(ok.astype(np.float64), SLOPE_PIXELS, axis=1, mode="constant")
    return np.where(ok, num / np.maximum(den, 1e-9), np.nan)


def nanmedian_rows(a: NDArray) -> NDArray:
    """Return ``np.nanmedian(a, axis=1)`` of a 2-D array, the same numbers, by one sort: NumPy
    takes a row of 600 or more values with a NaN one at a time in Python (36 us a row, 85 %
    of judging a tile's borders). NaN sorts last; the median is the mean of the middle two
    of a row's n values (the same one twice when n is odd); a row of NaN gives NaN."""
    if a.shape[1] == 0:
        return np.full(a.shape[0], np.nan, np.result_type(a.dtype, np.float16))
    s = np.sort(a, axis=1)
    n = a.shape[1] - np.isnan(a).sum(axis=1)
    lo = np.take_along_axis(s, np.maximum(n - 1, 0)[:, None] // 2, axis=1)[:, 0]
    hi = np.take_along_axis(s, (n // 2)[:, None], axis=1)[:, 0]
    return np.where(n > 0, (lo + hi) / 2, np.nan)


def _spread(steps: tuple[NDArray, NDArray]) -> tuple[NDArray, NDArray]:
    """Return per row the median absolute deviation of the scaled steps about their median
    [m], and the median step [m]."""
    st, scale = steps
    scaled = st * scale
    return nanmedian_rows(np.abs(scaled - nanmedian_rows(scaled)[:, None])), nanmedian_rows(st)


def _scan(sides: list[BorderSide], xs: NDArray, ys: NDArray) -> NDArray:
    """Return the step spread at every offset (xs[a], ys[b]) (len(xs), len(ys))."""
    return np.stack([_spread(_steps(sides, xs, float(y)))[0] for y in ys], axis=1)


def border_fit(sides: list[BorderSide], radius_m: float) -> BorderFit | None:
    """Return the offset within ``radius_m`` horizontally that makes the tile continue its
    neighbours best (the steps across its borders least spread; dz then cancels their
    median), or None without a neighbour."""
    if not sides:
        return None
    with np.errstate(invalid="ignore"):
        st0 = _steps(sides, np.zeros(1), 0.0)
        valid = np.isfinite(st0[0][0])
        if valid.sum() == 0:
            return None
        m0, med0 = _spread(st0)
        coarse = np.arange(-radius_m, radius_m + 1e-9, COARSE_STEP_M)
        C = _scan(sides, coarse, coarse)
        a, b = np.unravel_index(np.nanargmin(C), C.shape)
        fine = np.arange(-COARSE_STEP_M, COARSE_STEP_M + 1e-9, FINE_STEP_M)
        fx, fy = coarse[a] + fine, coarse[b] + fine
        F = _scan(sides, fx, fy)
        a2, b2 = np.unravel_index(np.nanargmin(F), F.shape)
        bx, by = float(fx[a2]), float(fy[b2])
        mb, med = _spread(_steps(sides, np.array([bx]), by))
    pixels = int(valid.sum())
    fit = BorderFit(pixels, float(m0[0]), float(mb[0]), np.array([bx, by, -float(med[0])]), np.zeros(3), -float(med0[0]))
    # offsets that continue the neighbours as well as the best within its noise span about +-2 sigma
    level = fit.best_step_m + 2 * fit.step_noise_m
    X, Y = np.meshgrid(coarse, coarse, indexing="ij")
    FX, FY = np.meshgrid(fx, fy, indexing="ij")
    near_x = np.concatenate([X[C <= level], FX[F <= level], [bx]])
    near_y = np.concatenate([Y[C <= level], FY[F <= level], [by]])
    sx = max(float(np.abs(near_x - bx).max()) / 2, MIN_SIGMA_M)
    sy = max(float(np.abs(near_y - by).max()) / 2, MIN_SIGMA_M)
    return replace(fit, sigma=np.array([sx, sy, 1.4826 * fit.step_noise_m]))  # dz: the steps' median, as a sigma
