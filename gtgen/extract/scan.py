"""The read: one pass over the bags, in record-time slices that run on the process pool.

Each slice reads the small topics (odometry, TF, GNSS, camera info) whole, notes the
header stamps of the large ones (maps, voxel map, images) and, given a stager, stages
what the plan will likely keep. A slice spans at most ``SLICE_S`` of the bag, so memory
stays flat in drive length; the merged scan does not depend on the split.

Every message of every role is checked here, once, before the plan is made: one that
does not decode (a GridMap whose data do not fit its layout, a JPEG that does not open, a
PointCloud2 shorter than its points) is a decode failure of its topic, a GridMap of
another size than the topic's first is dropped (``size_changed``), and one recorded twice
(same topic, stamp and bytes) is dropped as ``duplicate``, within a slice as it is read
and across slices when they are merged. So the plan only ever picks messages that decode,
and only a role left with no usable message stops the run.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.gridmap import check_gridmap
from gtgen.bag.decode.image import decode_image, image_source, intrinsics
from gtgen.bag.decode.pointcloud import decode_pointcloud, decode_scan
from gtgen.bag.decode.tf import frame_id, odometry_pose, quat_xyzw, transform_matrix
from gtgen.bag.reader import BagSet, Record, detached, stamp_ns
from gtgen.bag.tf import Edge, EdgeSamples, relevant_edges
from gtgen.config import GtgenConfig
from gtgen.errors import DecodeError
from gtgen.extract.inventory import DUPLICATE, UNUSABLE_MAP, Key, Scan, TopicStats
from gtgen.extract.roles import is_large, reference_role
from gtgen.extract.stage import Stager

SLICE_S = 20.0  # longest record-time slice of a pass [s]: bounds the memory of one job


def slices(bags: BagSet, workers: int, n: int | None = None) -> list[tuple[int | None, int | None]]:
    """Return record-time slices [start, stop) covering the bags (``n`` of them if given);
    the ends are open."""
    lo, hi = bags.time_range()
    n = n or max(2 * workers if workers > 1 else 1, int(np.ceil((hi - lo) * 1e-9 / SLICE_S)))
    edges = [lo + (hi - lo) * i // n for i in range(n + 1)]
    bounds: list[tuple[int | None, int | None]] = [(edges[i], edges[i + 1]) for i in range(n) if edges[i] < edges[i + 1]]
    if not bounds:
        return [(None, None)]
    bounds[0] = (None, bounds[0][1])
    bounds[-1] = (bounds[-1][0], None)
    return bounds


def import_readers() -> None:
    """Import what a slice needs (a pool worker's warm-up)."""
    import mcap.reader  # noqa: F401
    import numcodecs  # noqa: F401
    import PIL.Image  # noqa: F401
    import rosbags.highlevel  # noqa: F401
    import zarr  # noqa: F401
    import zstandard  # noqa: F401


@dataclass(frozen=True)
class Frames:
    """What every slice knows before it starts: the static TF edges and the frames the
    drive's data is published in (from the first message of each large topic)."""

    static: dict[Edge, NDArray]
    data: frozenset[str]


def prepass(bags: BagSet, cfg: GtgenConfig, roles: dict[str, str]) -> Frames:
    """Read ``tf_static`` and the first message of each large topic (cheap: only the chunks
    that hold them are read)."""
    tp = cfg.topics
    static: dict[Edge, NDArray] = {}
    frames = {tp.odom_frame, tp.base_frame}
    for _, _, _, msg, _ in bags.messages([tp.tf_static]):
        if msg is not None:
            static.update({(frame_id(tr.header.frame_id), frame_id(tr.child_frame_id)): transform_matrix(tr.transform)
                           for tr in msg.transforms})  # type: ignore[attr-defined]
    for topic, role in roles.items():
        if is_large(role) or role.startswith("camera_info."):
            for _, _, _, msg, _ in bags.messages([topic]):
                if msg is not None:
                    frames.add(frame_id(_header(role, msg).frame_id))
                    break
    return Frames(static, frozenset(frames))


def _header(role: str, msg: object) -> object:
    # a ROS 1 GridMap carries its header in info
    return msg.info.header if role.startswith("map.") and not hasattr(msg, "header") else msg.header  # type: ignore[attr-defined]


def scan_slice(paths: list[Path], cfg: GtgenConfig, roles: dict[str, str], frames: Frames, start: int | None,
               stop: int | None, store: str | None = None, k: int = 0) -> Scan:
    """The pass over the messages recorded in [start, stop) (a process-pool job). With a
    ``store``, what the plan will likely keep is staged there as slice ``k``. Only the
    dynamic TF edges that can connect the data's frames are kept (memory)."""
    with BagSet(paths) as bags:
        if store is None:
            scan = scan_messages(bags.records(list(roles), start, stop), cfg, roles)
        else:
            with Stager(store, k, cfg, reference_role(cfg, roles.values())) as stager:
                scan = scan_messages(bags.records(list(roles), start, stop), cfg, roles, stager)
            scan.staged = stager.result
        scan.warnings = list(bags.warnings)
    seen = frames.data | set(scan.frames.values()) | set(scan.voxel_frames) | {m[2] for v in scan.map_meta.values() for m in v}
    keep = relevant_edges(list(scan.tf), [*frames.static, *scan.static], seen - {""})
    scan.tf = defaultdict(EdgeSamples, {e: s for e, s in scan.tf.items() if e in keep})
    for s in scan.tf.values():
        s.pack()
    for u in scan.used.values():
        u.arrays()
    return scan


def any_confident(conf: NDArray) -> bool:
    """True if any confidence value is finite and > 0 (a leading block decides most maps)."""
    head = conf[:4096]
    if np.any((head > 0) & (head < np.inf)):
        return True
    return bool(np.any((conf > 0) & (conf < np.inf)))


class _Scanner:
    """Takes each message of a pass into a Scan; the stager, if any, sees every usable
    large message."""

    def __init__(self, cfg: GtgenConfig, roles: dict[str, str], stager: Stager | None) -> None:
        self.cfg, self.roles, self.stager = cfg, roles, stager
        self.scan = Scan(stats={t: TopicStats(t, r) for t, r in roles.items()})
        tp = cfg.topics
        self.layer_names = [tp.layers.elevation, tp.layers.risk, tp.layers.confidence]
        self.seen: dict[str, dict[Key, bool]] = defaultdict(dict)  # topic -> {key: whether it decoded}

    def take(self, topic: str, msgtype: str, t_rec: int, msg: object | None, err: str | None, digest: tuple[int, int]) -> None:
        s = self.scan.stats[topic]
        role = self.roles[topic]
        s.count += 1
        i = s.count - 1
        if msg is None:
            self._unusable(s, role, err or "")
            return
        key = (self._stamp(role, msg), *digest)
        if key in self.seen[topic]:  # recorded twice: a copy of a message that did not decode fails alike
            self._unusable(s, role, None if self.seen[topic][key] else s.first_error)
            return
        try:
            data = self._decoded(role, msg, msgtype)
        except DecodeError as e:
            self.seen[topic][key] = False
            self._unusable(s, role, str(e))
            return
        self.seen[topic][key] = True
        if role in ("tf_static", "tf"):
            self.scan.used[topic].add(i, key, 0.0)
            self._tf(role, msg)
            return
        hdr = _header(role, msg)
        t = key[0]
        skew = abs(t_rec - t) * 1e-9
        self.scan.used[topic].add(i, key, skew)
        s.stamps.append(t)
        s.record_skew_max_s = max(s.record_skew_max_s, skew)
        if role == "odometry":
            self.scan.odom.append((t, *data, i))
        elif role == "gnss":
            self._gnss(t, msg, i)
        elif role.startswith("camera_info."):
            self.scan.info.setdefault(role.split(".")[1], detached(msg))  # the scan goes back to the parent
        elif role.startswith("camera."):
            self.scan.stamps[role].append(t)
            self.scan.frames.setdefault(role, frame_id(hdr.frame_id))
            if self.stager is not None:
                self.stager.add_image(role, i, t, image_source(msg, msgtype, data))  # type: ignore[arg-type]
        elif role == "voxel_map":
            frame = frame_id(hdr.frame_id)
            self.scan.stamps[role].append(t)
            self.scan.voxel_frames.append(frame)
            if self.stager is not None:
                self.stager.add_voxels(i, t, data, frame)
        elif role.startswith("map."):
            self._map(role, s, i, t, msg, frame_id(hdr.frame_id), data)
        elif role.startswith("lidar."):
            self.scan.stamps[role].append(t)
            self.scan.frames.setdefault(role, frame_id(hdr.frame_id))
            if self.stager is not None:
                self.stager.add_scan(role, i, t, *data)

    def _stamp(self, role: str, msg: object) -> int:
        if role in ("tf_static", "tf"):
            trs = msg.transforms  # type: ignore[attr-defined]
            return stamp_ns(trs[0].header) if len(trs) else 0
        return stamp_ns(_header(role, msg))

    def _decoded(self, role: str, msg: object, msgtype: str) -> object:
        """Return what a message decodes to (an image, points, a GridMap's grid, a pose,
        intrinsics), so the plan never picks one that does not; raise DecodeError."""
        if role.startswith("camera."):
            return decode_image(msg, msgtype)
        if role == "voxel_map":
            return decode_pointcloud(msg)
        if role.startswith("lidar."):
            return decode_scan(msg)
        if role.startswith("map."):
            return check_gridmap(msg, self.layer_names)
        if role == "odometry":
            return odometry_pose(msg)
        if role.startswith("camera_info."):
            return intrinsics(msg)
        return None

    def _unusable(self, s: TopicStats, role: str, err: str | None) -> None:
        """Count a message the plan must not pick: a decode failure (``err``, a duplicate
        if None); keep the large roles' lists aligned with the ordinals."""
        if err is None:
            s.drop(DUPLICATE)
        else:
            s.decode_failures += 1
            s.first_error = s.first_error or err
        if role.startswith("map."):
            self.scan.map_meta[role].append(UNUSABLE_MAP)
        elif role.startswith(("camera.", "lidar.")) or role == "voxel_map":
            self.scan.stamps[role].append(-1)
            if role == "voxel_map":
                self.scan.voxel_frames.append("")

    def _tf(self, role: str, msg: object) -> None:
        for tr in msg.transforms:  # type: ignore[attr-defined]
            parent, child = frame_id(tr.header.frame_id), frame_id(tr.child_frame_id)
            if role == "tf_static":
                self.scan.static[(parent, child)] = transform_matrix(tr.transform)
            else:
                tt = tr.transform.translation
                self.scan.tf[(parent, child)].add(stamp_ns(tr.header), (tt.x, tt.y, tt.z), quat_xyzw(tr.transform.rotation))

    def _gnss(self, t: int, msg: object, i: int) -> None:
        cov = np.asarray(msg.position_covariance, dtype=np.float64)  # type: ignore[attr-defined]
        var = cov[[0, 4, 8]] if msg.position_covariance_type > 0 and cov.size == 9 else np.full(3, np.nan)  # type: ignore[attr-defined]
        self.scan.gnss.append((t, msg.latitude, msg.longitude, msg.altitude, var, msg.status.status, i))  # type: ignore[attr-defined]

    def _map(self, role: str, s: TopicStats, i: int, t: int, msg: object, frame: str, grid: tuple) -> None:
        names = list(msg.layers)  # type: ignore[attr-defined]
        conf = msg.data[names.index(self.cfg.topics.layers.confidence)].data  # type: ignore[attr-defined]
        ok = any_confident(np.asarray(conf))
        if not ok:
            s.first_error = s.first_error or "all-NaN or zero-confidence map"
        self.scan.map_meta[role].append((t, ok, frame, grid))
        if self.stager is not None:
            self.stager.add_map(role, i, t, msg, ok)


def scan_messages(records: Iterable[Record], cfg: GtgenConfig, roles: dict[str, str], stager: Stager | None = None) -> Scan:
    """Return the Scan of ``records`` (messages with their digests); ``stager`` sees every
    usable large message."""
    scanner = _Scanner(cfg, roles, stager)
    for r in records:
        scanner.take(*r)
    return scanner.scan
