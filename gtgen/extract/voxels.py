"""Voxel-map points: put in odom, thinned with range to a cap, padded into fixed-size rows."""

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
    ``shards.max_voxel_points`` (thinned far away, see ``thinned_points``)."""
    pts = decode_pointcloud(msg)
    frame = frame_id(msg.header.frame_id)  # type: ignore[attr-defined]
    return thinned_points(to_odom_frame(pts, cfg, tf, frame, stamp_ns(msg.header)), cfg.shards.max_voxel_points, cfg.shards.far_voxel_m)  # type: ignore[attr-defined]


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


def thinned_points(pts: NDArray[np.float32], n: int, far_voxel_m: float) -> NDArray[np.float32]:
    """Return at most ``n`` of ``pts``, in order: every point within a radius R of the
    cloud's xy centroid, and beyond R one point per ``far_voxel_m`` voxel (the nearest of
    the voxel's points to the centroid), with R the largest radius that keeps the total
    within ``n``. Far away the map keeps its extent at a coarser voxel instead of being cut
    off; if even the coarse voxels are too many, the ``n`` nearest of them are kept."""
    if len(pts) <= n:
        return pts
    c = pts[:, :2].mean(axis=0)
    r = np.hypot(pts[:, 0] - c[0], pts[:, 1] - c[1])
    ijk = np.floor(pts / np.float32(far_voxel_m)).astype(np.int64) + (1 << 20)  # 21 bits per axis: +-1.6 km at 1.6 m
    key = (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]
    order = np.lexsort((r, key))  # by voxel, nearest first
    k = key[order]
    first = np.ones(len(k), bool)
    first[1:] = k[1:] != k[:-1]
    rep = order[first]  # the nearest point of each coarse voxel
    r_all, r_rep = np.sort(r), np.sort(r[rep])
    # total(R = r_all[i]) = i points nearer than R + the coarse voxels whose representative is at R or beyond
    total = np.arange(len(r_all)) + len(r_rep) - np.searchsorted(r_rep, r_all, side="left")
    ok = np.nonzero(total <= n)[0]
    if not len(ok):  # the coarse voxels alone are too many: the nearest of them
        keep = rep[np.argsort(r[rep], kind="stable")[:n]]
        return pts[np.sort(keep)]
    R = r_all[ok[-1]]
    keep = np.union1d(np.nonzero(r < R)[0], rep[r[rep] >= R])
    return pts[keep]
