"""The drive's geometry from its small topics: the TF buffer, the pose track, camera
extrinsics, and where a message published in another frame lies in odom.

Every frame is put in ``odom_frame`` through the TF buffer, looked up at the message's
own stamp. A map, voxel map or image whose transform is missing at its stamp is not used
(counted per topic in the report as ``no_transform``); only a topic left with no usable
message fails the run, naming the missing edge.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.tf import frame_id
from gtgen.bag.poses import PoseTrack
from gtgen.bag.tf import TfBuffer
from gtgen.config import GtgenConfig
from gtgen.errors import PoseError, TopicError
from gtgen.extract.images import StoredCamera
from gtgen.extract.inventory import DUPLICATE, Scan
from gtgen.geometry import matrix_to_quat

NO_TRANSFORM = "no_transform"


def tf_buffer(cfg: GtgenConfig, scan: Scan) -> TfBuffer:
    """Return the drive's TF buffer (static and dynamic edges)."""
    return TfBuffer.from_samples(scan.static, scan.tf, int(cfg.extract.pose_tolerance_s * 1e9))


def pose_track(cfg: GtgenConfig, scan: Scan, tf: TfBuffer) -> tuple[PoseTrack, str, list[str]]:
    """Return the pose track T_odom_base, where it came from, and warnings about its stamps.

    Poses come from the Odometry topic, or with ``topics.odometry: null`` from TF
    ``odom_frame -> base_frame`` at the stamps of the dynamic edges between them. The odom
    -> base edge of an odometry track joins the TF buffer when TF does not connect them.
    """
    tp = cfg.topics
    tol = int(cfg.extract.pose_tolerance_s * 1e9)
    if tp.odometry is not None:  # the scan made sure it has a usable message
        t = np.array([s[0] for s in scan.odom], np.int64)
        track, ooo, dups = PoseTrack.from_unsorted(t, np.array([s[1] for s in scan.odom]), np.array([s[2] for s in scan.odom]), tol)
        source = f"odometry on '{tp.odometry}'"
    else:
        track, ooo, dups = _tf_track(cfg, tf)
        source = f"TF '{tp.odom_frame}' -> '{tp.base_frame}' on '{tp.tf}'"
    if len(track) < 2:
        raise PoseError(f"poses ({source}) have {len(track)} distinct stamps; expected at least 2")
    if tf.path(tp.odom_frame, tp.base_frame) is None:
        tf.add_dynamic((tp.odom_frame, tp.base_frame), track)
    return track, f"{source}: {len(track)} poses", _warnings(cfg, scan, track, ooo, dups)


def _tf_track(cfg: GtgenConfig, tf: TfBuffer) -> tuple[PoseTrack, int, int]:
    tp = cfg.topics
    path = tf.path(tp.odom_frame, tp.base_frame)
    if path is None:
        raise TopicError(f"topics.odometry is null, and {tf.why_not(tp.odom_frame, tp.base_frame)}")
    stamps = [tf.dynamic[e].t_ns for e, _ in path if e in tf.dynamic]
    if not stamps:
        raise TopicError(f"topics.odometry is null, but TF '{tp.odom_frame}' -> '{tp.base_frame}' is static: no motion to take poses from")
    t = np.unique(np.concatenate(stamps))
    T, ok = tf.lookup(tp.odom_frame, tp.base_frame, t)
    return PoseTrack(t[ok], T[ok, :3, 3], matrix_to_quat(T[ok, :3, :3]), int(cfg.extract.pose_tolerance_s * 1e9)), 0, 0


def _warnings(cfg: GtgenConfig, scan: Scan, track: PoseTrack, ooo: int, dups: int) -> list[str]:
    warnings = []
    if ooo:
        warnings.append(f"odometry: {ooo} out-of-order stamps (sorted)")
    if dups:
        warnings.append(f"odometry: {dups} messages share their stamp with an earlier one of other content (the first kept)")
    gaps = np.diff(track.t_ns) * 1e-9
    big = gaps > 2 * cfg.extract.pose_tolerance_s
    if big.any():
        warnings.append(f"poses: {int(big.sum())} gaps longer than {2 * cfg.extract.pose_tolerance_s:.2f} s "
                        f"(max {gaps.max():.2f} s); samples there are rejected")
    for s in scan.stats.values():
        if s.dropped.get(DUPLICATE):
            warnings.append(f"{s.topic}: {s.dropped[DUPLICATE]} duplicate messages (same stamp and bytes as an earlier one) dropped")
        if s.record_skew_max_s > cfg.extract.record_skew_warn_s:
            warnings.append(f"{s.topic}: header stamps differ from record times by up to {s.record_skew_max_s:.1f} s (header stamps are used)")
    return warnings


