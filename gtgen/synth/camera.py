"""The simulated cameras: their mounts and pinhole, a coarse raster of the world, and
images ray-marched through it (with the configured lens's distortion when it has one).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.config import SynthConfig
from gtgen.geometry import quat_to_matrix, rpy_to_quat
from gtgen.lens import Lens
from gtgen.synth.terrain import Terrain

CAMERA_MOUNTS = {
    # name: (x, y, z) [m] in base_link, yaw [rad], pitch down [rad]
    "front": ((1.2, 0.0, 1.7), 0.0, np.deg2rad(8.0)),
    "left": ((0.3, 0.6, 1.7), np.pi / 2, np.deg2rad(8.0)),
    "right": ((0.3, -0.6, 1.7), -np.pi / 2, np.deg2rad(8.0)),
    "back": ((-1.0, 0.0, 1.7), np.pi, np.deg2rad(8.0)),
}
# optical frame (x right, y down, z forward) expressed in a forward-looking body frame
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_extrinsic(name: str) -> NDArray[np.float64]:
    """Return T_base_camoptical (4x4) of camera ``name``."""
    (x, y, z), yaw, pitch = CAMERA_MOUNTS[name]
    R = quat_to_matrix(rpy_to_quat(0.0, pitch, yaw)) @ R_BODY_OPTICAL
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = (x, y, z)
    return T


def camera_intrinsic(cfg: SynthConfig) -> NDArray[np.float64]:
    """Return the 3x3 pinhole matrix K of the simulated cameras."""
    f = 0.5 * cfg.image_width / np.tan(np.deg2rad(cfg.camera_hfov_deg) / 2)
    # ROS convention: pixel centres at integer coordinates
    return np.array([[f, 0.0, (cfg.image_width - 1) / 2], [0.0, f, (cfg.image_height - 1) / 2], [0.0, 0.0, 1.0]])


class RenderRaster:
    """A coarse raster of the world for ray marching the camera images."""

    RES_M = 0.25

    def __init__(self, terrain: Terrain, bounds: tuple[float, float, float, float]) -> None:
        u0, v0, u1, v1 = bounds
        self.u0, self.v0 = u0, v0
        nu = int(np.ceil((u1 - u0) / self.RES_M))
        nv = int(np.ceil((v1 - v0) / self.RES_M))
        # a border of -inf cells around the raster: out-of-raster points clip onto it,
        # so a lookup is one gather; ``layers`` is the interior
        self._padded = np.full((3, nu + 2, nv + 2), -np.inf, np.float32)
        self.layers = self._padded[:, 1:-1, 1:-1]
        block = 1024
        for i in range(0, nu, block):
            for j in range(0, nv, block):
                bu, bv = min(block, nu - i), min(block, nv - j)
                g = terrain.eval_grid(u0 + i * self.RES_M, v0 + j * self.RES_M, self.RES_M, bu, bv)
                self.layers[0, i : i + bu, j : j + bv] = g["surface"]
                self.layers[1, i : i + bu, j : j + bv] = g["ground"]
                self.layers[2, i : i + bu, j : j + bv] = g["bare"]

    def share(self, folder: Path) -> None:
        """Put the raster in a file of ``folder``, so that a pickle of it names the file and
        each process that unpickles it maps the raster read-only."""
        folder.mkdir(parents=True, exist_ok=True)
        self._file = str(folder / "render_raster.npy")
        np.save(self._file, self._padded)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        if getattr(self, "_file", None):
            state["_padded"] = state["layers"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if self._padded is None:
            self._padded = np.load(self._file, mmap_mode="r")
            self.layers = self._padded[:, 1:-1, 1:-1]

    def lookup(self, u: NDArray, v: NDArray, layer: int) -> NDArray[np.float32]:
        """Return the nearest raster value of ``layer`` at (u, v) relative to (u0, v0); -inf outside."""
        nu, nv = self.layers.shape[1:]
        i = np.floor(u * (1 / self.RES_M)).astype(np.int64)
        j = np.floor(v * (1 / self.RES_M)).astype(np.int64)
        np.clip(i + 1, 0, nu + 1, out=i)
        np.clip(j + 1, 0, nv + 1, out=j)
        i *= nv + 2
        i += j
        return self._padded[layer].reshape(-1).take(i)


N_STEPS = 64
MARCH_BLOCK = 8  # depth steps marched per pass before finished rays drop out
DEPTHS = np.geomspace(0.8, 140.0, N_STEPS).astype(np.float32)


def march(raster: RenderRaster, o: NDArray[np.float32], rays: NDArray[np.float32]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Return (first step below the surface or 0, hit) of rays from ``o`` at DEPTHS.

    Steps are marched in blocks; a ray leaves the march once it has hit, so near
    ground pixels cost a block rather than all N_STEPS (``march_naive`` is the oracle).
    """
    k = np.zeros(len(rays), np.int64)
    hit = np.zeros(len(rays), bool)
    active = np.arange(len(rays))
    for b0 in range(0, N_STEPS, MARCH_BLOCK):
        P = o + DEPTHS[None, b0 : b0 + MARCH_BLOCK, None] * rays[active][:, None, :]
        below = P[..., 2] <= raster.lookup(P[..., 0], P[..., 1], 0)
        got = below.any(axis=1)
        k[active[got]] = b0 + np.argmax(below[got], axis=1)
        hit[active[got]] = True
        active = active[~got]
        if len(active) == 0:
            break
    return k, hit


