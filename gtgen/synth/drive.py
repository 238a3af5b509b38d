"""The vehicle's true path, its drifting odometry, and its GNSS fixes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen.config import SynthConfig
from gtgen.synth.terrain import Terrain

PATH_DT_S = 0.01
WHEELBASE_M = 2.4
TRACK_M = 1.6


@dataclass
class Path:
    """The true path sampled every PATH_DT_S: time [ns], local (u, v) [m], yaw [rad], speed [m/s]."""

    t_ns: NDArray[np.int64]
    uv: NDArray[np.float64]
    yaw: NDArray[np.float64]
    speed: NDArray[np.float64]
    dist: NDArray[np.float64]


def make_path(cfg: SynthConfig, t0_ns: int) -> Path:
    """Return a smooth seeded path at speeds within [speed_min, speed_max]."""
    rng = np.random.default_rng([cfg.seed, 3])
    n = int(round(cfg.duration_s / PATH_DT_S)) + 1
    t = np.arange(n) * PATH_DT_S
    # yaw rate and speed as sums of slow sinusoids: smooth and bounded
    yaw_rate = np.zeros(n)
    for _ in range(4):
        yaw_rate += rng.uniform(0.02, 0.08) * np.sin(2 * np.pi * t / rng.uniform(15, 60) + rng.uniform(0, 2 * np.pi))
    mid = 0.5 * (cfg.speed_min_mps + cfg.speed_max_mps)
    amp = 0.5 * (cfg.speed_max_mps - cfg.speed_min_mps)
    speed = mid + amp * np.sin(2 * np.pi * t / rng.uniform(25, 50) + rng.uniform(0, 2 * np.pi))
    yaw = rng.uniform(-np.pi, np.pi) + np.cumsum(yaw_rate) * PATH_DT_S
    step = speed * PATH_DT_S
    uv = np.zeros((n, 2))
    uv[1:, 0] = np.cumsum(step[:-1] * np.cos(yaw[:-1]))
    uv[1:, 1] = np.cumsum(step[:-1] * np.sin(yaw[:-1]))
    dist = np.concatenate([[0.0], np.cumsum(step[:-1])])
    return Path(t0_ns + np.round(t * 1e9).astype(np.int64), uv, yaw, speed, dist)


@dataclass
class Poses:
    """Poses at times t [ns]: position (N, 3) [m] and roll, pitch, yaw [rad]."""

    t_ns: NDArray[np.int64]
    pos: NDArray[np.float64]
    rpy: NDArray[np.float64]


def true_poses(path: Path, terrain: Terrain, idx: NDArray[np.int64]) -> Poses:
    """Return the true base poses (local world frame) at path indices ``idx``."""
    uv = path.uv[idx]
    yaw = path.yaw[idx]
    c, s = np.cos(yaw), np.sin(yaw)
    fwd = np.column_stack([c, s])
    left = np.column_stack([-s, c])
    h = WHEELBASE_M / 2
    w = TRACK_M / 2
    zf, zb, zl, zr = terrain.sample(
        np.concatenate([uv[:, 0] + h * fwd[:, 0], uv[:, 0] - h * fwd[:, 0], uv[:, 0] + w * left[:, 0], uv[:, 0] - w * left[:, 0]]),
        np.concatenate([uv[:, 1] + h * fwd[:, 1], uv[:, 1] - h * fwd[:, 1], uv[:, 1] + w * left[:, 1], uv[:, 1] - w * left[:, 1]]),
        ("bare",),
    )[0].reshape(4, -1)
    pitch = -np.arctan2(zf - zb, 2 * h)
    roll = np.arctan2(zl - zr, 2 * w)
    z = (zf + zb + zl + zr) / 4.0
    return Poses(path.t_ns[idx], np.column_stack([uv, z]), np.column_stack([roll, pitch, yaw]))


@dataclass
class Drift:
    """Odometry error as a gravity-aligned offset of the odom frame, per time.

    odom = Rz(dyaw) (world - p_true) + p_odom; so a world point maps to odom through
    the yaw offset ``dyaw`` and translation pair (p_true, p_odom).
    """

    dxy: NDArray[np.float64]
    dz: NDArray[np.float64]
    dyaw: NDArray[np.float64]


def make_drift(cfg: SynthConfig, path: Path) -> Drift:
    """Return seeded odometry drift along the path (xy and yaw grow with distance, z with time)."""
    rng = np.random.default_rng([cfg.seed, 4])
    n = len(path.t_ns)
    ddist = np.diff(path.dist, prepend=0.0)
    heading = np.cumsum(rng.normal(0, 0.02, n)) + rng.uniform(0, 2 * np.pi)
    dxy = np.cumsum(ddist[:, None] * cfg.drift_xy_per_m * np.column_stack([np.cos(heading), np.sin(heading)]), axis=0)
    sign = rng.choice([-1.0, 1.0])
    dyaw = sign * np.deg2rad(cfg.drift_yaw_deg_per_100m) * path.dist / 100.0
    t = (path.t_ns - path.t_ns[0]) * 1e-9
    dz = rng.choice([-1.0, 1.0]) * cfg.drift_z_m_per_s * t + 0.02 * np.sin(t / 7.0)
    return Drift(dxy, dz, dyaw)


class OdomFrame:
    """Maps between the local world frame and the drifting odom frame at path indices."""

    def __init__(self, true: Poses, drift: Drift, idx: NDArray[np.int64]) -> None:
        p0 = true.pos[0]
        yaw0 = true.rpy[0, 2]
        self.p_true = true.pos
        # odom starts at the first true pose, heading along x
        rel = true.pos - p0
        c, s = np.cos(-yaw0), np.sin(-yaw0)
        self.p_odom = np.column_stack([c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1], rel[:, 2]])
        self.p_odom[:, :2] += drift.dxy[idx]
        self.p_odom[:, 2] += drift.dz[idx]
        self.dyaw = -yaw0 + drift.dyaw[idx]
        self.rpy_odom = true.rpy.copy()
        self.rpy_odom[:, 2] = true.rpy[:, 2] + self.dyaw

    def world_to_odom(self, k: int, pts: NDArray) -> NDArray[np.float64]:
        """Return world points (..., 3) expressed in odom at pose index k."""
        c, s = np.cos(self.dyaw[k]), np.sin(self.dyaw[k])
        d = pts - self.p_true[k]
        return np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1], d[..., 2]], -1) + self.p_odom[k]

    def odom_to_world(self, k: int, pts: NDArray) -> NDArray[np.float64]:
        """Return odom points (..., 3) expressed in the local world frame at pose index k."""
        c, s = np.cos(-self.dyaw[k]), np.sin(-self.dyaw[k])
        d = pts - self.p_odom[k]
        return np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1], d[..., 2]], -1) + self.p_true[k]


def gnss_errors(cfg: SynthConfig, t_ns: NDArray[np.int64]) -> NDArray[np.float64]:
    """Return GNSS position errors (N, 3) [m]: a Gauss-Markov bias plus white noise."""
    rng = np.random.default_rng([cfg.seed, 5])
    n = len(t_ns)
    dt = np.diff(t_ns, prepend=t_ns[0]) * 1e-9
    phi = np.exp(-dt / cfg.gnss_bias_tau_s)
    bias = np.zeros((n, 3))
    bias[0] = rng.normal(0, cfg.gnss_bias_m, 3)
    drive = rng.normal(0, 1, (n, 3))
    for k in range(1, n):  # a recursion over time, not over cells: each step needs the last
        bias[k] = phi[k] * bias[k - 1] + np.sqrt(1 - phi[k] ** 2) * cfg.gnss_bias_m * drive[k]
    bias[:, 2] *= 1.5
    return bias + rng.normal(0, cfg.gnss_noise_m, (n, 3)) * np.array([1.0, 1.0, 1.5]) + gnss_jumps(cfg, t_ns)


def _events(cfg: SynthConfig, t_ns: NDArray[np.int64], n: int, length_s: float, stream: int) -> list[tuple[int, int]]:
    """Return ``n`` seeded [start, stop) intervals [ns] inside the drive."""
    if not n or not len(t_ns):
        return []
    rng = np.random.default_rng([cfg.seed, stream])
    t0, t1 = int(t_ns[0]), int(t_ns[-1])
    starts = np.sort(rng.uniform(t0 + 0.1 * (t1 - t0), t1 - length_s * 1e9, n)).astype(np.int64)
    return [(int(a), int(a + length_s * 1e9)) for a in starts]


def gnss_jumps(cfg: SynthConfig, t_ns: NDArray[np.int64]) -> NDArray[np.float64]:
    """Return the multipath jumps (N, 3) [m] added to the fixes at ``t_ns``: ``gnss_jumps``
    events of ``gnss_jump_m`` horizontally, each for ``gnss_jump_s``."""
    out = np.zeros((len(t_ns), 3))
    rng = np.random.default_rng([cfg.seed, 13])
    for a, b in _events(cfg, t_ns, cfg.gnss_jumps, cfg.gnss_jump_s, 14):
        ang = rng.uniform(0, 2 * np.pi)
        out[(t_ns >= a) & (t_ns < b), :2] += cfg.gnss_jump_m * np.array([np.cos(ang), np.sin(ang)])
    return out


def gnss_outage(cfg: SynthConfig, t_ns: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Return where the receiver has no fix (``gnss_outages`` outages of ``gnss_outage_s``)."""
    out = np.zeros(len(t_ns), bool)
    for a, b in _events(cfg, t_ns, cfg.gnss_outages, cfg.gnss_outage_s, 15):
        out |= (t_ns >= a) & (t_ns < b)
    return out
