"""Decode tf2_msgs/TFMessage transforms, and chain the static ones."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.errors import DecodeError
from gtgen.geometry import make_transform, quat_to_matrix


def frame_id(name: str) -> str:
    """Return a frame id without the leading slash ROS 1 allowed."""
    return str(name).lstrip("/")


def quat_xyzw(q: object) -> NDArray[np.float64]:
    """Return a geometry_msgs/Quaternion as an xyzw array."""
    return np.array([q.x, q.y, q.z, q.w])  # type: ignore[attr-defined]


def odometry_pose(msg: object) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return the position (3,) and quaternion xyzw (4,) of a nav_msgs/Odometry; raise
    DecodeError where they are not a pose (not finite, a zero quaternion)."""
    p = msg.pose.pose.position  # type: ignore[attr-defined]
    pos, q = np.array([p.x, p.y, p.z]), quat_xyzw(msg.pose.pose.orientation)  # type: ignore[attr-defined]
    if not (np.isfinite(pos).all() and np.isfinite(q).all() and np.linalg.norm(q) > 0.5):
        raise DecodeError(f"Odometry pose {pos.tolist()}, quaternion {q.tolist()} is not a pose")
    return pos, q


def transform_matrix(tr: object) -> NDArray[np.float64]:
    """Return the 4x4 matrix of a geometry_msgs/Transform."""
    t = tr.translation  # type: ignore[attr-defined]
    return make_transform(quat_to_matrix(quat_xyzw(tr.rotation)), np.array([t.x, t.y, t.z]))  # type: ignore[attr-defined]
