"""Per-sample DEM placement: the drive's GNSS prior, its vertical offset against the DEM,
and for each sample an ICP refinement of the prior and the decision to keep or reject it.

Each sample starts from the previous accepted sample's placement (``DrivePlacement``
keeps it), else from the drive's GNSS fit.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.bag.poses import PoseTrack
from gtgen.config import GtgenConfig
from gtgen.dem.fit import PlanarFit, gnss_fit
from gtgen.dem.icp import IcpResult, icp_4dof
from gtgen.dem.tiles import DemMosaic, sample_bilinear
from gtgen.errors import DemError
from gtgen.geometry import grid_xy, invert, quat_to_yaw, yaw_transform

MIN_ICP_POINTS = 100


def dem_patch(dem: DemMosaic, T_crs_target: NDArray, X: NDArray, Y: NDArray, margin: float = 5.0) -> NDArray[np.float32]:
    """Return DEM heights in the target frame at target cells (X, Y) (NaN where no DEM)."""
    R, t = T_crs_target[:3, :3], T_crs_target[:3, 3]
    E = R[0, 0] * X + R[0, 1] * Y + t[0]
    N = R[1, 0] * X + R[1, 1] * Y + t[1]
    grid, origin = dem.read(E.min() - margin, N.min() - margin, E.max() + margin, N.max() + margin)
    return sample_bilinear(grid, origin, E, N) - np.float32(t[2])


def _normals(Z: NDArray, res: float) -> NDArray:
    gx, gy = np.gradient(Z, res)
    n = np.stack([-gx, -gy, np.ones_like(Z)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _check_overlap(dem: DemMosaic, fit: PlanarFit, track: PoseTrack, dem_dir: Path) -> None:
    en = fit.apply_xy(track.pos[:, :2])
    l, b, r, t = dem.bounds()
    inside = (en[:, 0] > l) & (en[:, 0] < r) & (en[:, 1] > b) & (en[:, 1] < t)
    if not inside.any():
        raise DemError(
            f"DEM folder '{dem_dir}' does not cover the drive: drive spans E {en[:, 0].min():.0f}..{en[:, 0].max():.0f}, "
            f"N {en[:, 1].min():.0f}..{en[:, 1].max():.0f} in {dem.crs}; tiles span E {l:.0f}..{r:.0f}, N {b:.0f}..{t:.0f}"
        )


def _dz_against_dem(dem: DemMosaic, fit: PlanarFit, X: NDArray, Y: NDArray, drive: Any, fused: Any, n: int = 24) -> float:
    """Return the median DEM height minus odom height over observed short cells of a few samples."""
    S = fused["fused/short/region"].shape[0]
    pos = drive["samples/pos_odom_m"][:]
    yaw = quat_to_yaw(drive["samples/quat_odom_xyzw"][:])
    diffs = []
    for k in np.unique(np.linspace(0, S - 1, min(n, S)).astype(int)):
        reg = fused["fused/short/region"][k]
        el = fused["fused/short/elevation_m"][k]
        obs = codes.observed(reg)
        if not obs.any():
            continue
        T = yaw_transform(fit.tx, fit.ty, 0.0, fit.yaw) @ yaw_transform(*pos[k], yaw[k])
        d = (dem_patch(dem, T, X, Y) - el)[obs]  # both relative to the base z
        diffs.append(d[np.isfinite(d)])
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    if len(d) < 50:
        raise DemError("the DEM has no valid cells under the drive's observed terrain: wrong DEM folder, wrong area, or nodata")
    return float(np.median(d))


@dataclass(frozen=True)
class Placement:
    """One sample's outcome: its reason code (OK if kept), and the ICP result if ICP ran;
    ``T_crs_target`` is the placement after ICP of a kept sample."""

    reason: int
    icp: IcpResult | None = None
    T_crs_target: NDArray | None = None


class DrivePlacement:
    """A drive's placement in the DEM's CRS, refined sample by sample."""

    def __init__(self, cfg: GtgenConfig, dem: DemMosaic, fit: PlanarFit, dz_dem: float) -> None:
        self.cfg, self.dem, self.fit, self.dz_dem = cfg, dem, fit, dz_dem
        gs = cfg.grids.short
        self.X, self.Y = grid_xy(gs.size, gs.resolution_m)
        self.T_prior = yaw_transform(fit.tx, fit.ty, dz_dem, fit.yaw)  # T_crs_odom

    @classmethod
    def of_drive(cls, cfg: GtgenConfig, drive: Any, fused: Any, dem: DemMosaic, dem_dir: Path) -> DrivePlacement:
        """Fit the drive's odometry to GNSS in the working CRS, check that the DEM covers it,
        and estimate the odom -> DEM vertical offset."""
        track = PoseTrack(drive["poses/t_ns"][:], drive["poses/pos_odom_m"][:], drive["poses/quat_odom_xyzw"][:],
                          int(cfg.extract.pose_tolerance_s * 1e9))
        fit = gnss_fit(cfg, drive, track, dem.crs)
        _check_overlap(dem, fit, track, dem_dir)
        gs = cfg.grids.short
        return cls(cfg, dem, fit, _dz_against_dem(dem, fit, *grid_xy(gs.size, gs.resolution_m), drive, fused))

    @property
    def geoid_offset_m(self) -> float:
        """Ellipsoidal minus DEM height: the geoid separation the fit found [m]."""
        return self.fit.dz_gnss - self.dz_dem

    def alignment(self) -> dict[str, float | int]:
        """Return the drive-level alignment, as the dataset's attributes record it."""
        f = self.fit
        return {"gnss_yaw_rad": f.yaw, "gnss_tx_m": f.tx, "gnss_ty_m": f.ty, "gnss_rms_m": f.rms_m, "gnss_used": f.n_used,
                "gnss_outliers": f.n_outliers, "dz_dem_m": self.dz_dem, "geoid_offset_m": self.geoid_offset_m}

    def place(self, k: int, pos: NDArray, yaw: float, region: NDArray, elev: NDArray) -> Placement:
        """Refine sample ``k`` (base at ``pos``, ``yaw`` in odom; its fused short ``region``
        and ``elev``) by ICP against the DEM, and keep it or say why not. A kept sample's
        placement is the prior of the next."""
        dc = self.cfg.dem
        T_odom_target = yaw_transform(*pos, yaw)
        T_crs_target = self.T_prior @ T_odom_target
        dem = dem_patch(self.dem, T_crs_target, self.X, self.Y)
        src_mask = codes.observed(region) & np.isfinite(elev)
        tgt_mask = np.isfinite(dem)
        if not tgt_mask.any():
            return Placement(codes.NO_DEM)
        if src_mask.sum() < MIN_ICP_POINTS:
            return Placement(codes.TOO_FEW_POINTS)
        src = np.column_stack([self.X[src_mask], self.Y[src_mask], elev[src_mask]])
        if len(src) > dc.icp_max_points:
            src = src[np.random.default_rng(k).choice(len(src), dc.icp_max_points, replace=False)]  # per-sample seed: order-free
        tgt = np.column_stack([self.X[tgt_mask], self.Y[tgt_mask], dem[tgt_mask]])
        nrm = _normals(np.where(tgt_mask, dem, np.nanmedian(dem)), self.cfg.grids.short.resolution_m)[tgt_mask]
        res = icp_4dof(src, tgt, nrm, dc.icp_max_distance_m, dc.icp_iterations)
        if res.fitness < dc.min_fitness:
            return Placement(codes.LOW_FITNESS, res)
        if res.rmse_m > dc.max_rmse_m:
            return Placement(codes.HIGH_RMSE, res)
        T_crs_target = T_crs_target @ res.T
        self.T_prior = T_crs_target @ invert(T_odom_target)
        return Placement(codes.OK, res, T_crs_target)
