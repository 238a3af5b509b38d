"""Per-sample DEM placement: the drive's GNSS prior, its vertical offset against the DEM,
and for each sample an ICP refinement of the prior and the decision to keep or reject it.

Each sample starts from the previous accepted sample's placement (``DrivePlacement``
keeps it), else from the drive's GNSS fit.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.bag.poses import PoseTrack
from gtgen.config import GtgenConfig
from gtgen.dem.fit import PlanarFit, gnss_fit
from gtgen.dem.icp import GridNearest, IcpResult, icp_4dof
from gtgen.dem.tiles import DemSource, TileOffset, sample_bilinear
from gtgen.errors import DemError
from gtgen.geometry import invert, yaw_transform
from gtgen.grids import grid_xy
from gtgen.storage.drive import DriveSamples, DriveStore, Fixes
from gtgen.storage.fused import FusedStore

MIN_ICP_POINTS = 100
COARSE = 3.0  # correspondence distance of the first pass from a drifted prior, in icp_max_distance_m


def dem_patch(dem: DemSource, T_crs_target: NDArray, X: NDArray, Y: NDArray, margin: float = 5.0,
              at: NDArray[np.bool_] | None = None) -> NDArray[np.float32]:
    """Return DEM heights in the target frame at target cells (X, Y) (NaN where no DEM), or
    only at the cells ``at`` selects (1-D, in their order): the same values as the whole
    patch's there (the DEM is read over the whole patch either way)."""
    R, t = T_crs_target[:3, :3], T_crs_target[:3, 3]
    E = R[0, 0] * X + R[0, 1] * Y + t[0]
    N = R[1, 0] * X + R[1, 1] * Y + t[1]
    grid, origin = dem.read(E.min() - margin, N.min() - margin, E.max() + margin, N.max() + margin)
    if at is not None:
        E, N = E[at], N[at]
    return sample_bilinear(grid, origin, E, N) - np.float32(t[2])


