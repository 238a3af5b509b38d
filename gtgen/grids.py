"""Grid rules, each written once: where a vehicle-centric grid's cells lie, which cell a
point falls in, bilinear sampling and resampling, and the gap fills and distances the
model's inputs and the eval's baselines are made of.

Conventions (data_schema.md, 'Grids'): axis 0 is x, axis 1 is y, index 0 at the most
negative coordinate; cell (i, j) has its centre at (-L/2 + (i + 0.5) r, -L/2 + (j + 0.5) r).
Fractional cell coordinates put cell i's centre at i. The torch twin of ``xy_to_index``
(``gtgen.train.pillars.cell_index``) is tested against it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def cell_centers(size: int, resolution_m: float) -> F64:
    """Return the (size,) cell-centre coordinates [m] of a vehicle-centric grid axis."""
    return -0.5 * size * resolution_m + (np.arange(size) + 0.5) * resolution_m


def grid_xy(size: int, resolution_m: float) -> tuple[F64, F64]:
    """Return x and y [m] of every cell (size, size), axis 0 along x, axis 1 along y."""
    c = cell_centers(size, resolution_m)
    return np.meshgrid(c, c, indexing="ij")


def xy_to_index(x: NDArray, y: NDArray, size: int, resolution_m: float) -> tuple[NDArray, NDArray]:
    """Return the integer cell indices (i, j) of points (x, y) [m]; out-of-grid gives -1."""
    half = 0.5 * size * resolution_m
    i = np.floor((np.asarray(x) + half) / resolution_m).astype(np.int64)
    j = np.floor((np.asarray(y) + half) / resolution_m).astype(np.int64)
    bad = (i < 0) | (i >= size) | (j < 0) | (j >= size)
    return np.where(bad, -1, i), np.where(bad, -1, j)


def nearest_index(src_size: int, dst_size: int) -> NDArray[np.int64]:
    """Return, per destination cell, the source cell containing its centre (same extent)."""
    centres = (np.arange(dst_size) + 0.5) * (src_size / dst_size)
    return np.clip(np.floor(centres).astype(np.int64), 0, src_size - 1)


def cell_weights(coord: NDArray) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """Return the lower cell index and the bilinear weight of the upper one, per fractional
    cell coordinate (centres at integers), for samplers that gather the four neighbours
    themselves (the synthetic terrain's tile pool)."""
    f = np.asarray(coord, np.float64)
    i = np.floor(f)
    return i.astype(np.int64), (f - i).astype(np.float32)


def bilinear(grids: NDArray, rows: NDArray, cols: NDArray, outside: str = "nan") -> NDArray[np.float64]:
    """Return the grids (..., n, m) sampled bilinearly at fractional cell coordinates
    (``rows`` along the second-to-last axis, ``cols`` along the last; centres at integers),
    one value per coordinate pair of the broadcast shape. ``outside="nan"``: NaN beyond the
    outer cell centres and next to a NaN cell; ``"edge"``: the edge cells extended. The one
    bilinear sampler of gtgen (DEM heights, the prior's pyramid, grid resampling)."""
    from scipy.ndimage import map_coordinates

    if outside not in ("nan", "edge"):
        raise ValueError(f"outside={outside!r}; expected 'nan' or 'edge'")
    g = np.asarray(grids)
    rows, cols = np.asarray(rows, np.float64), np.asarray(cols, np.float64)
    if outside == "edge" and rows.shape == (rows.size, 1) and cols.shape == (1, cols.size):
        return _bilinear_outer(g, rows[:, 0], cols[0])
    r, c = np.broadcast_arrays(rows, cols)
    flat = g.reshape(-1, *g.shape[-2:])
    if outside == "nan" and g.dtype in (np.float32, np.float64) and min(g.shape[-2:]) >= 2:
        out = _bilinear_gather(flat, r.ravel(), c.ravel())
    else:
        coords = [r.ravel(), c.ravel()]
        mode, cval = ("constant", np.nan) if outside == "nan" else ("nearest", 0.0)
        out = np.stack([map_coordinates(x, coords, order=1, mode=mode, cval=cval, prefilter=False) for x in flat])
    return out.reshape(*g.shape[:-2], *r.shape)


GATHER_CHUNK = 1 << 15  # points per pass of the gathering sampler: its float64 temporaries stay in the cache (256 kB each)


def _bilinear_gather(flat: NDArray, r: NDArray[np.float64], c: NDArray[np.float64]) -> NDArray:
    """``bilinear(..., outside="nan")`` of float grids (k, n, m), n, m >= 2, at the flat
    coordinates ``r``, ``c``: four gathers and the weights map_coordinates uses, in its
    order of products and sums (float64), so the same bits as its order-1 spline (the
    test oracle) at about half its time (a DEM patch per sample in dem-align). Points are
    taken ``GATHER_CHUNK`` at a time, so memory stays bounded for a whole tile."""
    n, m = flat.shape[-2:]
    grids = flat.reshape(len(flat), -1)
    out = np.empty((len(flat), len(r)), flat.dtype)
    for s in range(0, len(r), GATHER_CHUNK):
        rs, cs = r[s : s + GATHER_CHUNK], c[s : s + GATHER_CHUNK]
        inside = (rs >= 0) & (rs <= n - 1) & (cs >= 0) & (cs <= m - 1)  # False for NaN coordinates
        rs, cs = np.where(inside, rs, 0.0), np.where(inside, cs, 0.0)
        i, j = np.minimum(np.floor(rs), n - 2), np.minimum(np.floor(cs), m - 2)
        a0, b0 = 1.0 - (rs - i), 1.0 - (cs - j)  # scipy's weights: the upper one is 1 minus the lower
        a1, b1 = 1.0 - a0, 1.0 - b0
        k = i.astype(np.intp) * m + j.astype(np.intp)
        for x, o in zip(grids, out):
            v = x[k] * a0
            v *= b0
            v += x[k + 1] * a0 * b1
            v += x[k + m] * a1 * b0
            v += x[k + m + 1] * a1 * b1
            o[s : s + GATHER_CHUNK] = np.where(inside, v, np.nan)
    return out


def _axis_taps(x: NDArray[np.float64], n: int) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """Return the two source cells and the upper one's weight of each coordinate ``x`` along
    an axis of ``n`` cells, the edge cells extended beyond the outer centres."""
    x = np.clip(x, 0.0, n - 1.0)
    i0 = np.minimum(np.floor(x).astype(np.int64), max(n - 2, 0))
    return i0, np.minimum(i0 + 1, n - 1), x - i0


def _bilinear_outer(g: NDArray, rows: NDArray[np.float64], cols: NDArray[np.float64]) -> NDArray[np.floating]:
    """``bilinear(g, rows[:, None], cols[None, :], outside="edge")`` on the grid of every
    (row, col) pair, as two separable passes (gathers of whole rows, then of columns):
    the same weights as the general sampler (its test oracle), a fraction of its time."""
    g = np.asarray(g)
    g = g.astype(np.result_type(g.dtype, np.float32), copy=False)  # float32 grids are sampled in float32, as map_coordinates does
    r0, r1, a = _axis_taps(rows, g.shape[-2])
    c0, c1, b = _axis_taps(cols, g.shape[-1])
    a, b = a.astype(g.dtype), b.astype(g.dtype)
    # the same products and sums as t[r0] (1 - a) + t[r1] a, then along the columns, in
    # place: the temporaries of the fine grid were most of its time
    t = g[..., r0, :] * (1.0 - a)[:, None]
    t += g[..., r1, :] * a[:, None]
    out = np.take(t, c0, axis=-1)
    out *= 1.0 - b
    hi = np.take(t, c1, axis=-1)
    hi *= b
    out += hi
    return out


def resample_bilinear(grids: NDArray, size: int) -> NDArray[np.float32]:
    """Return the square grids (..., n, n) resampled to (..., size, size) over the same
    extent, bilinear between cell centres (edge cells extended)."""
    x = (np.arange(size) + 0.5) * (grids.shape[-1] / size) - 0.5
    return bilinear(grids, x[:, None], x[None, :], outside="edge").astype(np.float32)


def raw_min_z(points: NDArray, size: int, res: float) -> NDArray[np.float32]:
    """Return the lowest point per cell of a (size, size) target grid of ``res`` (NaN where none)."""
    out = np.full(size * size, np.inf, np.float32)
    i, j = xy_to_index(points[:, 0], points[:, 1], size, res)
    ok = i >= 0
    np.minimum.at(out, i[ok] * size + j[ok], points[ok, 2])
    out[np.isinf(out)] = np.nan
    return out.reshape(size, size)


def smoothed_min_z(raw: NDArray, size: int = 3) -> NDArray[np.float32]:
    """Return the min-z grid averaged over its valid cells in a ``size`` x ``size`` window,
    at the valid cells only (normalized convolution; NaN elsewhere). Voxel-map minima sit on
    a 0.4 m voxel lattice; averaging neighbours removes most of that quantisation on smooth
    ground (docs/training.md, "M&M-lite")."""
    from scipy.ndimage import uniform_filter

    ok = np.isfinite(raw)
    m = ok.astype(np.float64)
    num = uniform_filter(np.where(ok, raw, 0.0).astype(np.float64), size, mode="constant")
    den = uniform_filter(m, size, mode="constant")
    return np.where(ok & (den > 0), num / np.maximum(den, 1e-12), np.nan).astype(np.float32)


def _pool2(a: NDArray) -> NDArray[np.float64]:
    """Return the 2 x 2 block means of a stack (m, n, n); an odd edge is padded with zeros
    (zero weight)."""
    m, n, _ = a.shape
    if n % 2:
        a = np.pad(a, ((0, 0), (0, 1), (0, 1)))
    k = a.shape[1] // 2
    return a.reshape(m, k, 2, k, 2).mean(axis=(2, 4))


def filled(grid: NDArray, max_sigma_cells: float = 4.0) -> NDArray[np.float32]:
    """Return ``grid`` with its NaN cells filled from the valid ones, coarse to fine: each
    empty cell takes the Gaussian-weighted mean of the valid cells at the finest of the
    scales sigma = 1, 2, 4, ... cells that reaches some (normalized convolution, weight
    above 1e-3); valid cells keep their value, a grid without any valid cell is 0. Beyond
    the voxel points it is the smooth continuation of the ground around them, which the
    heads correct.

    Scales above ``max_sigma_cells`` are computed on a pyramid of 2 x 2 block means (sigma
    at most ``max_sigma_cells`` cells of the level) and interpolated back bilinearly: every
    scale costs at most one filter of that width. The full-resolution fill
    (``max_sigma_cells=inf``) is the tests' oracle; the two differ only along the seams
    where a cell's scale changes. Why this fill and not another: docs/training.md,
    "M&M-lite"."""
    from scipy.ndimage import gaussian_filter

    ok = np.isfinite(grid)
    if ok.all():
        return grid.astype(np.float32)
    if not ok.any():
        return np.zeros(grid.shape, np.float32)
    n = grid.shape[0]
    level_wv = np.empty((2, *grid.shape))  # (weight, weighted value) of the current level
    level_wv[0] = ok
    level_wv[1] = np.where(ok, grid, 0.0)
    out = np.where(ok, grid, np.nan).astype(np.float64)  # the valid cells are done
    todo = ~ok  # the cells no scale has reached yet
    sigma, level = 1.0, 0
    while (rows := np.flatnonzero(todo.any(axis=1))).size and sigma <= 2 * max(grid.shape):
        while sigma / 2**level > max_sigma_cells and level_wv.shape[1] > 4:
            level_wv = _pool2(level_wv)
            level += 1
        # both planes in one call: the same 1-D passes, in the same order, as one filter each
        smooth = gaussian_filter(level_wv, sigma / 2**level, mode="constant", truncate=3.0, axes=(1, 2))
        if level:  # the level's cells at the fine cell centres, on the rows still holding an empty cell
            x = (np.arange(n) + 0.5) / 2**level - 0.5
            den, num = bilinear(smooth, x[rows][:, None], x[None, :], outside="edge")
        else:
            den, num = smooth[:, rows]
        reach = todo[rows] & (den > 1e-3)
        sub = out[rows]
        sub[reach] = num[reach] / den[reach]
        out[rows] = sub
        todo[rows] &= ~reach
        sigma *= 2
    out[todo] = float(grid[ok].mean())
    out[ok] = grid[ok]
    return out.astype(np.float32)


def nearest_filled(grid: NDArray) -> NDArray[np.float32]:
    """Return ``grid`` with every NaN cell set to the value of its nearest valid cell
    (the eval's trivial full-coverage baseline); all NaN stays NaN."""
    from scipy.ndimage import distance_transform_edt

    ok = np.isfinite(grid)
    if ok.all() or not ok.any():
        return grid.astype(np.float32)
    _, (i, j) = distance_transform_edt(~ok, return_indices=True)
    return grid[i, j].astype(np.float32)


def point_distance(grid: NDArray) -> NDArray[np.float32]:
    """Return, per cell, the distance to the nearest valid cell of ``grid`` over the grid's
    size (0 on valid cells, 1 everywhere when none is valid)."""
    from scipy.ndimage import distance_transform_edt

    ok = np.isfinite(grid)
    if not ok.any():
        return np.ones(grid.shape, np.float32)
    return (distance_transform_edt(~ok) / grid.shape[0]).astype(np.float32)
