"""Raw scans of the synthetic drive's three spinning 32-beam lidars (the paper's vehicle
carries three VLP-32C: front, front tilted down, back).

Every beam of every column is a ray cast from the sensor's pose at the scan stamp over
the world's render raster (``camera.RenderRaster``: terrain with the trees, rocks and
bushes as its surface layer, 0.25 m cells, as a heightfield: a crown is hit from the
side or above as the solid column of its height), see ``cast``.
A return then gets range noise (``scan_noise_m``) and is dropped with probability
``scan_dropout``; rays that hit nothing within ``scan_range_m`` give no return. Points are
published in the sensor frame with x, y, z, intensity (float32) and ring (uint16), a
real driver's layout. Vectorised over the rays of a scan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen.config import SynthConfig
from gtgen.geometry import make_transform, quat_to_matrix, rpy_to_quat
from gtgen.synth.camera import DEPTHS, RenderRaster, march

# the VLP-32C's beam elevations [deg], lowest first
VLP32C_DEG = np.array([-25.0, -15.64, -11.31, -8.84, -7.25, -6.15, -5.33, -4.67, -4.0, -3.67, -3.33, -3.0, -2.67, -2.33,
                       -2.0, -1.67, -1.33, -1.0, -0.67, -0.33, 0.0, 0.33, 0.67, 1.0, 1.33, 1.67, 2.33, 3.33, 4.67, 7.0,
                       10.33, 15.0])
# mounts on the base (x, y, z [m], roll, pitch, yaw [deg]): front, front tilted 20 deg down, back facing back
MOUNTS = {"front": (1.0, 0.0, 1.9, 0.0, 0.0, 0.0), "front_tilted": (1.2, 0.0, 2.0, 0.0, 20.0, 0.0),
          "back": (-1.0, 0.0, 1.9, 0.0, 0.0, 180.0)}
REFINE = 12  # bisection halvings of the step a ray crossed the surface in (a 4 m step to 1 mm)
N_STEPS = 160  # horizontal distances of a profile, geometric from 0.5 m to the range (1.7 m apart at 50 m)
AZ_BIN_DEG = 0.1  # azimuth bins of the profiles [deg]
POINT = np.dtype({"names": ["x", "y", "z", "intensity", "ring"], "formats": ["<f4", "<f4", "<f4", "<f4", "<u2"],
                  "offsets": [0, 4, 8, 12, 16], "itemsize": 20})


def lidar_frame(name: str) -> str:
    """Return the TF frame of lidar ``name``."""
    return f"lidar_{name}"


def T_base_lidar(name: str) -> NDArray[np.float64]:
    """Return the mount of lidar ``name``: T_base_lidar (4, 4)."""
    x, y, z, r, p, yw = MOUNTS[name]
    q = rpy_to_quat(*np.deg2rad([r, p, yw]))
    return make_transform(quat_to_matrix(q), np.array([x, y, z]))


def beam_rays(cfg: SynthConfig) -> tuple[NDArray[np.float32], NDArray[np.uint16]]:
    """Return the unit rays of one scan in the sensor frame (n, 3) and each ray's ring
    (beam index of the 32, 0 lowest): ``scan_beams`` beams evenly thinned, columns every
    ``scan_azimuth_deg``."""
    ring = np.unique(np.round(np.linspace(0, len(VLP32C_DEG) - 1, cfg.scan_beams)).astype(np.int64))
    el = np.deg2rad(VLP32C_DEG[ring])
    az = np.deg2rad(np.arange(0.0, 360.0, cfg.scan_azimuth_deg))
    A, E = np.meshgrid(az, el, indexing="ij")
    rays = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    return rays.astype(np.float32), np.broadcast_to(ring, A.shape).reshape(-1).astype(np.uint16)


@dataclass
class ScanHits:
    """A cast scan: hit ranges [m] (NaN: no return) of the rays, and whether each return is an
    obstacle (surface above the ground) rather than the ground."""

    range_m: NDArray[np.float32]
    obstacle: NDArray[np.bool_]


def cast(raster: RenderRaster, T_world_sensor: NDArray, rays: NDArray[np.float32], max_range_m: float) -> ScanHits:
    """Return the exact (noise-free) first hits of ``rays`` (sensor frame) from the sensor at
    ``T_world_sensor`` against the raster's surface.

    The rays are binned by world azimuth (``AZ_BIN_DEG``); the surface is sampled once per
    bin along its centre line at ``N_STEPS`` horizontal distances, and each ray's first
    step below that profile is found for all its steps at once (the beams of a column
    share one profile: 32 times fewer lookups than marching each ray). The crossing is
    then refined along the ray itself by bisection over the raster (``REFINE`` halvings),
    so a hit lies on the surface under the ray; only which crossing is found uses the
    profile (at most half a bin, 9 cm at 100 m, beside the ray)."""
    o = (T_world_sensor[:3, 3] - np.array([raster.u0, raster.v0, 0.0])).astype(np.float32)
    d = (rays @ T_world_sensor[:3, :3].T.astype(np.float32)).astype(np.float32)
    h = np.hypot(d[:, 0], d[:, 1])
    slope = d[:, 2] / np.maximum(h, 1e-6)
    n_bins = int(round(360.0 / AZ_BIN_DEG))
    b = np.round(np.arctan2(d[:, 1], d[:, 0]) * (n_bins / (2 * np.pi))).astype(np.int64) % n_bins
    used, inv = np.unique(b, return_inverse=True)
    H = np.geomspace(0.5, max_range_m, N_STEPS).astype(np.float32)
    ang = used * (2 * np.pi / n_bins)
    U = o[0] + np.cos(ang)[:, None].astype(np.float32) * H
    V = o[1] + np.sin(ang)[:, None].astype(np.float32) * H
    profile = raster.lookup(U, V, 0).reshape(len(used), N_STEPS)
    below = o[2] + slope[:, None] * H[None, :] <= profile[inv]
    k = np.argmax(below, axis=1)
    hit = below[np.arange(len(k)), k] & (k > 0) & (h > 1e-6)  # k = 0: the ray starts below the surface (in an obstacle)
    lo, hi = H[np.maximum(k - 1, 0)] / np.maximum(h, 1e-6), H[k] / np.maximum(h, 1e-6)  # ranges along the ray
    lo = np.where(_below(raster, o, d, lo), 0.0, lo)  # the profile is beside the ray: keep lo above the surface
    for _ in range(REFINE):  # bisection: lo stays above the surface, hi below (where it is)
        mid = 0.5 * (lo + hi)
        under = _below(raster, o, d, mid)
        hi = np.where(under, mid, hi)
        lo = np.where(under, lo, mid)
    r = hi.astype(np.float32)
    hit &= _below(raster, o, d, r)
    P = o + r[:, None] * d
    obstacle = raster.lookup(P[:, 0], P[:, 1], 0) - raster.lookup(P[:, 0], P[:, 1], 1) > 0.05
    ok = hit & (r <= max_range_m)
    return ScanHits(np.where(ok, r, np.float32(np.nan)).astype(np.float32), obstacle & ok)


def cast_naive(raster: RenderRaster, T_world_sensor: NDArray, rays: NDArray[np.float32], max_range_m: float) -> ScanHits:
    """``cast`` by marching every ray on its own (``camera.march``), then the same
    bisection: the test oracle."""
    o = (T_world_sensor[:3, 3] - np.array([raster.u0, raster.v0, 0.0])).astype(np.float32)
    d = (rays @ T_world_sensor[:3, :3].T.astype(np.float32)).astype(np.float32)
    k, hit = march(raster, o, d)
    hit &= k > 0
    lo, hi = DEPTHS[np.maximum(k - 1, 0)].copy(), DEPTHS[k].copy()
    for _ in range(REFINE):
        mid = 0.5 * (lo + hi)
        under = _below(raster, o, d, mid)
        hi = np.where(under, mid, hi)
        lo = np.where(under, lo, mid)
    P = o + hi[:, None] * d
    obstacle = raster.lookup(P[:, 0], P[:, 1], 0) - raster.lookup(P[:, 0], P[:, 1], 1) > 0.05
    ok = hit & (hi <= max_range_m)
    return ScanHits(np.where(ok, hi, np.float32(np.nan)).astype(np.float32), obstacle & ok)


def _below(raster: RenderRaster, o: NDArray, d: NDArray, r: NDArray) -> NDArray[np.bool_]:
    """Whether the points at ranges ``r`` along rays ``d`` from ``o`` are at or below the surface."""
    P = o + r[:, None].astype(np.float32) * d
    return P[:, 2] <= raster.lookup(P[:, 0], P[:, 1], 0)


def scan_points(cfg: SynthConfig, raster: RenderRaster, T_world_sensor: NDArray, rng: np.random.Generator) -> np.ndarray:
    """Return one scan's returns as PointCloud2 records (``POINT``) in the sensor frame: the
    hits with range noise, some dropped."""
    rays, ring = beam_rays(cfg)
    hits = cast(raster, T_world_sensor, rays, cfg.scan_range_m)
    r = hits.range_m + rng.standard_normal(len(rays), dtype=np.float32) * np.float32(cfg.scan_noise_m)
    keep = np.isfinite(r) & (rng.random(len(rays)) >= cfg.scan_dropout) & (r > 0)
    out = np.zeros(int(keep.sum()), POINT)
    p = rays[keep] * r[keep, None]
    out["x"], out["y"], out["z"] = p[:, 0], p[:, 1], p[:, 2]
    out["intensity"] = np.where(hits.obstacle[keep], 80.0, 30.0)
    out["ring"] = ring[keep]
    return out

