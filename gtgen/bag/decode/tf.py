"""Decode tf2_msgs/TFMessage transforms, and chain the static ones."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.geometry import make_transform, quat_to_matrix


def frame_id(name: str) -> str:
    """Return a frame id without the leading slash ROS 1 allowed."""
    return str(name).lstrip("/")


def quat_xyzw(q: object) -> NDArray[np.float64]:
    """Return a geometry_msgs/Quaternion as an xyzw array."""
    return np.array([q.x, q.y, q.z, q.w])  # type: ignore[attr-defined]


def transform_matrix(tr: object) -> NDArray[np.float64]:
    """Return the 4x4 matrix of a geometry_msgs/Transform."""
    t = tr.translation  # type: ignore[attr-defined]
    return make_transform(quat_to_matrix(quat_xyzw(tr.rotation)), np.array([t.x, t.y, t.z]))  # type: ignore[attr-defined]
