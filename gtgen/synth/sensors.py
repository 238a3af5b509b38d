"""Simulated sensors: a lidar's view of the ground, X-Racer maps, voxel map (the cameras:
``gtgen.synth.camera``).

The lidar model is a horizon test on a polar grid around the sensor: a sample is seen
when its elevation angle is at least the largest angle of every nearer sample on the
same azimuth (occlusion by terrain and tree crowns), within the vertical field of view
and the maximum range. Everything is vectorised over samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen.config import GridSpec, SynthConfig
from gtgen.synth.terrain import Terrain

N_AZ = 720
RANGE_STEP_M = 0.25  # polar range step near the lidar [m]
FAR_FROM_M = 30.0  # beyond this range the step doubles: fewer samples where cells are coarse anyway
FAR_STEP_M = 0.5
MIN_ELEV_ANGLE = np.tan(np.deg2rad(-25.0))


@dataclass
class LidarView:
    """What the lidar sees from one pose: polar samples (N_AZ, N_R) in the world frame."""

    origin: NDArray[np.float64]  # (3,) sensor position [m], world
    ranges: NDArray[np.float64]  # (N_R,)
    az: NDArray[np.float64]  # (N_AZ,)
    ground: NDArray[np.float32]  # ground height of each sample [m]
    surface: NDArray[np.float32]  # surface height (with crowns) [m]
    seen_surface: NDArray[np.bool_]  # the surface at the sample is hit by a beam
    seen_ground: NDArray[np.bool_]  # the ground itself is hit (not a crown)
    held_ground: NDArray[np.float32]  # last seen ground height along the ray (NaN before any)
    density: NDArray[np.float32] | None = None  # expected returns per m2 per revolution (density model)


def lidar_ranges(max_range_m: float) -> NDArray[np.float64]:
    """Return the polar sample ranges [m]: RANGE_STEP_M up to FAR_FROM_M, FAR_STEP_M beyond."""
    near = np.arange(1.0, min(FAR_FROM_M, max_range_m + 1e-9), RANGE_STEP_M)
    far = np.arange(FAR_FROM_M, max_range_m + 1e-9, FAR_STEP_M) if max_range_m >= FAR_FROM_M else np.zeros(0)
    return np.concatenate([near, far])


def lidar_view(cfg: SynthConfig, terrain: Terrain, origin: NDArray) -> LidarView:
    """Return the polar visibility of the terrain from a lidar at world ``origin``."""
    ranges = lidar_ranges(cfg.lidar_range_m)
    az = np.arange(N_AZ) * (2 * np.pi / N_AZ)
    U = origin[0] + np.cos(az)[:, None] * ranges[None, :]
    V = origin[1] + np.sin(az)[:, None] * ranges[None, :]
    ground, surface = terrain.sample(U, V, ("ground", "surface"))
    ang_s = (surface - origin[2]) / ranges
    prior = np.maximum.accumulate(ang_s, axis=1)
    prior = np.concatenate([np.full((N_AZ, 1), -np.inf, np.float32), prior[:, :-1]], axis=1)
    in_fov = ang_s >= MIN_ELEV_ANGLE
    seen_surface = (ang_s >= prior - 1e-4) & in_fov
    crown = surface - ground > 0.3
    seen_ground = seen_surface & ~crown
    # naive extrapolation: hold the last ground height seen along each ray
    idx = np.where(seen_ground, np.arange(len(ranges))[None, :], -1)
    idx = np.maximum.accumulate(idx, axis=1)
    held = np.take_along_axis(ground, np.maximum(idx, 0), axis=1)
    held = np.where(idx >= 0, held, np.nan).astype(np.float32)
    density = return_density(cfg, ranges, ang_s, prior, seen_surface) if cfg.confidence_model == "density" else None
    return LidarView(origin, ranges, az, ground, surface, seen_surface, seen_ground, held, density)


def return_density(cfg: SynthConfig, ranges: NDArray, ang: NDArray, prior: NDArray, seen: NDArray) -> NDArray[np.float32]:
    """Return the expected lidar returns per m2 per revolution at each polar sample.

    A visible sample spans the elevation angles between the horizon of the nearer samples
    (``prior``, tangents) and its own (``ang``); the beams, ``lidar_beams`` evenly over
    ``lidar_vfov_deg``, that fall in that span land on it, each with ``lidar_az_points``
    returns per revolution spread around its circle. So returns thin out as 1/r^3 on flat
    ground, pile up on slopes facing the sensor and vanish behind crests and obstacles.
    """
    beam = np.deg2rad(cfg.lidar_vfov_deg) / cfg.lidar_beams
    lo = np.maximum(prior, np.float32(MIN_ELEV_ANGLE))
    span = np.arctan(ang) - np.arctan(np.minimum(lo, ang))  # [rad] of elevation the sample takes
    step = np.diff(ranges, append=ranges[-1] + (ranges[-1] - ranges[-2] if len(ranges) > 1 else RANGE_STEP_M))
    per_m2 = (span / beam) * (cfg.lidar_az_points / (2 * np.pi * ranges))[None, :] / step[None, :]
    return np.where(seen, per_m2, 0.0).astype(np.float32)


def polar_lookup(view: LidarView, u: NDArray, v: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Return (azimuth index, range index, range [m]) of world points; range index -1 outside."""
    du = (u - view.origin[0]).astype(np.float32)
    dv = (v - view.origin[1]).astype(np.float32)
    r = np.hypot(du, dv)
    ai = np.round(np.arctan2(dv, du) * np.float32(N_AZ / (2 * np.pi))).astype(np.int64) % N_AZ
    n_near = int(np.count_nonzero(view.ranges < FAR_FROM_M))
    ri = np.round((r - view.ranges[0]) / RANGE_STEP_M).astype(np.int64)
    ri = np.where(ri < n_near, ri, n_near + np.round((r - FAR_FROM_M) / FAR_STEP_M).astype(np.int64))
    ri = np.where((ri < 0) | (ri >= len(view.ranges)), -1, ri)
    return ai, ri, r


