"""The drive's geometry from its small topics: the pose track, camera calibration, and
where a map published in another frame lies in odom."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.tf import chain, frame_id
from gtgen.bag.poses import PoseTrack
from gtgen.config import CAMERAS, GtgenConfig
from gtgen.errors import DecodeError, PoseError, TopicError
from gtgen.extract.scan import Scan
from gtgen.geometry import rescale_K, yaw_transform


def pose_track(cfg: GtgenConfig, scan: Scan) -> tuple[PoseTrack, list[str]]:
    """Return the pose track T_odom_base (odometry, else odom -> base TF) and warnings
    about its stamps and gaps."""
    src = scan.odom if scan.odom else scan.tf_dyn
    warnings: list[str] = []
    if not src:
        raise TopicError(f"role 'odometry': no usable message on '{cfg.topics.odometry}' (nor odom->base TF on '{cfg.topics.tf}')")
    t = np.array([s[0] for s in src], np.int64)
    track, ooo, dups = PoseTrack.from_unsorted(t, np.array([s[1] for s in src]), np.array([s[2] for s in src]),
                                              int(cfg.extract.pose_tolerance_s * 1e9))
    if ooo:
        warnings.append(f"odometry: {ooo} out-of-order stamps (sorted)")
    if dups:
        warnings.append(f"odometry: {dups} duplicate stamps (dropped)")
    if len(track) < 2:
        raise PoseError(f"odometry has {len(track)} distinct stamps; expected at least 2")
    gaps = np.diff(track.t_ns) * 1e-9
    big = gaps > 2 * cfg.extract.pose_tolerance_s
    if big.any():
        warnings.append(f"odometry: {int(big.sum())} gaps longer than {2 * cfg.extract.pose_tolerance_s:.2f} s "
                        f"(max {gaps.max():.2f} s); samples there are rejected")
    for s in scan.stats.values():
        if s.record_skew_max_s > cfg.extract.record_skew_warn_s:
            warnings.append(f"{s.topic}: header stamps differ from record times by up to {s.record_skew_max_s:.1f} s (header stamps are used)")
    return track, warnings


def extrinsics(cfg: GtgenConfig, scan: Scan) -> dict[str, tuple[NDArray, NDArray, tuple[int, int]]]:
    """Return per camera (K rescaled to the stored image size, T_base_cam, source size)."""
    out = {}
    W, H = cfg.extract.image_width, cfg.extract.image_height
    for c in CAMERAS:
        info = scan.info.get(c)
        if info is None:
            raise TopicError(f"role 'camera_info.{c}': no CameraInfo on '{cfg.topics.cameras[c].info}'")
        Kraw = np.asarray(getattr(info, "k", None) if hasattr(info, "k") else info.K, dtype=np.float64).reshape(3, 3)
        src = (int(info.width), int(info.height))
        frame = scan.frames.get(f"camera.{c}") or frame_id(info.header.frame_id)
        T = chain(scan.static, cfg.topics.base_frame, frame)
        if T is None:
            raise TopicError(f"camera '{c}': no static transform from '{cfg.topics.base_frame}' to '{frame}' in '{cfg.topics.tf_static}'")
        out[c] = (rescale_K(Kraw, src, (W, H)), T, src)
    return out


def map_to_odom(cfg: GtgenConfig, static: dict[tuple[str, str], NDArray], center: NDArray, yaw: float, frame: str
                ) -> tuple[NDArray, float]:
    """Return a grid's centre and yaw in odom, through tf_static if its frame differs."""
    if frame in ("", cfg.topics.odom_frame):
        return center, yaw
    T = chain(static, cfg.topics.odom_frame, frame)
    if T is None:
        raise DecodeError(f"GridMap frame '{frame}' has no static transform to '{cfg.topics.odom_frame}'")
    Tc = T @ yaw_transform(*center, yaw)
    return Tc[:3, 3], float(np.arctan2(Tc[1, 0], Tc[0, 0]))