def march_naive(raster: RenderRaster, o: NDArray[np.float32], rays: NDArray[np.float32]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """``march`` over every step of every ray at once: the test oracle."""
    P = o + DEPTHS[None, :, None] * rays[:, None, :]
    below = P[..., 2] <= raster.lookup(P[..., 0], P[..., 1], 0)
    return np.argmax(below, axis=1), below.any(axis=1)


def camera_lens(cfg: SynthConfig, name: str) -> Lens:
    """Return the lens of camera ``name``: plumb_bob ``cfg.distortion`` on ``cfg.distorted_camera``, else none."""
    return Lens.of("plumb_bob", cfg.distortion) if name == cfg.distorted_camera else Lens.of("plumb_bob", np.zeros(5))


@functools.lru_cache(maxsize=8)
def camera_rays(K: tuple[float, ...], size: tuple[int, int], lens: Lens | None) -> NDArray[np.float64]:
    """Return the ray (x, y, 1) in the optical frame that each pixel of a ``size`` camera
    with intrinsics K (flat) and ``lens`` sees (H * W, 3): the same for every frame."""
    W, H = size
    k = np.asarray(K).reshape(3, 3)
    px, py = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    xn, yn = (px - k[0, 2]) / k[0, 0], (py - k[1, 2]) / k[1, 1]
    if lens is not None:  # the pixel sees the ray whose distorted image it is
        xn, yn = lens.undistort(xn, yn)
    rays = np.stack([xn, yn, np.ones_like(px)], -1).reshape(-1, 3)
    rays.setflags(write=False)
    return rays


def render(raster: RenderRaster, T_world_cam: NDArray, K: NDArray, size: tuple[int, int], lens: Lens | None = None) -> NDArray[np.uint8]:
    """Return an RGB image (H, W, 3) of ``size`` (W, H) rendered by marching each pixel's
    ray over the raster, through intrinsics K (at ``size``) and ``lens`` (None: a pinhole)."""
    W, H = size
    py = np.broadcast_to(np.arange(H, dtype=np.float64)[:, None], (H, W))
    rays = (camera_rays(tuple(np.asarray(K, np.float64).ravel()), size, lens) @ T_world_cam[:3, :3].T).astype(np.float32)
    # march in a frame centred on the raster origin so float32 keeps centimetres
    o = (T_world_cam[:3, 3] - np.array([raster.u0, raster.v0, 0.0])).astype(np.float32)
    k, hit = march(raster, o, rays)
    kp = np.maximum(k - 1, 0)
    # refine the hit between the last step above and the first below the surface
    Pk = o + DEPTHS[k][:, None] * rays
    Pkp = o + DEPTHS[kp][:, None] * rays
    za = Pkp[:, 2] - raster.lookup(Pkp[:, 0], Pkp[:, 1], 0)
    zb = Pk[:, 2] - raster.lookup(Pk[:, 0], Pk[:, 1], 0)
    a = np.clip(za / np.where(za - zb == 0, 1, za - zb), 0, 1)
    a = np.where(k == 0, 0.0, a)
    hp = Pkp + (Pk - Pkp) * a[:, None]
    depth = DEPTHS[kp] + (DEPTHS[k] - DEPTHS[kp]) * a
    s = raster.lookup(hp[:, 0], hp[:, 1], 0)
    g = raster.lookup(hp[:, 0], hp[:, 1], 1)
    b = raster.lookup(hp[:, 0], hp[:, 1], 2)
    tree = (s - g) > 0.3
    rock = (g - b) > 0.08
    # procedural ground texture from world position: deterministic, no state
    hu, hv = hp[:, 0] + raster.u0, hp[:, 1] + raster.v0
    tex = 0.5 + 0.25 * np.sin(hu * 1.7) * np.sin(hv * 1.3) + 0.25 * np.sin((hu + hv) * 0.31)
    ground_rgb = np.stack([150 + 40 * tex, 130 + 30 * tex, 85 + 20 * tex], -1)
    height_tint = np.clip((g - 230.0) / 20.0, 0, 1)[:, None]
    ground_rgb = ground_rgb * (1 - 0.25 * height_tint) + np.array([110, 140, 70]) * 0.25 * height_tint
    rgb = np.where(rock[:, None], np.array([120.0, 120.0, 125.0]), ground_rgb)
    trunk = tree & ((hp[:, 2] - g) < 0.45 * (s - g))
    rgb = np.where(tree[:, None], np.where(trunk[:, None], np.array([90.0, 60.0, 35.0]), np.array([40.0, 110.0, 45.0])), rgb)
    fog = np.clip(depth / 160.0, 0, 0.6)[:, None]
    sky_rgb = np.array([170.0, 200.0, 235.0])
    rgb = rgb * (1 - fog) + sky_rgb * fog
    vert = np.clip(py.reshape(-1) / H, 0, 1)[:, None]
    sky = np.array([110.0, 160.0, 230.0]) * (1 - vert) + sky_rgb * vert
    rgb = np.where(hit[:, None], rgb, sky)
    return np.clip(rgb, 0, 255).astype(np.uint8).reshape(H, W, 3)