@dataclass
class MapLayers:
    """One X-Racer map in its own grid: (size, size) arrays, axis 0 = x, axis 1 = y."""

    elevation: NDArray[np.float32]
    risk: NDArray[np.float32]
    confidence: NDArray[np.float32]


def stack_memory_s(cfg: SynthConfig, speed_mps: float) -> float:
    """Return the time span [s] whose returns a map of the stack holds at ``speed_mps``: the
    last ``stack_memory_s``, but of at most ``stack_memory_m`` of travel (thinner at speed)."""
    return min(cfg.stack_memory_s, cfg.stack_memory_m / max(speed_mps, 1e-3))


def stack_revolutions(cfg: SynthConfig, speed_mps: float) -> float:
    """Return how many lidar revolutions a map of the stack holds at ``speed_mps``."""
    return cfg.lidar_rate_hz * stack_memory_s(cfg, speed_mps)


def xracer_map(
    cfg: SynthConfig,
    terrain: Terrain,
    view: LidarView,
    cell_world_uv: tuple[NDArray, NDArray],
    z_world_to_map: float,
    rng: np.random.Generator,
    cell_m: float = 0.2,
    speed_mps: float = 0.0,
    memory: tuple[LidarView, ...] = (),
    fill_m: float = 0.0,
) -> MapLayers:
    """Return the simulated X-Racer layers at cells whose world positions are given.

    Elevations are mapped to the map frame by adding ``z_world_to_map`` (the odometry's
    z offset), so odometry z drift appears in the published map as on a real robot. Where
    the lidar hits a crown or a bush, the map holds the ground under it, or with
    ``canopy`` the crown's top (as a real stack's elevation map does).

    With ``confidence_model: density`` a cell of edge ``cell_m`` is seen only where
    returns land in it (in its ``stack_voxel_m`` column when the cell is smaller): their count is Poisson drawn with the mean of the views' densities
    over the cell and the revolutions the map holds at ``speed_mps``, shared evenly by
    ``view`` and the ``memory`` views (the lidar at earlier poses of the stack's memory:
    its maps aggregate the returns over time); its confidence is
    ``(1 - exp(-count / stack_points_conf)) * 0.5 ** (range / confidence_range_m)``, range
    being the nearest a view that sees the cell came to it, its elevation noise falls as
    1 / sqrt(count). What it sees is blurred over a footprint growing with range
    (``stack_smoothing_m``), and ``fill_m`` > 0 extrapolates the map into unseen cells up
    to that far from a seen one (``extrapolate``); 0 holds the last ground seen along each
    ray instead.
    """
    if cfg.confidence_model == "density":
        return _density_map(cfg, terrain, (view, *memory), cell_world_uv, z_world_to_map, rng, cell_m, speed_mps, fill_m)
    u, v = cell_world_uv
    ground, risk, surface = terrain.sample(u, v, ("ground", "risk", "surface")) if cfg.canopy else (*terrain.sample(u, v, ("ground", "risk")), None)
    ai, ri, r = polar_lookup(view, u, v)
    ok = ri >= 0
    flat = ai * len(view.ranges) + np.maximum(ri, 0)  # one index into the (N_AZ, N_R) view arrays
    seen_s = ok & view.seen_surface.ravel().take(flat)
    seen_g = ok & view.seen_ground.ravel().take(flat)
    held = np.where(ok, view.held_ground.ravel().take(flat), np.float32(np.nan))
    r = r.astype(np.float32)
    noise_sd = np.float32(cfg.elevation_noise_m) + np.float32(cfg.elevation_noise_per_m) * r
    seen = ground if surface is None else np.where(seen_s & ~seen_g, surface, ground)  # canopy: the crown top is what is seen
    elev = np.where(seen_g | seen_s, seen + rng.standard_normal(u.shape, dtype=np.float32) * noise_sd, held)
    conf = np.exp2(r * np.float32(-1.0 / cfg.confidence_range_m))  # 0.5 ** (r / confidence_range_m)
    conf = np.clip(conf * (1 + np.float32(0.05) * rng.standard_normal(u.shape, dtype=np.float32)), 0, 1)
    conf = np.where(seen_s, np.maximum(conf, np.float32(0.12)), np.float32(0.0))
    risk_obs = np.clip(risk + np.float32(0.03) * rng.standard_normal(u.shape, dtype=np.float32), 0, 1)
    nan = np.isnan(elev)
    return MapLayers(
        elevation=(elev + np.float32(z_world_to_map)).astype(np.float32, copy=False),
        risk=np.where(nan, np.float32(np.nan), np.where(seen_s, risk_obs, np.float32(0.0))).astype(np.float32, copy=False),
        confidence=np.where(nan, np.float32(0.0), conf).astype(np.float32, copy=False),
    )


