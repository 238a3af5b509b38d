"""The images a drive store keeps: each camera's frames at the configured size, rectified
when its CameraInfo has distortion, as JPEG files.

Size: the source (CameraInfo's width x height) scaled by the largest factor <= 1 that
fits it in ``extract.image_width`` x ``image_height``: the aspect is kept and nothing is
upscaled. Bytes: the camera's own JPEG when its frame is already at that size and the
lens has no distortion (no pixel is touched), else the frame is decoded, resized
(PIL's antialiased bilinear), undistorted with CameraInfo's model into the pinhole
camera of the same intrinsics (``gtgen.lens``), and encoded at ``extract.jpeg_quality``.
The intrinsics stored are those of the stored (rectified) image.

A stored JPEG lives in a zero-padded row of ``capacity(cfg)`` bytes (three bytes per
pixel of the configured size: more than any JPEG of an image that size at the qualities
allowed), with its length beside it, so the stores keep one fixed-shape uint8 chunk per
image and the padding costs nothing once compressed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.image import decode_file, encode_jpeg, file_size, intrinsics, is_jpeg, lens, resize_image
from gtgen.config import GtgenConfig
from gtgen.errors import DecodeError, TopicError
from gtgen.geometry import rescale_K
from gtgen.lens import Lens, Remap, rectify_remap

Source = bytes | NDArray[np.uint8]  # a CompressedImage's file, or a raw Image decoded to RGB


def capacity(cfg: GtgenConfig) -> int:
    """Return the bytes of the row that holds one stored JPEG (3 per pixel of the size box)."""
    return 3 * cfg.extract.image_width * cfg.extract.image_height


def stored_size(src_wh: tuple[int, int], box_wh: tuple[int, int]) -> tuple[int, int]:
    """Return the stored (width, height) of a ``src_wh`` image: scaled to fit ``box_wh``,
    aspect kept, never upscaled."""
    s = min(box_wh[0] / src_wh[0], box_wh[1] / src_wh[1], 1.0)
    return max(1, int(round(src_wh[0] * s))), max(1, int(round(src_wh[1] * s)))


@dataclass
class StoredCamera:
    """How one camera's frames become stored JPEG files (picklable for pool jobs)."""

    name: str
    lens: Lens
    src_size: tuple[int, int]  # CameraInfo's (width, height) [px]
    size: tuple[int, int]  # stored (width, height) [px]
    K: NDArray[np.float64]  # intrinsics of the stored image (rectified: the raw K rescaled)
    quality: int
    capacity: int
    _remap: Remap | None = field(default=None, repr=False)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_remap": None}  # large; each process makes its own

    @property
    def passes_through(self) -> bool:
        """Whether the camera's own JPEG files can be stored as they are (right size, no distortion)."""
        return self.size == self.src_size and not self.lens.distorted

    def remap(self) -> Remap:
        """Return the rectifying resampling at the stored size (made once per process)."""
        if self._remap is None:
            self._remap = rectify_remap(self.lens, self.K, self.size)
        return self._remap

    def stored(self, src: Source) -> bytes:
        """Return the JPEG file stored for one frame ``src`` of this camera."""
        if isinstance(src, bytes):
            if is_jpeg(src) and not self.lens.distorted and len(src) <= self.capacity and file_size(src) == self.size:
                return src
            img = decode_file(src)
        else:
            img = src
        W, H = self.size
        img = resize_image(img, W, H)
        if self.lens.distorted:
            img = self.remap()(img)
        out = encode_jpeg(img, self.quality)
        if len(out) > self.capacity:
            raise DecodeError(f"camera '{self.name}': a {W} x {H} JPEG at quality {self.quality} took {len(out)} bytes, "
                              f"more than the {self.capacity} a stored image may take; lower extract.jpeg_quality")
        return out

    def padded(self, jpeg: bytes) -> NDArray[np.uint8]:
        """Return ``jpeg`` in its zero-padded row of ``capacity`` bytes."""
        row = np.zeros(self.capacity, np.uint8)
        row[: len(jpeg)] = np.frombuffer(jpeg, np.uint8)
        return row


def stored_cameras(cfg: GtgenConfig, info: dict[str, object]) -> list[StoredCamera]:
    """Return the configured cameras (``topics.cameras``' order) from their CameraInfo
    messages ``info``; raise TopicError for a camera without one, DecodeError for a
    CameraInfo that is no calibration or has a lens gtgen cannot undistort."""
    ex = cfg.extract
    cams = []
    for c in cfg.topics.camera_names:
        msg = info.get(c)
        if msg is None:
            raise TopicError(f"role 'camera_info.{c}': no CameraInfo on '{cfg.topics.cameras[c].info}'")
        K, src = intrinsics(msg)
        try:
            ln = lens(msg)
        except DecodeError as err:
            raise DecodeError(f"camera '{c}' ({cfg.topics.cameras[c].info}): {err}") from err
        size = stored_size(src, (ex.image_width, ex.image_height))
        cams.append(StoredCamera(c, ln, src, size, rescale_K(K, src, size), ex.jpeg_quality, capacity(cfg)))
    return cams


def read_source(file: Path) -> Source:
    """Return the frame a stager wrote to ``file`` (``write_source``)."""
    return np.load(file) if file.suffix == ".npy" else file.read_bytes()


def write_source(file: Path, src: Source) -> Path:
    """Write frame ``src`` to ``file`` (``.npy`` added for a raw image); return the file."""
    if isinstance(src, bytes):
        file.write_bytes(src)
        return file
    f = file.with_name(file.name + ".npy")
    with open(f, "wb") as fh:  # np.save on a path would add the suffix again
        np.save(fh, src)
    return f
