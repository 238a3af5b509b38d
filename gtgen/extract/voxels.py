"""Voxel-map points: to odom, capped to the nearest ones, padded into fixed-size rows."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.pointcloud import decode_pointcloud
from gtgen.bag.decode.tf import frame_id
from gtgen.bag.poses import PoseTrack
from gtgen.bag.reader import stamp_ns
from gtgen.config import GtgenConfig
from gtgen.errors import DecodeError


def voxel_points(msg: object, cfg: GtgenConfig, track: PoseTrack) -> NDArray[np.float32]:
    """Return a voxel map's points in odom, at most ``shards.max_voxel_points`` (the nearest)."""
    tp = cfg.topics
    pts = decode_pointcloud(msg)
    frame = frame_id(msg.header.frame_id)  # type: ignore[attr-defined]
    if frame not in ("", tp.odom_frame):
        if frame != tp.base_frame:
            raise DecodeError(f"voxel map frame '{frame}' unsupported; expected '{tp.odom_frame}' or '{tp.base_frame}'")
        pts = base_to_odom(pts, stamp_ns(msg.header), track)  # type: ignore[attr-defined]
    return nearest_points(pts, cfg.shards.max_voxel_points)


def padded(pts: NDArray[np.float32], n: int) -> NDArray[np.float32]:
    """Return ``pts`` (at most ``n``) as an (n, 3) block, NaN after the last point."""
    out = np.full((n, 3), np.nan, np.float32)
    out[: len(pts)] = pts
    return out


def base_to_odom(pts: NDArray[np.float32], t: int, track: PoseTrack) -> NDArray[np.float32]:
    """Return points given in the base frame at time ``t`` in odom."""
    T = track.transforms(np.array([t]))[0]
    return (pts @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def nearest_points(pts: NDArray[np.float32], n: int) -> NDArray[np.float32]:
    """Return the ``n`` points nearest the cloud's xy centroid (the far ones matter least), in order."""
    if len(pts) <= n:
        return pts
    c = pts[:, :2].mean(axis=0)
    d2 = np.square(pts[:, 0] - c[0]) + np.square(pts[:, 1] - c[1])
    return pts[np.sort(np.argpartition(d2, n - 1)[:n])]