def _density_map(cfg: SynthConfig, terrain: Terrain, views: tuple[LidarView, ...], cell_world_uv: tuple[NDArray, NDArray],
                 z_world_to_map: float, rng: np.random.Generator, cell_m: float, speed_mps: float, fill_m: float) -> MapLayers:
    """``xracer_map`` with confidence from the returns in each cell (the paper world)."""
    if any(w.density is None for w in views):
        raise ValueError("xracer_map: the density model needs views made with confidence_model 'density'")
    u, v = cell_world_uv
    ground, risk, surface = terrain.sample(u, v, ("ground", "risk", "surface")) if cfg.canopy else (*terrain.sample(u, v, ("ground", "risk")), None)
    area = max(cell_m, cfg.stack_voxel_m) ** 2  # the stack counts returns per voxel column at least
    per_view = np.float32(area * stack_revolutions(cfg, speed_mps) / len(views))
    mean = np.zeros(u.shape, np.float32)
    seen_s = np.zeros(u.shape, bool)
    seen_g = np.zeros(u.shape, bool)
    r = np.full(u.shape, np.inf, np.float32)
    for j, view in enumerate(views):
        ai, ri, rj = polar_lookup(view, u, v)
        ok = ri >= 0
        flat = ai * len(view.ranges) + np.maximum(ri, 0)
        dens = np.where(ok, view.density.ravel().take(flat), np.float32(0.0))
        mean += dens * per_view
        seen_s |= ok & view.seen_surface.ravel().take(flat)
        seen_g |= ok & view.seen_ground.ravel().take(flat)
        r = np.where(dens > 0, np.minimum(r, rj), r)
        if j == 0:
            held = np.where(ok, view.held_ground.ravel().take(flat), np.float32(np.nan))
            r0 = rj
    r = np.where(np.isfinite(r), r, r0).astype(np.float32)
    count = rng.poisson(mean).astype(np.float32)
    hit = count > 0
    seen_s &= hit
    seen_g &= hit
    noise_sd = (np.float32(cfg.elevation_noise_m) + np.float32(cfg.elevation_noise_per_m) * r) / np.sqrt(np.maximum(count, 1))
    seen = ground if surface is None else np.where(seen_s & ~seen_g, surface, ground)
    seen = range_smoothed(seen, r, cfg.stack_smoothing_m, cell_m)
    elev = seen + rng.standard_normal(u.shape, dtype=np.float32) * noise_sd
    conf = (1 - np.exp(-count / np.float32(cfg.stack_points_conf))) * np.exp2(r * np.float32(-1.0 / cfg.confidence_range_m))
    conf = np.clip(conf * (1 + np.float32(0.05) * rng.standard_normal(u.shape, dtype=np.float32)), 0, 1)
    conf = np.where(seen_s, conf, np.float32(0.0))
    if fill_m > 0:
        slope_err = rng.standard_normal(2) * cfg.stack_fill_slope_sd
        elev, guess = extrapolate(np.where(seen_g | seen_s, elev, np.float32(np.nan)), cell_m, fill_m, slope_err)
        conf = np.where(seen_s, conf, np.float32(cfg.stack_fill_confidence) * guess)
    else:
        elev = np.where(seen_g | seen_s, elev, held)
    risk_obs = np.clip(risk + np.float32(0.03) * rng.standard_normal(u.shape, dtype=np.float32), 0, 1)
    nan = np.isnan(elev)
    return MapLayers(
        elevation=(elev + np.float32(z_world_to_map)).astype(np.float32, copy=False),
        risk=np.where(nan, np.float32(np.nan), np.where(seen_s, risk_obs, np.float32(0.0))).astype(np.float32, copy=False),
        confidence=np.where(nan, np.float32(0.0), conf).astype(np.float32, copy=False),
    )


