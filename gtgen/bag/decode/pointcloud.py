"""Decode sensor_msgs/PointCloud2 into xyz arrays."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.errors import DecodeError

FLOAT_KINDS = {7: "f4", 8: "f8"}  # PointField FLOAT32, FLOAT64


def decode_pointcloud(msg: object) -> NDArray[np.float32]:
    """Return the finite xyz points (N, 3) of a PointCloud2."""
    fields = {f.name: f for f in msg.fields}  # type: ignore[attr-defined]
    if not all(k in fields for k in "xyz"):
        raise DecodeError(f"PointCloud2 has fields {sorted(fields)}; expected x, y, z")
    if any(fields[k].datatype not in FLOAT_KINDS for k in "xyz"):
        raise DecodeError("PointCloud2 x/y/z must be FLOAT32 or FLOAT64")
    endian = ">" if msg.is_bigendian else "<"  # type: ignore[attr-defined]
    n = int(msg.width) * int(msg.height)  # type: ignore[attr-defined]
    step = int(msg.point_step)  # type: ignore[attr-defined]
    ends = [fields[k].offset + np.dtype(FLOAT_KINDS[fields[k].datatype]).itemsize for k in "xyz"]
    if max(ends) > step:
        raise DecodeError(f"PointCloud2 fields x, y, z end at bytes {ends}, beyond its point_step {step}")
    if len(msg.data) < n * step:  # type: ignore[attr-defined]
        raise DecodeError(f"PointCloud2 has {len(msg.data)} data bytes for {n} points of {step} bytes")  # type: ignore[attr-defined]
    dt = np.dtype({"names": list("xyz"), "formats": [endian + FLOAT_KINDS[fields[k].datatype] for k in "xyz"],
                   "offsets": [fields[k].offset for k in "xyz"], "itemsize": step})
    raw = np.asarray(msg.data, dtype=np.uint8)  # type: ignore[attr-defined]
    rec = raw[: n * dt.itemsize].view(dt)
    pts = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float32)
    return pts[np.all(np.isfinite(pts), axis=1)]
