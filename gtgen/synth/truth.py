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

    def labels(self, T_odom_target: NDArray, X: NDArray, Y: NDArray, t_ns: int) -> tuple[NDArray, NDArray, NDArray]:
        """Return, at target cells (X, Y), the true (ground elevation, risk, elevation the
        stack should see), elevations relative to the base z at t. What the stack should see
        is the ground, or with ``canopy`` the top of crowns and bushes; the DEM's truth is
        the ground."""
        T = self.T_crs_odom(t_ns) @ T_odom_target
        E = T[0, 0] * X + T[0, 1] * Y + T[0, 3]
        N = T[1, 0] * X + T[1, 1] * Y + T[1, 3]
        g, r, srf = self.world.terrain.sample(E - self.origin[0], N - self.origin[1], ("ground", "risk", "surface"))
        seen = np.where(srf - g > 0.3, srf, g) if self.world.cfg.canopy else g
        return (g - T[2, 3]).astype(np.float32), r, (seen - T[2, 3]).astype(np.float32)

    def standing(self, T_odom_target: NDArray, X: NDArray, Y: NDArray, t_ns: int) -> NDArray[np.float32]:
        """Return, at target cells (X, Y), the height of what stands on the ground there (tree
        crowns and trunks, bushes) [m]; rocks are ground."""
        T = self.T_crs_odom(t_ns) @ T_odom_target
        E = T[0, 0] * X + T[0, 1] * Y + T[0, 3]
        N = T[1, 0] * X + T[1, 1] * Y + T[1, 3]
        g, srf = self.world.terrain.sample(E - self.origin[0], N - self.origin[1], ("ground", "surface"))
        return (srf - g).astype(np.float32)

    def dem_heights(self, E: NDArray, N: NDArray) -> NDArray[np.float64]:
        """Return what the DEM tiles hold at CRS points (E, N), noise aside: the terrain as
        surveyed (before the terrain changes), from elsewhere in the shifted and wrong tile."""
        from gtgen.synth.dem import altered_tiles

        w = self.world
        E, N = np.asarray(E, np.float64), np.asarray(N, np.float64)
        du, dv = np.zeros(E.shape), np.zeros(E.shape)
        tile = w.cfg.dem_tile_m
        for (e0, n0), (de, dn) in altered_tiles(w).items():
            inside = (E >= e0) & (E < e0 + tile) & (N >= n0) & (N < n0 + tile)
            du[inside], dv[inside] = de, dn
        u, v = E - self.origin[0] + du, N - self.origin[1] + dv
        return w.terrain.sample(u, v, ("ground",))[0] - w.changes.height(u, v)

    def ground(self, E: NDArray, N: NDArray) -> NDArray[np.float64]:
        """Return the driven ground's height at CRS points (E, N)."""
        return self.world.terrain.sample(np.asarray(E) - self.origin[0], np.asarray(N) - self.origin[1], ("ground",))[0].astype(np.float64)