SMOOTH_AT_M = 50.0  # range at which the stack's footprint has std stack_smoothing_m [m]
SLOPE_WINDOW_M = 2.0  # std of the window the stack averages the local slope of what it saw over [m]
MAX_FILL_SLOPE = 0.6  # steepest slope the stack extrapolates along [m/m]


def range_smoothed(z: NDArray[np.float32], r: NDArray[np.float32], sigma_m: float, cell_m: float) -> NDArray[np.float32]:
    """Return the grid ``z`` blurred over a Gaussian footprint whose std grows linearly with
    the range ``r`` [m] (``sigma_m`` at SMOOTH_AT_M): blends of ``z`` and ``z`` blurred by
    ``sigma_m`` up to SMOOTH_AT_M, then of the blur by ``sigma_m`` and by twice that."""
    if sigma_m <= 0:
        return z
    from scipy.ndimage import gaussian_filter

    b1 = gaussian_filter(z, sigma_m / cell_m, mode="nearest")
    b2 = gaussian_filter(z, 2 * sigma_m / cell_m, mode="nearest")
    w = np.clip(r * np.float32(1 / SMOOTH_AT_M), 0, 2)
    near = z + np.minimum(w, 1) * (b1 - z)
    return np.where(w <= 1, near, b1 + (w - 1) * (b2 - b1)).astype(np.float32, copy=False)


