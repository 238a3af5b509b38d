"""Camera lenses as sensor_msgs/CameraInfo describes them: the distortion models, and
the maps that rectify an image (undistort it into the pinhole camera with the same K).

Models (ROS ``distortion_model``, coefficients D): ``plumb_bob`` (k1, k2, p1, p2[, k3]),
``rational_polynomial`` (k1, k2, p1, p2, k3, k4, k5, k6) and ``equidistant`` (the
fisheye model: k1, k2, k3, k4 on the angle from the axis). A lens whose coefficients
are all zero has no distortion, whatever its model. Normalised coordinates are those of
the camera's optical frame divided by z; pixel centres are at integer coordinates, as in
ROS. The rectification rotation R of CameraInfo is taken as the identity (monocular
cameras): the rectified camera is the raw one with its distortion removed, so the
extrinsics of the raw camera are those of the rectified image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen.errors import DecodeError

MODELS = ("plumb_bob", "rational_polynomial", "equidistant")
_N_COEFFS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}


@dataclass(frozen=True)
class Lens:
    """A camera's distortion: its model and coefficients D (zero-padded to the model's count)."""

    model: str
    D: tuple[float, ...]

    @classmethod
    def of(cls, model: str, D: object) -> Lens:
        """Return the lens of a CameraInfo's ``distortion_model`` and D; raise DecodeError
        for a model gtgen cannot undistort (unless D is all zero)."""
        d = np.asarray(D, np.float64).ravel()
        if not np.isfinite(d).all():
            raise DecodeError(f"CameraInfo distortion D={d.tolist()} is not finite")
        if not d.any():
            return cls("none", ())
        if model not in MODELS:
            raise DecodeError(f"CameraInfo distortion_model {model!r} with D={d.tolist()} unsupported; expected one of {list(MODELS)}")
        n = _N_COEFFS[model]
        if len(d) > n and d[n:].any():
            raise DecodeError(f"CameraInfo {model} takes {n} coefficients; D={d.tolist()} has more")
        return cls(model, tuple(np.pad(d[:n], (0, n - min(n, len(d)))).tolist()))

    @property
    def distorted(self) -> bool:
        """Whether the lens bends rays at all."""
        return self.model != "none"

    def distort(self, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
        """Return the distorted normalised coordinates of the ideal (pinhole) ones (x, y)."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if self.model == "none":
            return x, y
        if self.model == "equidistant":
            k1, k2, k3, k4 = self.D
            r = np.hypot(x, y)
            th = np.arctan(r)
            th2 = th * th
            thd = th * (1 + th2 * (k1 + th2 * (k2 + th2 * (k3 + th2 * k4))))
            s = np.where(r > 1e-12, thd / np.where(r > 1e-12, r, 1.0), 1.0)
            return x * s, y * s
        k1, k2, p1, p2, k3 = self.D[:5]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        if self.model == "rational_polynomial":
            k4, k5, k6 = self.D[5:]
            radial = radial / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xy = x * y
        return x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy

    def undistort(self, xd: NDArray, yd: NDArray, iterations: int = 30) -> tuple[NDArray, NDArray]:
        """Return the ideal normalised coordinates whose distortion is (xd, yd), by
        Gauss-Newton on :meth:`distort` (numerical Jacobian); exact to ~1e-10 within the
        lens's field of view."""
        xd, yd = np.asarray(xd, np.float64), np.asarray(yd, np.float64)
        if self.model == "none":
            return xd, yd
        x, y = xd.copy(), yd.copy()
        h = 1e-7
        for _ in range(iterations):
            fx, fy = self.distort(x, y)
            ex, ey = fx - xd, fy - yd
            ax, ay = self.distort(x + h, y)
            bx, by = self.distort(x, y + h)
            j11, j21, j12, j22 = (ax - fx) / h, (ay - fy) / h, (bx - fx) / h, (by - fy) / h
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            x = x - (j22 * ex - j12 * ey) / det
            y = y - (-j21 * ex + j11 * ey) / det
        return x, y


@dataclass(frozen=True)
class Remap:
    """A bilinear resampling of an (h, w) image onto an (H, W) one: for each output pixel
    its four source pixels (flat indices) and weights; outside the source it is black."""

    index: NDArray[np.int64]  # (4, H * W)
    weight: NDArray[np.float32]  # (4, H * W), zero outside the source
    shape: tuple[int, int]  # output (H, W)
    src_shape: tuple[int, int]  # source (h, w)

    def __call__(self, img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """Return ``img`` (h, w, C) resampled onto the output grid (H, W, C)."""
        if img.shape[:2] != self.src_shape:
            raise ValueError(f"remap made for {self.src_shape} images, got {img.shape[:2]}")
        flat = img.reshape(-1, img.shape[2]).astype(np.float32)
        out = np.zeros((self.index.shape[1], img.shape[2]), np.float32)
        for k in range(4):
            out += flat[self.index[k]] * self.weight[k][:, None]
        return np.clip(out + 0.5, 0, 255).astype(np.uint8).reshape(*self.shape, img.shape[2])


def remap_at(u: NDArray, v: NDArray, src_hw: tuple[int, int]) -> Remap:
    """Return the bilinear :class:`Remap` sampling source pixel coordinates (u, v) [px]
    (arrays of the output's shape); samples outside the source are black."""
    h, w = src_hw
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = (u - u0).ravel(), (v - v0).ravel()
    idx, wts = [], []
    for du, dv, wt in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        uu, vv = u0.ravel() + du, v0.ravel() + dv
        inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
        idx.append(np.where(inside, np.clip(vv, 0, h - 1) * w + np.clip(uu, 0, w - 1), 0))
        wts.append(np.where(inside, wt, 0.0))
    # a sample more than half a pixel outside the source is black; nearer, the edge pixels carry it
    ok = (u.ravel() > -0.5) & (u.ravel() < w - 0.5) & (v.ravel() > -0.5) & (v.ravel() < h - 0.5)
    W = np.array(wts)
    tot = W.sum(axis=0)
    W = np.where(ok & (tot > 0), W / np.where(tot > 0, tot, 1.0), 0.0)
    return Remap(np.array(idx), W.astype(np.float32), u.shape, (h, w))


def rectify_remap(lens: Lens, K: NDArray, size: tuple[int, int]) -> Remap:
    """Return the :class:`Remap` that turns a raw image of ``size`` (width, height) taken
    through ``lens`` with intrinsics K into the pinhole image with the same K and size."""
    W, H = size
    K = np.asarray(K, np.float64)
    px, py = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    yn = (py - K[1, 2]) / K[1, 1]
    xn = (px - K[0, 2] - K[0, 1] * yn) / K[0, 0]
    xd, yd = lens.distort(xn, yn)
    return remap_at(K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2], (H, W))


def project(K: NDArray, P_cam: NDArray, lens: Lens | None = None) -> NDArray[np.float64]:
    """Return the pixels (N, 2) of points ``P_cam`` (N, 3, optical frame, z > 0) through
    intrinsics K and ``lens`` (None: a pinhole)."""
    P = np.atleast_2d(np.asarray(P_cam, np.float64))
    x, y = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    if lens is not None:
        x, y = lens.distort(x, y)
    return np.column_stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]])
