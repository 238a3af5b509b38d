"""Decode sensor_msgs/PointCloud2 into xyz arrays (and a per-point time, if the cloud has one).

A real cloud carries more than x, y, z: intensity, ring, per-point time, padding
(a Velodyne HDL-64E driver: x, y, z, intensity float32, ring uint16 at 20, 8 bytes of
padding, point_step 32). Fields are read at their offsets through one structured dtype
of ``point_step`` bytes, rows at ``row_step`` (organised clouds may pad their rows).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.errors import DecodeError
from gtgen.geometry import all_columns, finite_rows

FLOAT_KINDS = {7: "f4", 8: "f8"}  # PointField FLOAT32, FLOAT64
KINDS = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}  # every PointField datatype
# per-point time fields of common drivers and their unit [s]: velodyne / ouster ROS 2 (time, t),
# livox / hesai (timestamp, offset_time)
TIME_FIELDS = {"time": 1.0, "t": 1e-9, "timestamp": 1.0, "offset_time": 1e-9}


def _records(msg: object, names: list[str]) -> np.ndarray:
    """Return the cloud's points as a structured array of the fields ``names`` (checked)."""
    fields = {f.name: f for f in msg.fields}  # type: ignore[attr-defined]
    if not all(k in fields for k in "xyz"):
        raise DecodeError(f"PointCloud2 has fields {sorted(fields)}; expected x, y, z")
    if any(fields[k].datatype not in FLOAT_KINDS for k in "xyz"):
        raise DecodeError("PointCloud2 x/y/z must be FLOAT32 or FLOAT64")
    if any(fields[k].datatype not in KINDS for k in names):
        raise DecodeError(f"PointCloud2 fields {names} have datatypes {[fields[k].datatype for k in names]}; expected 1..8")
    endian = ">" if msg.is_bigendian else "<"  # type: ignore[attr-defined]
    w, h = int(msg.width), int(msg.height)  # type: ignore[attr-defined]
    step = int(msg.point_step)  # type: ignore[attr-defined]
    row = int(getattr(msg, "row_step", 0)) or w * step
    ends = [fields[k].offset + np.dtype(KINDS[fields[k].datatype]).itemsize for k in names]
    if max(ends) > step:
        raise DecodeError(f"PointCloud2 fields {names} end at bytes {ends}, beyond its point_step {step}")
    if row < w * step:
        raise DecodeError(f"PointCloud2 row_step {row} is shorter than width {w} x point_step {step}")
    need = (h - 1) * row + w * step if h else 0
    if len(msg.data) < need:  # type: ignore[attr-defined]
        raise DecodeError(f"PointCloud2 has {len(msg.data)} data bytes for {w * h} points of {step} bytes")  # type: ignore[attr-defined]
    dt = np.dtype({"names": names, "formats": [endian + KINDS[fields[k].datatype] for k in names],
                   "offsets": [fields[k].offset for k in names], "itemsize": step})
    raw = np.asarray(msg.data, dtype=np.uint8)  # type: ignore[attr-defined]
    if row == w * step:
        return raw[: w * h * step].view(dt)
    rows = np.lib.stride_tricks.as_strided(raw, (h, w * step), (row, 1))  # rows padded beyond their points
    return np.ascontiguousarray(rows).reshape(-1).view(dt)


def _xyz(rec: np.ndarray) -> NDArray[np.float32]:
    """Return the records' x, y, z as float32 (N, 3): one strided copy where the three are
    float32 side by side (most drivers), else a column per field."""
    from numpy.lib.recfunctions import structured_to_unstructured

    return np.ascontiguousarray(structured_to_unstructured(rec[["x", "y", "z"]], dtype=np.float32))


def time_field(msg: object) -> str | None:
    """Return the name of the cloud's per-point time field, if it has one."""
    names = {f.name for f in msg.fields}  # type: ignore[attr-defined]
    return next((n for n in TIME_FIELDS if n in names), None)


def decode_pointcloud(msg: object) -> NDArray[np.float32]:
    """Return the finite xyz points (N, 3) of a PointCloud2."""
    pts = _xyz(_records(msg, list("xyz")))
    return finite_rows(pts)


def decode_scan(msg: object) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
    """Return a lidar scan's finite xyz points (N, 3) and, if the cloud has a per-point time
    field (``TIME_FIELDS``), each point's time relative to the header stamp (N,) [s]."""
    tf = time_field(msg)
    rec = _records(msg, list("xyz") + ([tf] if tf else []))
    pts = _xyz(rec)
    ok = all_columns(np.isfinite(pts))
    if tf is None:
        return np.compress(ok, pts, axis=0), None
    t = rec[tf].astype(np.float64) * TIME_FIELDS[tf]
    if t.size and np.abs(t).max() > 1e6:  # absolute times (some drivers): relative to the header stamp
        hdr = msg.header.stamp  # type: ignore[attr-defined]
        t = t - (int(hdr.sec) + int(getattr(hdr, "nanosec", getattr(hdr, "nsec", 0))) * 1e-9)
    ok &= np.isfinite(t)
    return np.compress(ok, pts, axis=0), t[ok].astype(np.float32)  # rows by compress, as finite_rows
