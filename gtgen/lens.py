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
from functools import cached_property

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
    """A resampling of a source image onto an (H, W) one: the source pixel coordinates
    (u, v) [px] each output pixel takes its value from, bilinearly; black beyond the
    source's outer pixel centres. The four source pixels and their weights of every output
    pixel are worked out once (``taps``), so each image costs four gathers and a weighted
    sum; :meth:`naive` (``grids.bilinear``, gtgen's one bilinear sampler) is its oracle."""

    u: NDArray[np.float64]  # (H, W) source column of each output pixel
    v: NDArray[np.float64]  # (H, W) source row
    src_shape: tuple[int, int]  # source (h, w)

    @cached_property
    def taps(self) -> tuple[NDArray[np.intp], NDArray[np.float32]]:
        """The flat source indices (4, H*W) of each output pixel's four neighbours and their
        bilinear weights (4, H*W, 1), worked out once; weight 0 outside the source."""
        h, w = self.src_shape
        u, v = self.u.ravel(), self.v.ravel()
        inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        j0 = np.clip(np.floor(u), 0, max(w - 2, 0)).astype(np.intp)  # the last centre: j0 = w-2, fc = 1
        i0 = np.clip(np.floor(v), 0, max(h - 2, 0)).astype(np.intp)
        fc, fr = np.where(inside, u - j0, 0.0), np.where(inside, v - i0, 0.0)
        j1, i1 = np.minimum(j0 + 1, w - 1), np.minimum(i0 + 1, h - 1)
        idx = np.stack([i0 * w + j0, i0 * w + j1, i1 * w + j0, i1 * w + j1])
        wts = np.stack([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc]) * inside
        return idx, wts.astype(np.float32)[..., None]

    def __call__(self, img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """Return ``img`` (h, w, C) resampled onto the output grid (H, W, C)."""
        if img.shape[:2] != self.src_shape:
            raise ValueError(f"remap made for {self.src_shape} images, got {img.shape[:2]}")
        idx, wts = self.taps
        flat = img.reshape(-1, img.shape[-1])
        acc = np.take(flat, idx[0], axis=0) * wts[0]  # take: a quarter of fancy indexing's time on (N, C) rows
        for k in range(1, 4):
            acc += np.take(flat, idx[k], axis=0) * wts[k]
        acc += 0.5
        return np.clip(acc, 0, 255).astype(np.uint8).reshape(*self.u.shape, img.shape[-1])

    def naive(self, img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """The same resampling by ``grids.bilinear`` per channel (the test oracle)."""
        from gtgen.grids import bilinear

        out = bilinear(np.moveaxis(img, -1, 0).astype(np.float32), self.v, self.u, outside="nan")
        return np.clip(np.nan_to_num(np.moveaxis(out, 0, -1), nan=0.0) + 0.5, 0, 255).astype(np.uint8)


def rectify_remap(lens: Lens, K: NDArray, size: tuple[int, int]) -> Remap:
    """Return the :class:`Remap` that turns a raw image of ``size`` (width, height) taken
    through ``lens`` with intrinsics K into the pinhole image with the same K and size."""
    W, H = size
    K = np.asarray(K, np.float64)
    px, py = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    yn = (py - K[1, 2]) / K[1, 1]
    xn = (px - K[0, 2] - K[0, 1] * yn) / K[0, 0]
    xd, yd = lens.distort(xn, yn)
    return Remap(K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2], (H, W))


def project(K: NDArray, P_cam: NDArray, lens: Lens | None = None) -> NDArray[np.float64]:
    """Return the pixels (N, 2) of points ``P_cam`` (N, 3, optical frame, z > 0) through
    intrinsics K and ``lens`` (None: a pinhole)."""
    P = np.atleast_2d(np.asarray(P_cam, np.float64))
    x, y = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    if lens is not None:
        x, y = lens.distort(x, y)
    return np.column_stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]])