def _normals(Z: NDArray, res: float) -> NDArray:
    gx, gy = np.gradient(Z, res)
    n = np.stack([-gx, -gy, np.ones_like(Z)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _check_overlap(dem: DemSource, fit: PlanarFit, track: PoseTrack, dem_dir: Path) -> None:
    en = fit.apply_xy(track.pos[:, :2])
    l, b, r, t = dem.bounds()
    inside = (en[:, 0] > l) & (en[:, 0] < r) & (en[:, 1] > b) & (en[:, 1] < t)
    if not inside.any():
        raise DemError(
            f"DEM '{dem_dir}' does not cover the drive: drive spans E {en[:, 0].min():.0f}..{en[:, 0].max():.0f}, "
            f"N {en[:, 1].min():.0f}..{en[:, 1].max():.0f} in {dem.crs}; tiles span E {l:.0f}..{r:.0f}, N {b:.0f}..{t:.0f}"
        )


def _dz_against_dem(dem: DemSource, fit: PlanarFit, X: NDArray, Y: NDArray, samples: DriveSamples, fused: FusedStore,
                    n: int = 24) -> float:
    """Return the median DEM height minus odom height over observed short cells of a few samples."""
    S = len(samples)
    region, elev = fused.grid("short", "region"), fused.grid("short", "elevation_m")
    diffs = []
    for k in np.unique(np.linspace(0, S - 1, min(n, S)).astype(int)):
        reg, el = region[k], elev[k]
        obs = codes.observed(reg)
        if not obs.any():
            continue
        T = yaw_transform(fit.tx, fit.ty, 0.0, fit.yaw) @ yaw_transform(*samples.pos_odom_m[k], samples.yaw_odom_rad[k])
        d = (dem_patch(dem, T, X, Y) - el)[obs]  # both relative to the base z
        diffs.append(d[np.isfinite(d)])
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    if len(d) < 50:
        raise DemError("the DEM has no valid cells under the drive's observed terrain: wrong DEM folder, wrong area, or nodata")
    return float(np.median(d))


@dataclass(frozen=True)
class Placement:
    """One sample's outcome: its reason code (OK if kept), the ICP result if ICP ran, its
    placement after ICP (``T_crs_target``) and the signals the decision read."""

    reason: int
    icp: IcpResult | None = None
    T_crs_target: NDArray | None = None
    signals: dict[str, float] = field(default_factory=dict)


def vegetation(d: NDArray, mask: NDArray, vegetation_m: float) -> NDArray[np.bool_]:
    """Return the cells of ``mask`` in blobs standing more than ``vegetation_m`` above the
    DEM (``d``: label minus DEM, per cell) after the median offset: a blob, because noise
    spikes come alone while crowns, bushes and berms cover neighbouring cells."""
    from scipy.ndimage import binary_dilation, binary_opening

    high = mask & (d - np.median(d[mask]) > vegetation_m)
    if not high.any():
        return high
    return binary_dilation(binary_opening(high, np.ones((2, 2), bool)), iterations=1) & mask


class DrivePlacement:
    """A drive's placement in the DEM's CRS, refined sample by sample (see ``place``)."""

    def __init__(self, cfg: GtgenConfig, dem: DemSource, fit: PlanarFit, dz_dem: float, gnss: tuple[NDArray, NDArray],
                 gnss_sd_m: float = np.nan) -> None:
        self.cfg, self.dem, self.fit, self.dz_dem = cfg, dem, fit, dz_dem
        self.gnss_sd_m = gnss_sd_m  # the fixes' stated horizontal std per axis [m] (median; NaN: not stated)
        gs = cfg.grids.short
        self.X, self.Y = grid_xy(gs.size, gs.resolution_m)
        self.T_fit = yaw_transform(fit.tx, fit.ty, dz_dem, fit.yaw)  # T_crs_odom of the GNSS fit
        self.T_prior = self.T_fit  # T_crs_odom the next sample starts from
        self.chained = False  # the prior is a kept sample's placement (else the GNSS fit's)
        self.kept_at_m = 0.0  # odometry distance of the last kept sample
        self.gnss_t, self.gnss_xy = gnss  # (t_ns, (odom x, y, CRS E, N)) of the usable fixes
        n = len(dem.tile_names)
        # per tile: observed ground cells over it at the kept placements, and those that disagree with it
        self.tile_cells, self.tile_bad = np.zeros(n, np.int64), np.zeros(n, np.int64)

    @classmethod
    def of_drive(cls, cfg: GtgenConfig, drive: DriveStore, fused: FusedStore, dem: DemSource, dem_dir: Path) -> DrivePlacement:
        """Fit the drive's odometry to GNSS in the working CRS, check that the DEM covers it,
        and estimate the odom -> DEM vertical offset."""
        p = drive.poses()
        track = PoseTrack(p.t_ns, p.pos_odom_m, p.quat_odom_xyzw, int(cfg.extract.pose_tolerance_s * 1e9))
        fixes = drive.gnss()
        fit = gnss_fit(cfg, fixes, track, dem.crs)
        _check_overlap(dem, fit, track, dem_dir)
        gs = cfg.grids.short
        dz = _dz_against_dem(dem, fit, *grid_xy(gs.size, gs.resolution_m), drive.samples, fused)
        var = fixes.var_enu_m2[fixes.usable, :2].mean(axis=1) if len(fixes.t_ns) else np.zeros(0)
        var = var[np.isfinite(var) & (var > 0)]
        return cls(cfg, dem, fit, dz, gnss_fixes(fixes, track, dem.crs), float(np.sqrt(np.median(var))) if len(var) else np.nan)

    def without(self, tiles: frozenset[int]) -> DrivePlacement:
        """Return a fresh placement of the drive (same GNSS fit and vertical offset) that does
        not read ``tiles``."""
        return self.adjusted(tiles, None)

    def adjusted(self, tiles: frozenset[int], offsets: dict[int, TileOffset] | None) -> DrivePlacement:
        """Return a fresh placement of the drive (same GNSS fit and vertical offset) that does
        not read ``tiles`` either, and reads the tiles of ``offsets`` put back (these alone;
        None: the same as this one)."""
        return DrivePlacement(self.cfg, self.dem.adjusted(tiles, offsets), self.fit, self.dz_dem, (self.gnss_t, self.gnss_xy), self.gnss_sd_m)

    @property
    def geoid_offset_m(self) -> float:
        """Ellipsoidal minus DEM height: the geoid separation the fit found [m]."""
        return self.fit.dz_gnss - self.dz_dem

    def alignment(self) -> dict[str, float | int]:
        """Return the drive-level alignment, as the dataset's attributes record it."""
        f = self.fit
        return {"gnss_yaw_rad": f.yaw, "gnss_tx_m": f.tx, "gnss_ty_m": f.ty, "gnss_rms_m": f.rms_m, "gnss_used": f.n_used,
                "gnss_outliers": f.n_outliers, "dz_dem_m": self.dz_dem, "geoid_offset_m": self.geoid_offset_m}

    def place(self, k: int, t_ns: int, pos: NDArray, yaw: float, region: NDArray, elev: NDArray, distance_m: float) -> Placement:
        """Refine sample ``k`` (time ``t_ns``, base at ``pos``, ``yaw`` in odom, ``distance_m``
        travelled; its fused short ``region`` and ``elev``) by ICP against the DEM from its
        prior, and keep it or say why not. A kept sample's placement is the prior of the next."""
        dc = self.cfg.dem
        T_odom_target = yaw_transform(*pos, yaw)
        T_prior = self.T_prior @ T_odom_target
        dem = dem_patch(self.dem, T_prior, self.X, self.Y)
        obs = codes.observed(region) & np.isfinite(elev)
        # a sample mostly on tiles set aside is not refined (ICP on the cells off them drifts
        # along the tiles' edge: measured on configs/adversity.yaml, worse than odometry
        # alone): it keeps the last kept placement carried by odometry while that is recent
        aside = bool(self.dem.exclude) and bool(obs.any()) and self._on_set_aside(T_prior, obs) > 0.5
        if not aside and not np.isfinite(dem).any():
            return Placement(codes.NO_DEM)
        if obs.sum() < MIN_ICP_POINTS:
            return Placement(codes.TOO_FEW_POINTS)
        age = abs(distance_m - self.kept_at_m) if self.chained else np.inf  # travel since the prior's kept sample
        if aside and not (self.chained and age <= dc.carry_over_m):
            return Placement(codes.SUSPECT_TILE, T_crs_target=T_prior)
        both = obs & np.isfinite(dem)  # cells without DEM (set-aside tiles, gaps) have nothing to fit
        d = np.where(both, elev - dem, 0.0)
        veg = vegetation(d, both, dc.vegetation_m) if both.any() else both
        ground = both & ~veg
        extra = {"vegetation_share": float(veg.sum() / max(obs.sum(), 1)), "prior_age_m": float(age)}
        if aside:  # kept where odometry carries the prior; the chain is not renewed: its age keeps growing
            return Placement(codes.OK, None, T_prior, {**self._signals(None, T_prior, T_odom_target, t_ns, elev, ground, dem), **extra})
        stale = self.chained and age > dc.judge_within_m  # odometry has drifted since
        # ICP fits the ground observed at t (obs PC): cells first observed later carry the
        # odometry's drift since t and would pull the placement of the frame at t off by it
        # (on configs/adversity.yaml: unobserved labels 0.075 / 0.070 m against 0.117 / 0.111 m
        # fitting every observed cell)
        src = ground & (region == codes.OBS_PC)
        res = self._icp(k, src if src.sum() >= MIN_ICP_POINTS else ground, elev, dem, coarse=stale)
        T = T_prior @ res.T
        aligned = np.full(self.X.shape, np.nan, np.float32)  # read only on the ground cells (signals, tile counts)
        aligned[ground] = dem_patch(self.dem, T, self.X, self.Y, at=ground)
        sig = {**self._signals(res, T, T_odom_target, t_ns, elev, ground, aligned), **extra}
        reason = self._decide(res, sig, dc.drift_allowance * age if self.chained else 0.0)
        if reason == codes.OK:
            self._count_tiles(T, ground, elev, aligned)
            self.T_prior = T @ invert(T_odom_target)
            self.chained, self.kept_at_m = True, distance_m
        return Placement(reason, res, T, sig)

    def track_offsets(self, T: NDArray, T_odom_target: NDArray, t_ns: int) -> tuple[NDArray, NDArray]:
        """Return a placement ``T`` (of the target at ``T_odom_target`` in odom, time ``t_ns``)
        as its horizontal offsets (E, N) [m]: from the drive's GNSS fit carried by odometry, and
        from the window's GNSS fixes (their median offset; NaN with fewer than
        ``dem.min_window_fixes``)."""
        r = self._fix_residuals(T, T_odom_target, self._window(t_ns))
        g = np.median(r, axis=0) if r is not None else np.full(2, np.nan)
        return T[:2, 3] - (self.T_fit @ T_odom_target)[:2, 3], g

    def _window(self, t_ns: int) -> NDArray[np.bool_]:
        """Return which GNSS fixes lie within ``dem.gnss_window_s`` of ``t_ns``."""
        return np.abs(self.gnss_t - t_ns) <= int(self.cfg.dem.gnss_window_s * 1e9)

    def _fix_residuals(self, T: NDArray, T_odom_target: NDArray, win: NDArray[np.bool_]) -> NDArray | None:
        """Return the fixes ``win`` (``_window``) at placement ``T`` less where GNSS put them,
        (n, 2) (E, N) [m]; None with fewer than ``dem.min_window_fixes``."""
        if win.sum() < self.cfg.dem.min_window_fixes:
            return None
        T_crs_odom = T @ invert(T_odom_target)
        xy = self.gnss_xy[win]
        return xy[:, :2] @ T_crs_odom[:2, :2].T + T_crs_odom[:2, 3] - xy[:, 2:]

    def _icp(self, k: int, src_mask: NDArray, elev: NDArray, dem: NDArray, coarse: bool = False) -> IcpResult:
        """ICP of the masked observed cells onto the DEM patch; ``coarse`` first matches within
        COARSE times the correspondence distance, for a prior that may be metres off."""
        dc = self.cfg.dem
        src = np.column_stack([self.X[src_mask], self.Y[src_mask], elev[src_mask]])
        if len(src) > dc.icp_max_points:
            src = src[np.random.default_rng(k).choice(len(src), dc.icp_max_points, replace=False)]  # per-sample seed: order-free
        tgt_mask = np.isfinite(dem)
        tgt = np.column_stack([self.X[tgt_mask], self.Y[tgt_mask], dem[tgt_mask]])
        nrm = _normals(np.where(tgt_mask, dem, np.nanmedian(dem)), self.cfg.grids.short.resolution_m)[tgt_mask]
        near = GridNearest(self.X[:, 0], self.Y[0], dem)  # the patch is a height field on the short grid
        init = icp_4dof(src, tgt, nrm, COARSE * dc.icp_max_distance_m, dc.icp_iterations, nearest=near).T if coarse else None
        return icp_4dof(src, tgt, nrm, dc.icp_max_distance_m, dc.icp_iterations, init=init, nearest=near)

    def _signals(self, res: IcpResult | None, T: NDArray, T_odom_target: NDArray, t_ns: int, elev: NDArray, ground: NDArray,
                 aligned: NDArray) -> dict[str, float]:
        """The evidence on a placement ``T``: the correction over the prior, the disagreement of
        the observed ground with the DEM there (``aligned``), and the offset of the window's
        GNSS fixes."""
        dc = self.cfg.dem
        C = np.eye(4) if res is None else res.T  # None: placed by odometry alone
        g = ground & np.isfinite(aligned)
        dev = np.abs(elev[g] - aligned[g])
        win = self._window(t_ns)
        r = self._fix_residuals(T, T_odom_target, win)
        offset = float(np.median(np.linalg.norm(r, axis=1))) if r is not None else np.nan
        return {"correction_xy_m": float(np.hypot(C[0, 3], C[1, 3])), "correction_z_m": float(abs(C[2, 3])),
                "correction_yaw_deg": float(abs(np.degrees(np.arctan2(C[1, 0], C[0, 0])))),
                "disagreement": float((dev > dc.disagreement_m).mean()) if len(dev) else (1.0 if res is not None else np.nan),
                "gnss_offset_m": offset, "gnss_fixes": int(win.sum())}

    def _decide(self, res: IcpResult, sig: dict[str, float], allowed_m: float = 0.0) -> int:
        """Return the reason code of a placement (``allowed_m``: the drift since the last
        kept sample, added to the correction limits)."""
        dc = self.cfg.dem
        if res.fitness < dc.min_fitness:
            return codes.LOW_FITNESS
        if res.rmse_m > dc.max_rmse_m:
            return codes.HIGH_RMSE
        # a prior from the GNSS fit is only as good as GNSS: the first sample may move far
        if self.chained and (sig["correction_xy_m"] > dc.max_correction_m + allowed_m
                             or sig["correction_z_m"] > dc.max_correction_z_m + allowed_m
                             or sig["correction_yaw_deg"] > dc.max_correction_yaw_deg):
            return codes.LARGE_CORRECTION
        if sig["disagreement"] > dc.max_disagreement:
            return codes.DEM_DISAGREES
        if np.isfinite(sig["gnss_offset_m"]) and sig["gnss_offset_m"] > dc.max_gnss_offset_m:
            return codes.GNSS_DISAGREES
        return codes.OK

    def _count_tiles(self, T: NDArray, ground: NDArray, elev: NDArray, aligned: NDArray) -> None:
        """Count per tile the observed ground cells over it at a kept placement ``T``
        (``aligned``: the DEM there) and those that disagree with it (beyond the sample's
        median offset)."""
        m = ground & np.isfinite(aligned)
        if m.sum() < MIN_ICP_POINTS:
            return
        r = elev[m] - aligned[m]
        tile = self._tiles_at(T, m)
        on = tile >= 0
        n = len(self.tile_cells)
        self.tile_cells += np.bincount(tile[on], minlength=n)
        self.tile_bad += np.bincount(tile[on], weights=np.abs(r - np.median(r))[on] > self.cfg.dem.disagreement_m, minlength=n).astype(np.int64)

    def _tiles_at(self, T: NDArray, mask: NDArray) -> NDArray[np.int64]:
        """Return the tile index of each cell of ``mask`` at placement ``T``, -1 off every tile."""
        E = T[0, 0] * self.X[mask] + T[0, 1] * self.Y[mask] + T[0, 3]
        N = T[1, 0] * self.X[mask] + T[1, 1] * self.Y[mask] + T[1, 3]
        return self.dem.tile_of(E, N)

    def _on_set_aside(self, T: NDArray, mask: NDArray) -> float:
        """Return the share of the cells ``mask`` that lie on tiles set aside, at placement ``T``."""
        return float(np.isin(self._tiles_at(T, mask), list(self.dem.exclude)).mean())


def gnss_fixes(fixes: Fixes, track: PoseTrack, crs: str) -> tuple[NDArray, NDArray]:
    """Return the usable fixes of a drive: stamps (n,), and (odom x, y, CRS E, N) (n, 4)."""
    from pyproj import Transformer

    ok = fixes.usable & track.covered(fixes.t_ns)
    E, N = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(fixes.lon_deg[ok], fixes.lat_deg[ok])
    pos, _ = track.interpolate(fixes.t_ns[ok])
    return fixes.t_ns[ok], np.column_stack([pos[:, :2], E, N])
