"""Truth of a synthetic drive at dataset samples: labels, risk and the true DEM placement."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.geometry import yaw_transform


class Truth:
    """A synth drive's truth, rebuilt from ``truth/`` beside its bags."""

    def __init__(self, folder: Path) -> None:
        from gtgen.synth.run import load_world

        meta = json.loads((folder / "truth.json").read_text())
        self.meta = meta
        self.world = load_world(folder.parent)
        traj = np.load(folder / "trajectory.npz")
        self.t_ns = traj["t_ns"]
        self.pos_w = traj["pos_world_m"]
        self.pos_o = traj["pos_odom_m"]
        self.dyaw = traj["rpy_odom_rad"][:, 2] - traj["rpy_world_rad"][:, 2]
        self.origin = np.array([meta["origin_e_m"], meta["origin_n_m"]])

    @classmethod
    def find(cls, bag_paths: list[str]) -> Truth | None:
        """Return the truth next to the first bag that has one, else None."""
        for p in bag_paths:
            folder = Path(p).parent / "truth"
            if (folder / "truth.json").is_file():
                return cls(folder)
        return None

    def T_crs_odom(self, t_ns: int) -> NDArray[np.float64]:
        """Return the true 4x4 odom -> DEM CRS transform at ``t_ns`` (z: orthometric heights)."""
        k = int(np.clip(np.searchsorted(self.t_ns, t_ns), 1, len(self.t_ns) - 1))
        a = (t_ns - self.t_ns[k - 1]) / max(self.t_ns[k] - self.t_ns[k - 1], 1)
        pw = self.pos_w[k - 1] + a * (self.pos_w[k] - self.pos_w[k - 1])
        po = self.pos_o[k - 1] + a * (self.pos_o[k] - self.pos_o[k - 1])
        dy = np.unwrap(self.dyaw[k - 1 : k + 1])
        dyaw = dy[0] + a * (dy[1] - dy[0])
        # world = Rz(-dyaw) (odom - p_odom) + p_world; crs = world + origin
        R = yaw_transform(0, 0, 0, -dyaw)
        T = yaw_transform(self.origin[0] + pw[0], self.origin[1] + pw[1], pw[2], 0.0) @ R @ yaw_transform(-po[0], -po[1], -po[2], 0.0)
        return T

    def labels(self, T_odom_target: NDArray, X: NDArray, Y: NDArray, t_ns: int) -> tuple[NDArray, NDArray]:
        """Return true (elevation rel. base z at t, risk) at target cells (X, Y)."""
        T = self.T_crs_odom(t_ns) @ T_odom_target
        E = T[0, 0] * X + T[0, 1] * Y + T[0, 3]
        N = T[1, 0] * X + T[1, 1] * Y + T[1, 3]
        g, r = self.world.terrain.sample(E - self.origin[0], N - self.origin[1], ("ground", "risk"))
        return (g - T[2, 3]).astype(np.float32), r
