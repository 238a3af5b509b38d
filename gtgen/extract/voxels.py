"""Voxel-map points: put in odom, capped to the nearest ones, padded into fixed-size rows."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.pointcloud import decode_pointcloud
from gtgen.bag.decode.tf import frame_id
from gtgen.bag.reader import stamp_ns
from gtgen.bag.tf import TfBuffer
from gtgen.config import GtgenConfig


def voxel_points(msg: object, cfg: GtgenConfig, tf: TfBuffer) -> NDArray[np.float32]:
    """Return a voxel map's points in odom (through TF at its stamp), at most
    ``shards.max_voxel_points`` (the nearest)."""
    pts = decode_pointcloud(msg)
    frame = frame_id(msg.header.frame_id)  # type: ignore[attr-defined]
    return nearest_points(to_odom_frame(pts, cfg, tf, frame, stamp_ns(msg.header)), cfg.shards.max_voxel_points)  # type: ignore[attr-defined]


def padded(pts: NDArray[np.float32], n: int) -> NDArray[np.float32]:
    """Return ``pts`` (at most ``n``) as an (n, 3) block, NaN after the last point."""
    out = np.full((n, 3), np.nan, np.float32)
    out[: len(pts)] = pts
    return out


def to_odom_frame(pts: NDArray[np.float32], cfg: GtgenConfig, tf: TfBuffer, frame: str, t: int) -> NDArray[np.float32]:
    """Return points given in ``frame`` at time ``t`` in odom."""
    if frame in ("", cfg.topics.odom_frame):
        return pts
    T = tf.at(cfg.topics.odom_frame, frame, t)
    return (pts @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def nearest_points(pts: NDArray[np.float32], n: int) -> NDArray[np.float32]:
    """Return the ``n`` points nearest the cloud's xy centroid (the far ones matter least), in order."""
    if len(pts) <= n:
        return pts
    c = pts[:, :2].mean(axis=0)
    d2 = np.square(pts[:, 0] - c[0]) + np.square(pts[:, 1] - c[1])
    return pts[np.sort(np.argpartition(d2, n - 1)[:n])]
