"""Decode sensor_msgs/CompressedImage and Image into RGB arrays, resize them, encode and
decode JPEG files; read the intrinsics and lens of a sensor_msgs/CameraInfo."""

from __future__ import annotations

import io

import numpy as np
from numpy.typing import NDArray

from gtgen.errors import DecodeError
from gtgen.lens import Lens

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


def image_source(msg: object, msgtype: str, rgb: NDArray[np.uint8] | None = None) -> bytes | NDArray[np.uint8]:
    """Return what an image message carries as it came: a CompressedImage's file bytes,
    else its RGB (``rgb`` if decoded already): a raw Image has no file to keep."""
    if msgtype.endswith("CompressedImage"):
        return bytes(msg.data)  # type: ignore[attr-defined]
    return decode_image(msg, msgtype) if rgb is None else rgb


def is_jpeg(data: bytes) -> bool:
    """Whether ``data`` is a JPEG file (starts with the SOI marker)."""
    return data[:3] == b"\xff\xd8\xff"


def file_size(data: bytes) -> tuple[int, int]:
    """Return the (width, height) [px] an image file's header gives, without decoding it."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as img:
            return int(img.size[0]), int(img.size[1])
    except Exception as err:  # noqa: BLE001 - PIL raises several types
        raise DecodeError(f"image file of {len(data)} bytes does not open: {err}") from err


def decode_file(data: bytes) -> NDArray[np.uint8]:
    """Return the RGB uint8 image (H, W, 3) of an image file (JPEG, PNG)."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as img:
            return np.asarray(img.convert("RGB"))
    except Exception as err:  # noqa: BLE001 - PIL raises several types
        raise DecodeError(f"image file of {len(data)} bytes does not decode: {err}") from err


def encode_jpeg(img: NDArray[np.uint8], quality: int) -> bytes:
    """Return the JPEG file of RGB ``img`` (H, W, 3) at ``quality`` (1-100, 4:2:0 chroma)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img)).save(buf, format="JPEG", quality=int(quality))
    return buf.getvalue()


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


def lens(info: object) -> Lens:
    """Return the lens (distortion model and D) of a CameraInfo (ROS 1 or 2 field names)."""
    D = info.d if hasattr(info, "d") else info.D  # type: ignore[attr-defined]
    return Lens.of(str(info.distortion_model), D)  # type: ignore[attr-defined]
