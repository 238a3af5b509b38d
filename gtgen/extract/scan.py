"""The read: one pass over the bags, in record-time slices that run on the process pool.

Each slice reads the small topics (odometry, TF, GNSS, camera info) whole, notes the
header stamps of the large ones (maps, voxel map, images) and, given a stager, stages
what the plan will likely keep. A slice spans at most ``SLICE_S`` of the bag, so memory
stays flat in drive length; the merged scan does not depend on the split.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.gridmap import decode_gridmap
from gtgen.bag.decode.tf import frame_id, quat_xyzw, transform_matrix
from gtgen.bag.reader import BagSet, Message, stamp_ns
from gtgen.bag.tf import Edge, EdgeSamples, relevant_edges
from gtgen.config import GtgenConfig
from gtgen.extract.roles import is_large
from gtgen.extract.stage import Staged, Stager

SLICE_S = 20.0  # longest record-time slice of a pass [s]: bounds the memory of one job


@dataclass
class TopicStats:
    """Per-topic report line."""

    topic: str
    role: str
    count: int = 0
    decode_failures: int = 0
    first_error: str = ""
    stamps: list[int] = field(default_factory=list)
    record_skew_max_s: float = 0.0
    dropped: dict[str, int] = field(default_factory=dict)  # messages not used, by why

    def drop(self, why: str, n: int = 1) -> None:
        """Count ``n`` messages not used because of ``why``."""
        if n:
            self.dropped[why] = self.dropped.get(why, 0) + n

    def summary(self) -> dict:
        """Return the report line (count, rate, largest gap, decode failures, skew)."""
        t = np.sort(np.asarray(self.stamps, dtype=np.int64))
        span = (t[-1] - t[0]) * 1e-9 if len(t) > 1 else 0.0
        gaps = np.diff(t) * 1e-9 if len(t) > 1 else np.zeros(0)
        return {
            "topic": self.topic,
            "role": self.role,
            "count": self.count,
            "rate_hz": round((len(t) - 1) / span, 3) if span > 0 else 0.0,
            "max_gap_s": round(float(gaps.max()), 3) if len(gaps) else 0.0,
            "decode_failures": self.decode_failures,
            "first_error": self.first_error,
            "record_minus_header_max_s": round(self.record_skew_max_s, 3),
            "dropped": dict(self.dropped),
        }

    def extend(self, other: TopicStats) -> None:
        """Add the stats of the same topic in the next slice."""
        self.count += other.count
        self.decode_failures += other.decode_failures
        self.first_error = self.first_error or other.first_error
        self.stamps.extend(other.stamps)
        self.record_skew_max_s = max(self.record_skew_max_s, other.record_skew_max_s)
        for k, v in other.dropped.items():
            self.drop(k, v)


@dataclass
class Scan:
    """What a pass saw: stats per topic, the small topics whole, stamps of the large ones."""

    stats: dict[str, TopicStats]
    odom: list[tuple[int, NDArray, NDArray]] = field(default_factory=list)
    tf: dict[Edge, EdgeSamples] = field(default_factory=lambda: defaultdict(EdgeSamples))  # dynamic edges
    static: dict[Edge, NDArray] = field(default_factory=dict)
    gnss: list[tuple] = field(default_factory=list)
    info: dict[str, object] = field(default_factory=dict)
    frames: dict[str, str] = field(default_factory=dict)
    stamps: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))
    voxel_frames: list[str] = field(default_factory=list)  # per voxel-map message, "" where it did not decode
    map_meta: dict[str, list[tuple[int, bool, str]]] = field(default_factory=lambda: defaultdict(list))  # (stamp, usable, frame)
    map_shape: dict[str, tuple[tuple[int, int], float]] = field(default_factory=dict)  # role -> (shape, resolution)
    staged: Staged | None = None  # what this slice staged (not merged by ``extend``)
    warnings: list[str] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        """Messages per role in this scan (decode failures included): the ordinal span."""
        return {s.role: s.count for s in self.stats.values()}

    def extend(self, other: Scan) -> None:
        """Append the scan of the next slice."""
        for t, o in other.stats.items():
            self.stats[t].extend(o)
        self.odom.extend(other.odom)
        for e, samples in other.tf.items():
            self.tf[e].extend(samples)
        self.static.update(other.static)
        self.voxel_frames.extend(other.voxel_frames)
        self.gnss.extend(other.gnss)
        for k, v in other.info.items():
            self.info.setdefault(k, v)
        for k, v in other.frames.items():
            self.frames.setdefault(k, v)
        for k, v in other.stamps.items():
            self.stamps[k].extend(v)
        for k, v in other.map_meta.items():
            self.map_meta[k].extend(v)
        for k, v in other.map_shape.items():
            self.map_shape.setdefault(k, v)
        self.warnings += [w for w in other.warnings if w not in self.warnings]


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
            scan = scan_messages(bags.messages(list(roles), start, stop), cfg, roles)
        else:
            with Stager(store, k, cfg) as stager:
                scan = scan_messages(bags.messages(list(roles), start, stop), cfg, roles, stager.add)
            scan.staged = stager.result
        scan.warnings = list(bags.warnings)
    seen = frames.data | set(scan.frames.values()) | set(scan.voxel_frames) | {m[2] for v in scan.map_meta.values() for m in v}
    keep = relevant_edges(list(scan.tf), [*frames.static, *scan.static], seen - {""})
    scan.tf = defaultdict(EdgeSamples, {e: s for e, s in scan.tf.items() if e in keep})
    for s in scan.tf.values():
        s.pack()
    return scan


def any_confident(conf: NDArray) -> bool:
    """True if any confidence value is finite and > 0 (a leading block decides most maps)."""
    head = conf[:4096]
    if np.any((head > 0) & (head < np.inf)):
        return True
    return bool(np.any((conf > 0) & (conf < np.inf)))


class _Scanner:
    """Takes each message of a pass into a Scan (``stage`` sees every large message)."""

    def __init__(self, cfg: GtgenConfig, roles: dict[str, str], stage: Callable | None) -> None:
        self.cfg, self.roles, self.stage = cfg, roles, stage
        self.scan = Scan(stats={t: TopicStats(t, r) for t, r in roles.items()})
        tp = cfg.topics
        self.layer_names = [tp.layers.elevation, tp.layers.risk, tp.layers.confidence]

    def take(self, topic: str, msgtype: str, t_rec: int, msg: object | None, err: str | None) -> None:
        s = self.scan.stats[topic]
        role = self.roles[topic]
        s.count += 1
        if msg is None:
            s.decode_failures += 1
            s.first_error = s.first_error or err or ""
            if role.startswith("map."):
                self.scan.map_meta[role].append((-1, False, ""))
            elif role.startswith("camera.") or role == "voxel_map":
                self.scan.stamps[role].append(-1)
                if role == "voxel_map":
                    self.scan.voxel_frames.append("")
            return
        if role in ("tf_static", "tf"):
            self._tf(role, msg)
            return
        hdr = _header(role, msg)
        t = stamp_ns(hdr)
        s.stamps.append(t)
        s.record_skew_max_s = max(s.record_skew_max_s, abs(t_rec - t) * 1e-9)
        if role == "odometry":
            p, q = msg.pose.pose.position, msg.pose.pose.orientation  # type: ignore[attr-defined]
            self.scan.odom.append((t, np.array([p.x, p.y, p.z]), quat_xyzw(q)))
        elif role == "gnss":
            self._gnss(t, msg)
        elif role.startswith("camera_info."):
            self.scan.info.setdefault(role.split(".")[1], msg)
        elif role.startswith("camera.") or role == "voxel_map":
            self.scan.stamps[role].append(t)
            if role.startswith("camera."):
                self.scan.frames.setdefault(role, frame_id(hdr.frame_id))
            else:
                self.scan.voxel_frames.append(frame_id(hdr.frame_id))
            if self.stage is not None:
                self.stage(role, s.count - 1, t, msg, msgtype, True)
        elif role.startswith("map."):
            self._map(role, s, t, msg, msgtype, frame_id(hdr.frame_id))

    def _tf(self, role: str, msg: object) -> None:
        for tr in msg.transforms:  # type: ignore[attr-defined]
            parent, child = frame_id(tr.header.frame_id), frame_id(tr.child_frame_id)
            if role == "tf_static":
                self.scan.static[(parent, child)] = transform_matrix(tr.transform)
            else:
                tt = tr.transform.translation
                self.scan.tf[(parent, child)].add(stamp_ns(tr.header), (tt.x, tt.y, tt.z), quat_xyzw(tr.transform.rotation))

    def _gnss(self, t: int, msg: object) -> None:
        cov = np.asarray(msg.position_covariance, dtype=np.float64)  # type: ignore[attr-defined]
        var = cov[[0, 4, 8]] if msg.position_covariance_type > 0 and cov.size == 9 else np.full(3, np.nan)  # type: ignore[attr-defined]
        self.scan.gnss.append((t, msg.latitude, msg.longitude, msg.altitude, var, msg.status.status))  # type: ignore[attr-defined]

    def _map(self, role: str, s: TopicStats, t: int, msg: object, msgtype: str, frame: str) -> None:
        names = list(msg.layers)  # type: ignore[attr-defined]
        ok = all(n in names for n in self.layer_names)
        if not ok:
            s.decode_failures += 1
            s.first_error = s.first_error or f"layers {names}; expected {self.layer_names} (topics.layers)"
        else:
            conf = msg.data[names.index(self.cfg.topics.layers.confidence)].data  # type: ignore[attr-defined]
            ok = any_confident(np.asarray(conf))
            if not ok:
                s.first_error = s.first_error or "all-NaN or zero-confidence map"
            elif role not in self.scan.map_shape:
                g = decode_gridmap(msg, self.layer_names)
                self.scan.map_shape[role] = (g.shape, g.resolution_m)
        self.scan.map_meta[role].append((t, ok, frame))
        if self.stage is not None:
            self.stage(role, s.count - 1, t, msg, msgtype, ok)


def scan_messages(messages: Iterable[Message], cfg: GtgenConfig, roles: dict[str, str], stage: Callable | None = None) -> Scan:
    """Return the Scan of ``messages``; ``stage`` sees every large message."""
    scanner = _Scanner(cfg, roles, stage)
    for m in messages:
        scanner.take(*m)
    return scanner.scan
