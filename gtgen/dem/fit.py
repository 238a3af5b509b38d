"""Drive-level placement of odom in the DEM's CRS from GNSS fixes (x, y, yaw).

The fit is a weighted 2D rigid transform (Kabsch without scale) iterated with
outlier rejection; weights are the inverse horizontal variances of the fixes. The
UTM grid convergence and any odometry heading offset end up in the yaw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.poses import PoseTrack
from gtgen.config import GtgenConfig
from gtgen.dem.index import NO_DEM
from gtgen.errors import AlignmentError
from gtgen.storage.drive import Fixes


@dataclass(frozen=True)
class PlanarFit:
    """T_crs_odom restricted to the plane, the GNSS-minus-odom height offset, and QA."""

    yaw: float
    tx: float
    ty: float
    dz_gnss: float  # ellipsoidal height minus odom z (includes the geoid separation) [m]
    rms_m: float
    n_used: int
    n_outliers: int

    def apply_xy(self, xy: NDArray) -> NDArray[np.float64]:
        """Return CRS (E, N) of odom points (..., 2)."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.stack([c * xy[..., 0] - s * xy[..., 1] + self.tx, s * xy[..., 0] + c * xy[..., 1] + self.ty], -1)


def _kabsch2d(src: NDArray, dst: NDArray, w: NDArray) -> tuple[float, NDArray]:
    ws = w / w.sum()
    cs, cd = ws @ src, ws @ dst
    H = ((src - cs) * ws[:, None]).T @ (dst - cd)
    yaw = np.arctan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1])
    c, s = np.cos(yaw), np.sin(yaw)
    t = cd - np.array([[c, -s], [s, c]]) @ cs
    return float(yaw), t


def fit_planar(odom_xyz: NDArray, gnss_enu: NDArray, var_h: NDArray, outlier_m: float, min_fixes: int) -> PlanarFit:
    """Return the robust fit of odom positions (N, 3) to projected GNSS (E, N, h) (N, 3)."""
    ok = np.all(np.isfinite(odom_xyz), axis=1) & np.all(np.isfinite(gnss_enu), axis=1)
    src, dst = odom_xyz[ok], gnss_enu[ok]
    var = np.where(np.isfinite(var_h[ok]) & (var_h[ok] > 0), var_h[ok], 1.0)
    if len(src) < min_fixes:
        raise AlignmentError(f"{len(src)} usable GNSS fixes for the drive; expected at least {min_fixes} (dem.min_gnss_fixes)")
    extent = np.ptp(src[:, :2], axis=0).max()
    if extent < 10.0:
        raise AlignmentError(f"the drive spans only {extent:.1f} m; at least 10 m of travel are needed to fit the heading to GNSS")
    w = 1.0 / var
    inl = np.ones(len(src), bool)
    for _ in range(10):
        yaw, t = _kabsch2d(src[inl, :2], dst[inl, :2], w[inl])
        c, s = np.cos(yaw), np.sin(yaw)
        pred = src[:, :2] @ np.array([[c, s], [-s, c]]) + t
        r = np.linalg.norm(pred - dst[:, :2], axis=1)
        # outliers: beyond the configured distance or 4 robust sigmas, whichever is larger
        sigma = 1.4826 * np.median(r[inl]) if inl.any() else outlier_m
        new = r < max(outlier_m, 4 * sigma)
        if new.sum() < min_fixes:
            raise AlignmentError(f"only {int(new.sum())} GNSS fixes agree with the odometry within {outlier_m} m; expected at least {min_fixes}")
        if np.array_equal(new, inl):
            break
        inl = new
    dz = float(np.median(dst[inl, 2] - src[inl, 2]))
    return PlanarFit(yaw, float(t[0]), float(t[1]), dz, float(np.sqrt(np.mean(r[inl] ** 2))), int(inl.sum()), int((~inl).sum()))


def gnss_fit(cfg: GtgenConfig, fixes: Fixes, track: PoseTrack, crs: str) -> PlanarFit:
    """Return the fit of a drive's odometry to its GNSS ``fixes`` projected into ``crs``."""
    from pyproj import Transformer

    if len(fixes.t_ns) == 0:
        raise AlignmentError(f"GNSS absent for the whole drive (no fix on '{cfg.topics.gnss}'); dem-align needs GNSS to place the DEM; {NO_DEM}")
    E, N = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(fixes.lon_deg, fixes.lat_deg)
    pos, _ = track.interpolate(fixes.t_ns, strict=False)
    enu = np.column_stack([E, N, fixes.alt_m])
    enu[~fixes.usable] = np.nan
    return fit_planar(pos, enu, fixes.var_enu_m2[:, :2].mean(axis=1), cfg.dem.gnss_outlier_m, cfg.dem.min_gnss_fixes)


def gnss_lonlat(cfg: GtgenConfig, fixes: Fixes) -> tuple[float, float]:
    """Return the median (lon, lat) [deg] of a drive's usable GNSS fixes."""
    ok = fixes.usable
    if not ok.any():
        raise AlignmentError(f"GNSS absent for the whole drive (no fix on '{cfg.topics.gnss}'); dem-align needs GNSS to place the DEM; {NO_DEM}")
    return float(np.median(fixes.lon_deg[ok])), float(np.median(fixes.lat_deg[ok]))