def extrapolate(elev: NDArray[np.float32], cell_m: float, fill_m: float, slope_err: NDArray) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Return (``elev`` with its NaN cells within ``fill_m`` of a finite one filled, how much
    each cell is a guess's weight: 1 next to a seen cell falling to 0 at ``fill_m``, 0 on
    seen cells). A filled cell continues its nearest seen cell along the local slope of the
    seen cells around it (their gradient averaged over SLOPE_WINDOW_M, which flattens toward
    the edge of what was seen; at most MAX_FILL_SLOPE), tilted
    by ``slope_err`` (the map's slope error, per grid axis): a guess errs more the farther
    it is from what was seen and the more the ground curves."""
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    known = np.isfinite(elev)
    none = np.zeros(elev.shape, np.float32)
    if not known.any() or known.all():
        return elev, none
    d, (I, J) = distance_transform_edt(~known, return_indices=True)
    d_m = (d * cell_m).astype(np.float32)
    fill = ~known & (d_m <= fill_m)
    s = max(1.0, SLOPE_WINDOW_M / cell_m)
    w = gaussian_filter(known.astype(np.float32), s, mode="constant")
    zs = gaussian_filter(np.where(known, elev, np.float32(0.0)), s, mode="constant") / np.maximum(w, np.float32(1e-6))
    gx, gy = np.gradient(zs, cell_m)
    gx = np.clip(gx[I, J] + np.float32(slope_err[0]), -MAX_FILL_SLOPE, MAX_FILL_SLOPE)
    gy = np.clip(gy[I, J] + np.float32(slope_err[1]), -MAX_FILL_SLOPE, MAX_FILL_SLOPE)
    ii, jj = np.indices(elev.shape)
    guessed = elev[I, J] + (gx * (ii - I) + gy * (jj - J)) * np.float32(cell_m)
    out = np.where(fill, guessed, elev).astype(np.float32, copy=False)
    return out, np.where(fill, 1 - d_m / np.float32(max(fill_m, 1e-9)), np.float32(0.0)).astype(np.float32, copy=False)


def map_cells_world(grid: GridSpec, center_odom_xy: NDArray, odom, k: int) -> tuple[NDArray, NDArray]:
    """Return world (u, v) of the cells of an odom-aligned grid centred at ``center_odom_xy``,
    through ``odom.odom_to_world`` at pose ``k``. That map is a rotation and shift in the
    plane, so the grid maps as outer sums of its two axes (the same numbers, no (n, n, 3)
    temporaries)."""
    c = -0.5 * grid.length_m + (np.arange(grid.size) + 0.5) * grid.resolution_m
    dx = (center_odom_xy[0] + c) - odom.p_odom[k, 0]
    dy = (center_odom_xy[1] + c) - odom.p_odom[k, 1]
    cs, sn = np.cos(-odom.dyaw[k]), np.sin(-odom.dyaw[k])
    u = (cs * dx[:, None] - sn * dy[None, :]) + odom.p_true[k, 0]
    v = (sn * dx[:, None] + cs * dy[None, :]) + odom.p_true[k, 1]
    return u, v


def voxelize(points: NDArray, voxel_m: float) -> NDArray[np.float32]:
    """Return the centres of the occupied voxels of edge ``voxel_m`` (sorted, unique)."""
    keys = np.floor(points / voxel_m).astype(np.int64) + (1 << 20)
    if len(keys) and (keys.min() < 0 or keys.max() >= 1 << 21):
        raise ValueError("voxelize: points farther than 400 km from the origin")
    flat = np.unique((keys[:, 0] << 42) | (keys[:, 1] << 21) | keys[:, 2])
    keys = np.column_stack([flat >> 42, (flat >> 21) & ((1 << 21) - 1), flat & ((1 << 21) - 1)]) - (1 << 20)
    return ((keys + 0.5) * voxel_m).astype(np.float32)


def view_points(view: LidarView, rng: np.random.Generator | None = None, revolutions: float = 1.0) -> NDArray[np.float64]:
    """Return the world points (N, 3) the lidar hit in ``view``: every visible sample, or
    with ``rng`` and a view with densities, those that returns of ``revolutions`` land on
    (each with the probability that at least one does)."""
    seen = view.seen_surface
    if rng is not None and view.density is not None:
        step = np.diff(view.ranges, append=view.ranges[-1] + (view.ranges[-1] - view.ranges[-2]))
        area = view.ranges * step * (2 * np.pi / len(view.az))  # [m2] of a polar sample
        p_hit = -np.expm1(-view.density * (area * revolutions)[None, :])
        seen = seen & (rng.random(seen.shape, dtype=np.float32) < p_hit)
    a, k = np.nonzero(seen)
    r = view.ranges[k]
    return np.column_stack([view.origin[0] + np.cos(view.az[a]) * r, view.origin[1] + np.sin(view.az[a]) * r, view.surface[a, k]])


LIDAR_MOUNT = (0.0, 0.0, 2.0)  # the lidar in base_link [m]