def drop_untransformable(cfg: GtgenConfig, scan: Scan, tf: TfBuffer) -> None:
    """Mark the maps, voxel maps and images whose frame has no transform at their stamp as
    unusable (counted per topic); raise TopicError for a topic left with none."""
    tp = cfg.topics
    topic_of = {s.role: s for s in scan.stats.values()}
    for role, meta in scan.map_meta.items():
        if role not in topic_of:  # no topic: made from lidar later (gtgen.extract.mapped)
            continue
        t = np.array([m[0] for m in meta], np.int64)
        frames = [m[2] for m in meta]
        ok = _known(tf, tp.odom_frame, frames, t) | (t < 0)
        topic_of[role].drop(NO_TRANSFORM, int(sum(1 for m, k in zip(meta, ok) if m[1] and not k)))
        scan.map_meta[role] = [(m[0], m[1] and bool(k), *m[2:]) for m, k in zip(meta, ok)]
    for role, frames, target in [("voxel_map", scan.voxel_frames, tp.odom_frame)] + \
            [(f"camera.{c}", [scan.frames.get(f"camera.{c}", "")] * len(scan.stamps[f"camera.{c}"]), tp.base_frame) for c in tp.cameras] + \
            [(r, [scan.frames.get(r, "")] * len(scan.stamps[r]), tp.odom_frame) for r in sorted(scan.stamps) if r.startswith("lidar.")]:
        if role not in topic_of:
            continue
        t = np.asarray(scan.stamps[role], np.int64)
        ok = _known(tf, target, frames, t) | (t < 0)
        topic_of[role].drop(NO_TRANSFORM, int((~ok).sum()))
        scan.stamps[role] = list(np.where(ok, t, -1))
    for role, s in topic_of.items():
        usable = sum(m[1] for m in scan.map_meta[role]) if role.startswith("map.") else sum(t >= 0 for t in scan.stamps.get(role, [1]))
        if s.dropped.get(NO_TRANSFORM) and not usable:
            frames = [m[2] for m in scan.map_meta[role]] if role.startswith("map.") else scan.voxel_frames if role == "voxel_map" else [scan.frames.get(role, "")]
            target = tp.base_frame if role.startswith("camera.") else tp.odom_frame
            raise TopicError(f"{s.topic}: none of its {s.count} messages can be put in '{target}': "
                             f"{tf.why_not(target, next((f for f in frames if f), '?'))}")


def _known(tf: TfBuffer, target: str, frames: list[str], t: NDArray) -> NDArray[np.bool_]:
    """Return where the transform target <- frame is known at stamp t (frames per message)."""
    ok = np.zeros(len(t), bool)
    for f in set(frames):
        sel = np.array([x == f for x in frames], bool)
        if f in ("", target):
            ok[sel] = True
        elif sel.any():
            ok[sel] = tf.lookup(target, f, t[sel])[1]
    return ok


def map_to_odom(cfg: GtgenConfig, tf: TfBuffer, center: NDArray, yaw: float, frame: str, t_ns: int) -> tuple[NDArray, float, float]:
    """Return a grid's centre and yaw in odom, and the height its elevations are measured
    from (the map frame's height at the grid centre, 0 for a map in odom)."""
    if frame in ("", cfg.topics.odom_frame):
        return np.asarray(center, np.float64), float(yaw), 0.0
    T = tf.at(cfg.topics.odom_frame, frame, t_ns)
    c, s = np.cos(yaw), np.sin(yaw)
    Tc = T @ np.array([[c, -s, 0, center[0]], [s, c, 0, center[1]], [0, 0, 1, center[2]], [0, 0, 0, 1.0]])
    z0 = float((T @ np.array([center[0], center[1], 0.0, 1.0]))[2])
    return Tc[:3, 3], float(np.arctan2(Tc[1, 0], Tc[0, 0])), z0


def extrinsics(cfg: GtgenConfig, scan: Scan, tf: TfBuffer, image_t: NDArray, cams: list[StoredCamera]) -> tuple[NDArray, NDArray]:
    """Return the intrinsics K (C, 3, 3) of the stored (rectified) images of the C cameras
    ``cams``, and per sample T_base_cam (S, C, 4, 4) at each image's stamp ``image_t`` (S, C)."""
    Ts = []
    for c_i, c in enumerate(cfg.topics.camera_names):
        frame = scan.frames.get(f"camera.{c}") or frame_id(scan.info[c].header.frame_id)  # type: ignore[attr-defined]
        T, ok = tf.lookup(cfg.topics.base_frame, frame, image_t[:, c_i])
        if not ok.all():
            raise TopicError(f"camera '{c}': no transform from '{cfg.topics.base_frame}' to '{frame}': {tf.why_not(cfg.topics.base_frame, frame)}")
        Ts.append(T)
    if not cams:
        return np.zeros((0, 3, 3)), np.zeros((len(image_t), 0, 4, 4))
    return np.stack([cam.K for cam in cams]), np.stack(Ts, axis=1)
