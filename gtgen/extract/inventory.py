"""What the read of the bags found (``gtgen.extract.scan``): per topic its counts and
drops (``TopicStats``), the stamps and metadata of every usable message by role (``Scan``),
what the plan took (``Used``); the slices' scans ``merged`` in order, with the messages
recorded twice across slices dropped and each range's grid settled.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.tf import Edge, EdgeSamples
from gtgen.errors import DecodeError
from gtgen.extract.roles import is_large
from gtgen.extract.stage import Staged

DUPLICATE = "duplicate"  # dropped: the same topic, stamp and bytes as an earlier message
SIZE_CHANGED = "size_changed"  # dropped: a GridMap of another size or resolution than the topic's first


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


Key = tuple[int, int, int]  # (header stamp [ns], crc32c, length) of a message: equal keys, one message recorded twice
UNUSABLE_MAP = (-1, False, "", None)  # the map_meta entry of a map the plan must not pick


@dataclass
class Used:
    """The messages of one topic a pass used, as they are read: per message its ordinal,
    key and record-minus-header time [s]; packed into arrays by ``pack`` (40 bytes a
    message, so a long drive's record stays small)."""

    rows: list[tuple[int, int, int, int]] = field(default_factory=list)  # ordinal, stamp, crc32c, length
    skews: list[float] = field(default_factory=list)
    packed: tuple[NDArray, NDArray] = field(default_factory=lambda: (np.zeros((0, 4), np.int64), np.zeros(0)))

    def add(self, i: int, key: Key, skew: float) -> None:
        self.rows.append((i, *key))
        self.skews.append(skew)

    def arrays(self) -> tuple[NDArray, NDArray]:
        """Return (rows (n, 4): ordinal, stamp, crc32c, length; skews (n,)), packed."""
        if self.rows:
            self.packed = (np.concatenate([self.packed[0], np.asarray(self.rows, np.int64).reshape(-1, 4)]),
                           np.concatenate([self.packed[1], np.asarray(self.skews, np.float64)]))
            self.rows, self.skews = [], []
        return self.packed

    def extend(self, other: Used, shift: int) -> None:
        """Append ``other`` (the next slice's), its ordinals shifted by ``shift``."""
        rows, skews = other.arrays()
        mine = self.arrays()
        self.packed = (np.concatenate([mine[0], rows + np.array([shift, 0, 0, 0])]), np.concatenate([mine[1], skews]))

    def repeats(self) -> NDArray[np.bool_]:
        """Return where a row's key is that of an earlier row."""
        rows = self.arrays()[0]
        first = np.zeros(len(rows), bool)
        first[np.unique(rows[:, 1:], axis=0, return_index=True)[1]] = True
        return ~first


@dataclass
class Scan:
    """What a pass saw: stats per topic, the small topics whole, stamps of the large ones.

    Message ordinals count every message of a topic (decode failures and duplicates
    included) in record-time order: the large roles' lists are indexed by them, and the
    odometry and GNSS entries end with theirs.
    """

    stats: dict[str, TopicStats]
    odom: list[tuple[int, NDArray, NDArray, int]] = field(default_factory=list)  # (stamp, position, quaternion, ordinal)
    tf: dict[Edge, EdgeSamples] = field(default_factory=lambda: defaultdict(EdgeSamples))  # dynamic edges
    static: dict[Edge, NDArray] = field(default_factory=dict)
    gnss: list[tuple] = field(default_factory=list)  # (stamp, lat, lon, alt, variances, status, ordinal)
    info: dict[str, object] = field(default_factory=dict)  # camera -> its CameraInfo, detached (gtgen.bag.reader.detached)
    frames: dict[str, str] = field(default_factory=dict)
    stamps: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))  # per image / voxel map, -1 where unusable
    voxel_frames: list[str] = field(default_factory=list)  # per voxel-map message, "" where it is unusable
    map_meta: dict[str, list[tuple[int, bool, str, tuple | None]]] = field(default_factory=lambda: defaultdict(list))  # (stamp, usable, frame, (shape, resolution))
    map_shape: dict[str, tuple[tuple[int, int], float]] = field(default_factory=dict)  # role -> (shape, resolution), set by ``merged``
    used: dict[str, Used] = field(default_factory=lambda: defaultdict(Used))  # per topic
    staged: Staged | None = None  # what this slice staged (not merged by ``extend``)
    warnings: list[str] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        """Messages per role in this scan (decode failures included): the ordinal span."""
        return {s.role: s.count for s in self.stats.values()}

    def extend(self, other: Scan) -> None:
        """Append the scan of the next slice (its ordinals shifted past this one's)."""
        shift = {t: s.count for t, s in self.stats.items()}
        odom_shift = next((shift[t] for t, s in self.stats.items() if s.role == "odometry"), 0)
        gnss_shift = next((shift[t] for t, s in self.stats.items() if s.role == "gnss"), 0)
        for t, o in other.stats.items():
            self.stats[t].extend(o)
        self.odom += [(*o[:-1], o[-1] + odom_shift) for o in other.odom]
        for e, samples in other.tf.items():
            self.tf[e].extend(samples)
        self.static.update(other.static)
        self.voxel_frames.extend(other.voxel_frames)
        self.gnss += [(*g[:-1], g[-1] + gnss_shift) for g in other.gnss]
        for k, v in other.info.items():
            self.info.setdefault(k, v)
        for k, v in other.frames.items():
            self.frames.setdefault(k, v)
        for k, v in other.stamps.items():
            self.stamps[k].extend(v)
        for k, v in other.map_meta.items():
            self.map_meta[k].extend(v)
        for t, v in other.used.items():
            self.used[t].extend(v, shift[t])
        self.warnings += [w for w in other.warnings if w not in self.warnings]

    def drop_repeats(self) -> None:
        """Drop the messages recorded twice that different slices read (a slice drops its
        own as it reads them): each key's first message stays."""
        for topic, used in self.used.items():
            again = used.repeats()
            if again.any():
                self._retract(topic, again)

    def _retract(self, topic: str, again: NDArray[np.bool_]) -> None:
        """Take the messages of ``topic`` whose rows of ``used`` are ``again`` out of the
        scan, as duplicates (from its stats too: stamps, record skew)."""
        s = self.stats[topic]
        rows, skews = self.used[topic].arrays()
        ordinals = set(rows[again, 0].tolist())
        s.drop(DUPLICATE, len(ordinals))
        gone = Counter(rows[again, 1].tolist())
        s.stamps = [t for t in s.stamps if not _take(gone, t)]
        s.record_skew_max_s = float(skews[~again].max(initial=0.0))
        self.used[topic].packed = (rows[~again], skews[~again])
        if s.role == "odometry":
            self.odom = [o for o in self.odom if o[-1] not in ordinals]
        elif s.role == "gnss":
            self.gnss = [g for g in self.gnss if g[-1] not in ordinals]
        elif s.role.startswith("map."):
            for o in ordinals:
                self.map_meta[s.role][o] = UNUSABLE_MAP
        elif s.role.startswith(("camera.", "lidar.")) or s.role == "voxel_map":
            for o in ordinals:
                self.stamps[s.role][o] = -1
                if s.role == "voxel_map":
                    self.voxel_frames[o] = ""
        # tf, tf_static and camera info: a second copy adds nothing (TF drops repeated
        # stamps of an edge, the first CameraInfo is used), so counting it is all

    def settle_map_sizes(self) -> None:
        """Fix each range's grid (shape, resolution) to that of its first usable map and
        drop the usable maps of another one (``size_changed``): the store holds one grid."""
        topic_of = {s.role: s for s in self.stats.values()}
        for role, meta in self.map_meta.items():
            ref = next((m[3] for m in meta if m[1]), None)
            if ref is None:
                continue
            self.map_shape[role] = ref
            other = [i for i, m in enumerate(meta) if m[1] and not _same_grid(m[3], ref)]
            for i in other:
                meta[i] = UNUSABLE_MAP
            topic_of[role].drop(SIZE_CHANGED, len(other))

    def require_usable(self) -> None:
        """Raise DecodeError for the first role the drive needs that is left with no
        usable message (GNSS and TF are judged where they are used)."""
        for s in self.stats.values():
            if s.role.startswith("map."):
                usable = any(m[1] for m in self.map_meta.get(s.role, []))
            elif is_large(s.role):
                usable = any(t >= 0 for t in self.stamps.get(s.role, []))
            elif s.role.startswith("camera_info."):
                usable = s.role.split(".")[1] in self.info
            elif s.role == "odometry":
                usable = bool(self.odom)
            else:
                continue
            if not usable:
                raise DecodeError(f"{s.topic}: none of its {s.count} messages is usable ({_why_none(s)})")


def _take(counts: Counter, t: int) -> bool:
    """Count one of ``t`` off ``counts``; return whether there was one."""
    if counts[t] > 0:
        counts[t] -= 1
        return True
    return False


def _same_grid(a: tuple[tuple[int, int], float], b: tuple[tuple[int, int], float]) -> bool:
    return a[0] == b[0] and abs(a[1] - b[1]) <= 1e-9 * b[1]


def _why_none(s: TopicStats) -> str:
    why = [f"{s.decode_failures} decode failures"] if s.decode_failures else []
    why += [f"{n} dropped: {k}" for k, n in s.dropped.items()]
    if s.first_error:
        why.append(f"first error: {s.first_error}")
    return "; ".join(why) or "no message"


def merged(parts: list[Scan]) -> Scan:
    """Return the scan of the whole drive from its slices' scans, in order (the first one
    grows), with the duplicates across slices dropped and each range's grid settled."""
    scan = parts[0]
    for part in parts[1:]:
        scan.extend(part)
    scan.drop_repeats()
    scan.settle_map_sizes()
    return scan
