"""Decode sensor_msgs/CompressedImage and Image into RGB arrays, and resize them; read
the intrinsics of a sensor_msgs/CameraInfo."""

from __future__ import annotations

import io

import numpy as np
from numpy.typing import NDArray

from gtgen.errors import DecodeError

CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}


def decode_image(msg: object, msgtype: str) -> NDArray[np.uint8]:
    """Return an RGB uint8 image (H, W, 3) from a CompressedImage or Image message."""
    from PIL import Image

    if msgtype.endswith("CompressedImage"):
        try:
            img = Image.open(io.BytesIO(bytes(msg.data))).convert("RGB")  # type: ignore[attr-defined]
        except Exception as err:  # noqa: BLE001 - PIL raises several types
            raise DecodeError(f"CompressedImage ({msg.format!r}) does not decode: {err}") from err  # type: ignore[attr-defined]
        return np.asarray(img)
    enc = str(msg.encoding).lower()  # type: ignore[attr-defined]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)  # type: ignore[attr-defined]
    raw = np.asarray(msg.data, dtype=np.uint8)  # type: ignore[attr-defined]
    if enc not in CHANNELS:
        raise DecodeError(f"Image encoding {enc!r} unsupported; expected one of {sorted(CHANNELS)}")
    if h < 1 or w < 1 or step < w * CHANNELS[enc] or raw.size < h * step:
        raise DecodeError(f"Image {w} x {h} {enc} with step {step} needs {h * max(step, w * CHANNELS[enc])} bytes; it has {raw.size}")
    arr = raw[: h * step].reshape(h, step)[:, : w * CHANNELS[enc]].reshape(h, w, CHANNELS[enc])
    if enc.startswith("bgr"):
        arr = arr[..., [2, 1, 0]]
    if CHANNELS[enc] == 1:
        arr = np.repeat(arr, 3, axis=-1)
    return np.ascontiguousarray(arr[..., :3])


def resize_image(img: NDArray[np.uint8], width: int, height: int) -> NDArray[np.uint8]:
    """Return ``img`` resized (bilinear) to width x height."""
    if img.shape[1] == width and img.shape[0] == height:
        return img
    from PIL import Image

    return np.asarray(Image.fromarray(img).resize((width, height), Image.BILINEAR))


def intrinsics(info: object) -> tuple[NDArray[np.float64], tuple[int, int]]:
    """Return the intrinsics K (3, 3) of a CameraInfo (ROS 1 or 2 field names) and the
    (width, height) [px] they are for; raise DecodeError for an uncalibrated one (a size
    of 0, a K that is not finite or has no focal length), whose K would rescale into
    infinities."""
    K = np.asarray(info.k if hasattr(info, "k") else info.K, dtype=np.float64).reshape(3, 3)  # type: ignore[attr-defined]
    size = (int(info.width), int(info.height))  # type: ignore[attr-defined]
    if min(size) < 1 or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DecodeError(f"CameraInfo of {size[0]} x {size[1]} px with focal lengths {K[0, 0]}, {K[1, 1]} is not a calibration")
    return K, size
