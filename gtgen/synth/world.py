"""The deterministic world of a synthetic drive: path, obstacles, terrain, poses.

Everything here is a pure function of the synth config (seed included), which is how
``truth/`` stays small: ``SynthWorld(cfg)`` rebuilds the same world later.
"""

from __future__ import annotations

import numpy as np

from gtgen.config import SynthConfig
from gtgen.synth.drive import (
    Drift,
    OdomFrame,
    Path,
    Poses,
    make_drift,
    make_path,
    true_poses,
)
from gtgen.synth.terrain import (
    Changes,
    Obstacles,
    Terrain,
    place_changes,
    place_obstacles,
)

T0_NS = 1_714_586_400_000_000_000  # 2024-05-01T18:00:00Z: a plausible field-test afternoon
WORLD_MARGIN_M = 160.0


class SynthWorld:
    """The synthetic drive's truth."""

    def __init__(self, cfg: SynthConfig) -> None:
        self.cfg = cfg
        self.path: Path = make_path(cfg, T0_NS)
        lo = self.path.uv.min(axis=0) - WORLD_MARGIN_M
        hi = self.path.uv.max(axis=0) + WORLD_MARGIN_M
        self.bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        self.obstacles: Obstacles = place_obstacles(cfg, self.bounds, self.path.uv)
        self.changes: Changes = place_changes(cfg, self.path.uv)
        self.terrain = Terrain(cfg, self.obstacles, self.changes)
        self.drift: Drift = make_drift(cfg, self.path)
        step = max(1, int(round(1.0 / (cfg.odom_rate_hz * 0.01))))
        self.pose_idx = np.arange(0, len(self.path.t_ns), step)
        self.poses: Poses = true_poses(self.path, self.terrain, self.pose_idx)
        self.odom = OdomFrame(self.poses, self.drift, self.pose_idx)

    @property
    def t_ns(self) -> np.ndarray:
        """Odometry times [ns] (one per pose)."""
        return self.poses.t_ns

    def utm(self, uv: np.ndarray) -> np.ndarray:
        """Return UTM (E, N) of local (u, v) points (..., 2)."""
        return uv + np.array([self.cfg.origin_e_m, self.cfg.origin_n_m])
