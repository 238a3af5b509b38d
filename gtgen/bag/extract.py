"""``gtgen extract``: bags -> a time-indexed per-drive store.

One streaming read, split into record-time slices that run on ``workers`` processes.
Each slice reads the small topics (odometry, TF, GNSS, camera info) whole, notes the
header stamps of the large ones (maps, voxel map, images) and stages what the plan will
likely keep (see "staging" below). The merged slices fix the sample times and the maps
to keep; staged images, maps and voxel maps are moved into the store as chunk files,
and whatever no slice staged is read in a targeted second pass. One chunk per image, map
and voxel map, so slices never write the same chunk. A slice spans at most ``SLICE_S``
of the bag, so memory stays flat in drive length; the store does not depend on the split.
"""

from __future__ import annotations

import hashlib
import io
import logging
import shutil
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen import reasons
from gtgen.bag import store as st
from gtgen.bag.gridmap import decode_gridmap
from gtgen.bag.poses import PoseTrack
from gtgen.bag.reader import BagSet, TopicInfo, stamp_ns
from gtgen.bag.store import MAP_LAYERS
from gtgen.config import CAMERAS, RANGES, GtgenConfig
from gtgen.errors import BagError, DecodeError, PoseError, TopicError
from gtgen.format import Runs, check_encoded_chunks, chunk_file, compressors, encode_chunk, make_parent, place_chunk
from gtgen.geometry import invert, make_transform, quat_to_matrix, yaw_transform
from gtgen.progress import ProcessJobs

log = logging.getLogger(__name__)

GRIDMAP = "grid_map_msgs/msg/GridMap"
TYPES = {
    "odometry": ("nav_msgs/msg/Odometry",),
    "gnss": ("sensor_msgs/msg/NavSatFix",),
    "voxel_map": ("sensor_msgs/msg/PointCloud2",),
    "image": ("sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image"),
    "info": ("sensor_msgs/msg/CameraInfo",),
    "tf": ("tf2_msgs/msg/TFMessage",),
    "map": (GRIDMAP,),
}


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

    def summary(self) -> dict:
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
        }


@dataclass
class ExtractResult:
    """What an extract did: the store, per-topic stats, sample counts by reason."""

    store: Path
    topics: list[dict]
    n_candidates: int
    n_samples: int
    rejected: dict[str, int]
    maps_kept: dict[str, int]
    skew_s: dict[str, float]
    warnings: list[str]
    reread: int = 0  # kept messages no slice had staged, read in a second pass
    bag_sha256: list[str] = field(default_factory=list)  # of each bag, in the order given


# -- role resolution ------------------------------------------------------------------
def _require(topics: dict[str, TopicInfo], role: str, topic: str, kind: str) -> None:
    info = topics.get(topic)
    types = TYPES[kind]
    if info is None:
        cands = sorted(t for t, i in topics.items() if i.msgtype in types)
        raise TopicError(f"role '{role}': topic '{topic}' not in the bags; {types[0].split('/')[-1]} topics found: {cands}")
    if info.msgtype not in types:
        raise TopicError(f"role '{role}': topic '{topic}' has type {info.msgtype}; expected {' or '.join(types)}")


def _roles(cfg: GtgenConfig, topics: dict[str, TopicInfo]) -> dict[str, str]:
    """Return topic -> role for every role present, raising for missing required roles."""
    tp = cfg.topics
    roles: dict[str, str] = {}
    for r in RANGES:
        _require(topics, f"map.{r}", tp.map_topic(r), "map")
        roles[tp.map_topic(r)] = f"map.{r}"
    _require(topics, "voxel_map", tp.voxel_map, "voxel_map")
    roles[tp.voxel_map] = "voxel_map"
    for c in CAMERAS:
        _require(topics, f"camera.{c}", tp.cameras[c].image, "image")
        _require(topics, f"camera_info.{c}", tp.cameras[c].info, "info")
        roles[tp.cameras[c].image] = f"camera.{c}"
        roles[tp.cameras[c].info] = f"camera_info.{c}"
    if tp.odometry in topics:
        _require(topics, "odometry", tp.odometry, "odometry")
        roles[tp.odometry] = "odometry"
    elif tp.tf in topics:
        roles[tp.tf] = "tf"
    else:
        _require(topics, "odometry", tp.odometry, "odometry")
    if tp.tf_static in topics:
        roles[tp.tf_static] = "tf_static"
    else:
        raise TopicError(f"role 'tf_static': topic '{tp.tf_static}' not in the bags; camera extrinsics come from it")
    if tp.gnss in topics:
        _require(topics, "gnss", tp.gnss, "gnss")
        roles[tp.gnss] = "gnss"
    return roles


# -- the read (one pass over the bags, in slices) --------------------------------------
@dataclass
class _Scan:
    stats: dict[str, TopicStats]
    odom: list[tuple[int, NDArray, NDArray]] = field(default_factory=list)
    tf_dyn: list[tuple[int, NDArray, NDArray]] = field(default_factory=list)
    static: dict[tuple[str, str], NDArray] = field(default_factory=dict)
    gnss: list[tuple] = field(default_factory=list)
    info: dict[str, object] = field(default_factory=dict)
    frames: dict[str, str] = field(default_factory=dict)
    stamps: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))
    map_meta: dict[str, list[tuple[int, bool]]] = field(default_factory=lambda: defaultdict(list))
    map_shape: dict[str, tuple[tuple[int, int], float]] = field(default_factory=dict)  # role -> (shape, resolution)
    staged: _Staged | None = None  # what this slice staged (not merged by ``extend``)

    def counts(self) -> dict[str, int]:
        """Messages per role in this scan (decode failures included): the ordinal span."""
        return {s.role: s.count for s in self.stats.values()}

    def extend(self, other: _Scan) -> None:
        """Append the scan of the next slice."""
        for t, o in other.stats.items():
            s = self.stats[t]
            s.count += o.count
            s.decode_failures += o.decode_failures
            s.first_error = s.first_error or o.first_error
            s.stamps.extend(o.stamps)
            s.record_skew_max_s = max(s.record_skew_max_s, o.record_skew_max_s)
        self.odom.extend(other.odom)
        self.tf_dyn.extend(other.tf_dyn)
        self.static.update(other.static)
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


def _tf_matrix(tr: object) -> NDArray:
    t, q = tr.translation, tr.rotation  # type: ignore[attr-defined]
    return make_transform(quat_to_matrix(np.array([q.x, q.y, q.z, q.w])), np.array([t.x, t.y, t.z]))


def _scan_slice(paths: list[Path], cfg: GtgenConfig, roles: dict[str, str], start: int | None, stop: int | None,
                store: str | None = None, k: int = 0) -> _Scan:
    """The pass over the messages recorded in [start, stop) (a process-pool job). With a
    ``store``, what the plan will likely keep is staged there as slice ``k``."""
    with BagSet(paths) as bags:
        if store is None:
            return _scan(bags.messages(list(roles), start, stop), cfg, roles)
        with _Stager(store, k, cfg) as stager:
            scan = _scan(bags.messages(list(roles), start, stop), cfg, roles, stager.add)
        scan.staged = stager.result
        return scan


def _scan(messages, cfg: GtgenConfig, roles: dict[str, str], stage=None) -> _Scan:
    tp = cfg.topics
    scan = _Scan(stats={t: TopicStats(t, r) for t, r in roles.items()})
    layer_names = [tp.layers.elevation, tp.layers.risk, tp.layers.confidence]
    for topic, msgtype, t_rec, msg, err in messages:
        s = scan.stats[topic]
        role = roles[topic]
        s.count += 1
        if msg is None:
            s.decode_failures += 1
            s.first_error = s.first_error or err or ""
            if role.startswith("map."):
                scan.map_meta[role].append((-1, False))
            elif role.startswith("camera.") or role == "voxel_map":
                scan.stamps[role].append(-1)
            continue
        if role == "tf_static":
            for tr in msg.transforms:
                scan.static[(tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))] = _tf_matrix(tr.transform)
            continue
        if role == "tf":
            for tr in msg.transforms:
                if tr.header.frame_id.lstrip("/") == tp.odom_frame and tr.child_frame_id.lstrip("/") == tp.base_frame:
                    T = _tf_matrix(tr.transform)
                    scan.tf_dyn.append((stamp_ns(tr.header), T[:3, 3], msg_quat(tr.transform.rotation)))
            continue
        hdr = msg.info.header if role.startswith("map.") and not hasattr(msg, "header") else msg.header
        t = stamp_ns(hdr)
        s.stamps.append(t)
        s.record_skew_max_s = max(s.record_skew_max_s, abs(t_rec - t) * 1e-9)
        if role == "odometry":
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            scan.odom.append((t, np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w])))
        elif role == "gnss":
            cov = np.asarray(msg.position_covariance, dtype=np.float64)
            var = cov[[0, 4, 8]] if msg.position_covariance_type > 0 and cov.size == 9 else np.full(3, np.nan)
            scan.gnss.append((t, msg.latitude, msg.longitude, msg.altitude, var, msg.status.status))
        elif role.startswith("camera_info."):
            scan.info.setdefault(role.split(".")[1], msg)
        elif role.startswith("camera."):
            scan.stamps[role].append(t)
            scan.frames.setdefault(role, hdr.frame_id.lstrip("/"))
            if stage is not None:
                stage(role, s.count - 1, t, msg, msgtype, True)
        elif role == "voxel_map":
            scan.stamps[role].append(t)
            if stage is not None:
                stage(role, s.count - 1, t, msg, msgtype, True)
        elif role.startswith("map."):
            names = list(msg.layers)
            ok = all(n in names for n in layer_names)
            if not ok:
                s.decode_failures += 1
                s.first_error = s.first_error or f"layers {names}; expected {layer_names} (topics.layers)"
            else:
                ok = _any_confident(np.asarray(msg.data[names.index(tp.layers.confidence)].data))
                if not ok:
                    s.first_error = s.first_error or "all-NaN or zero-confidence map"
                elif role not in scan.map_shape:
                    g = decode_gridmap(msg, layer_names)
                    scan.map_shape[role] = (g.shape, g.resolution_m)
            scan.map_meta[role].append((t, ok))
            if stage is not None:
                stage(role, s.count - 1, t, msg, msgtype, ok)
    return scan


def _any_confident(conf: NDArray) -> bool:
    """True if any confidence value is finite and > 0 (a leading block decides most maps)."""
    head = conf[:4096]
    if np.any((head > 0) & (head < np.inf)):
        return True
    return bool(np.any((conf > 0) & (conf < np.inf)))


def msg_quat(q: object) -> NDArray:
    return np.array([q.x, q.y, q.z, q.w])  # type: ignore[attr-defined]


# -- staging: the single pass keeps what the plan will likely want ----------------------
# The plan (sample times, kept maps) needs every stamp of the drive, so it exists only
# once all slices are read. Rather than read the bags a second time, each slice stages
# what the plan will likely keep while it reads: every image, every voxel cloud, the
# earliest map of each thinning period and, for each front-camera frame (a sample time
# is always one), the latest map stamped at or before it. Each is written as the encoded
# chunk file it will be in the store (``format.encode_chunk``), and once the plan exists
# the kept ones are moved into place by rename; anything the plan wants but no slice
# staged (stamps far out of record order) is read in a second, targeted pass. The store
# does not depend on what was staged.
STAGE = "stage"  # folder of the partial store holding staged chunks; removed before the store completes


def _period_ns(cfg: GtgenConfig) -> int:
    return int(1e9 / cfg.extract.map_rate_hz)


@dataclass
class _Staged:
    """What one slice staged: the slice ordinals staged per role (chunk files named by
    ordinal), map poses as stamped (frames resolved later), voxel point counts (voxel
    maps in base_link are kept raw in .npy files, for the pose track to place)."""

    k: int
    dir: str
    ordinals: dict[str, set[int]] = field(default_factory=lambda: defaultdict(set))
    map_pose: dict[tuple[str, int], tuple[NDArray, float, str]] = field(default_factory=dict)
    map_shape: dict[str, tuple[int, int]] = field(default_factory=dict)
    voxels: dict[int, tuple[int, int]] = field(default_factory=dict)  # ordinal -> (points, stamp); -1 points: raw .npy

    def chunk(self, role: str, i: int, layer: str = "") -> Path:
        """Return the staged chunk file of message ``i`` of ``role`` (map layer ``layer``)."""
        return Path(self.dir) / (f"{role}.{layer}" if layer else role) / str(i)

    def raw_voxels(self, i: int) -> Path:
        """Return the .npy file of voxel map ``i`` staged in its own frame (base_link)."""
        return Path(self.dir) / "voxel_map.raw" / f"{i}.npy"


class _Stager:
    """Stages images, voxel clouds and likely maps of one slice as encoded chunk files in
    ``<store>/stage/<k>`` (written on threads)."""

    def __init__(self, store: str, k: int, cfg: GtgenConfig) -> None:
        self.cfg = cfg
        self.result = _Staged(k, str(Path(store) / STAGE / str(k)))
        tp = cfg.topics
        self.layer_names = [tp.layers.elevation, tp.layers.risk, tp.layers.confidence]
        self.period = _period_ns(cfg)
        self.bin_first: dict[str, dict[int, int]] = defaultdict(dict)  # role -> {period: earliest stamp staged}
        self.held: dict[str, list[tuple[int, int, object]]] = defaultdict(list)  # role -> [(stamp, ordinal, msg)]
        self.pending: dict[str, list[int]] = defaultdict(list)  # role -> front stamps awaiting their map
        self.made: set[Path] = set()

    def __enter__(self) -> _Stager:
        self.writes = _Writes().__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            if exc[0] is None:
                for role in list(self.held):
                    for h in self.held[role]:  # the next slice's first frames may want them
                        self._stage_map(role, h)
        finally:
            self.writes.__exit__(*exc)

    def _write(self, file: Path, value: NDArray) -> None:
        make_parent(file, self.made)
        self.writes.submit(lambda: file.write_bytes(encode_chunk(value)))

    def add(self, role: str, i: int, t: int, msg: object, msgtype: str, ok: bool) -> None:
        """Take message ``i`` (slice ordinal) of a large role, stamped ``t``; ``ok`` is
        False for a map the plan cannot use."""
        if role.startswith("camera."):
            self._stage_image(role, i, msg, msgtype)
            if role == "camera.front":
                for r in RANGES:
                    self.pending[f"map.{r}"].append(t)
                    self._resolve(f"map.{r}")
        elif role == "voxel_map":
            self._stage_voxel(i, t, msg)
        elif ok:
            b = t // self.period
            if t < self.bin_first[role].get(b, t + 1):
                self.bin_first[role][b] = t
                self._stage_map(role, (t, i, msg))
            self.held[role].append((t, i, msg))
            self._resolve(role)

    def _stage_image(self, role: str, i: int, msg: object, msgtype: str) -> None:
        W, H = self.cfg.extract.image_width, self.cfg.extract.image_height
        try:
            img = resize_image(decode_image(msg, msgtype), W, H)
        except DecodeError:
            return  # staged nothing: if the plan wants it, the targeted pass reports the error
        self._write(self.result.chunk(role, i), img)
        self.result.ordinals[role].add(i)

    def _stage_voxel(self, i: int, t: int, msg: object) -> None:
        tp = self.cfg.topics
        frame = msg.header.frame_id.lstrip("/")  # type: ignore[attr-defined]
        if frame not in ("", tp.odom_frame, tp.base_frame):
            return
        try:
            pts = decode_pointcloud(msg)
        except DecodeError:
            return
        if frame == tp.base_frame:  # to odom once the whole pose track is known
            f = self.result.raw_voxels(i)
            make_parent(f, self.made)
            np.save(f, pts)
            self.result.voxels[i] = (-1, t)
            return
        pts = _nearest_points(pts, self.cfg.shards.max_voxel_points)
        self._write(self.result.chunk("voxel_map", i), _padded(pts, self.cfg.shards.max_voxel_points))
        self.result.voxels[i] = (len(pts), t)

    def _resolve(self, role: str) -> None:
        """Stage, for each front frame older than the newest map, the latest map stamped at
        or before it; keep held only the maps a later frame may still want."""
        held = self.held[role]
        if not held:
            return
        newest = max(h[0] for h in held)
        still = []
        for tf in self.pending[role]:
            if tf < newest:
                before = [h for h in held if h[0] <= tf]
                if before:
                    self._stage_map(role, max(before, key=lambda h: h[0]))
            else:
                still.append(tf)
        self.pending[role] = still
        m = min(still) if still else newest
        floor = max((h[0] for h in held if h[0] <= m), default=min(h[0] for h in held))
        self.held[role] = [h for h in held if h[0] >= floor]

    def _stage_map(self, role: str, h: tuple[int, int, object]) -> None:
        _, i, msg = h
        if i in self.result.ordinals[role]:
            return
        try:
            g = decode_gridmap(msg, self.layer_names)
        except DecodeError:
            return
        if g.shape != self.result.map_shape.setdefault(role, g.shape):
            return  # a size change: the targeted pass reports it if the plan wants this map
        for name, layer in zip(MAP_LAYERS, self.layer_names):
            self._write(self.result.chunk(role, i, name), g.layers[layer])
        self.result.ordinals[role].add(i)
        self.result.map_pose[(role, i)] = (g.center_m, g.yaw_rad, g.frame_id)


# -- selection ---------------------------------------------------------------------------
def _nearest(stamps: NDArray, t: NDArray) -> tuple[NDArray, NDArray]:
    """Return (index, |skew| ns) of the stamp nearest each t; stamps sorted; -1 stamps ignored."""
    if len(stamps) == 0:
        return np.full(len(t), -1), np.full(len(t), np.iinfo(np.int64).max)
    i = np.clip(np.searchsorted(stamps, t), 1, len(stamps) - 1) if len(stamps) > 1 else np.zeros(len(t), np.int64)
    lo = np.maximum(i - 1, 0)
    d_lo = np.abs(t - stamps[lo])
    d_hi = np.abs(stamps[i] - t)
    best = np.where(d_lo <= d_hi, lo, i)
    return best, np.minimum(d_lo, d_hi)


def _sorted_valid(stamps: list[int]) -> tuple[NDArray, NDArray]:
    """Return (sorted valid stamps, their ordinal in the message stream)."""
    a = np.asarray(stamps, dtype=np.int64)
    ords = np.nonzero(a >= 0)[0]
    order = np.argsort(a[ords], kind="stable")
    return a[ords][order], ords[order]


@dataclass
class _Plan:
    t: NDArray  # (S,)
    cand_t: NDArray
    cand_reason: NDArray
    image_ord: NDArray  # (S, 4) ordinal of the image message per camera
    image_t: NDArray
    voxel_t: NDArray  # (S,)
    voxel_index: NDArray  # (S,) index into the kept voxel maps
    voxel_ord: NDArray  # (V,) ordinals of the kept voxel maps, sorted by stamp
    voxel_map_t: NDArray  # (V,)
    map_ord: dict[str, NDArray]  # kept map ordinals per range, sorted by stamp
    map_t: dict[str, NDArray]
    sample_map: dict[str, NDArray]  # (S,) index into kept maps


def _select(cfg: GtgenConfig, track_: PoseTrack, scan: _Scan) -> _Plan:
    ex = cfg.extract
    dist = track_.distance()
    marks = np.arange(0.0, dist[-1] + 1e-9, ex.stride_m) if len(dist) else np.zeros(0)
    # candidate: the time travel reaches each mark (interpolated in the pose stream)
    cand = np.interp(marks, dist, track_.t_ns.astype(np.float64)).astype(np.int64) if len(marks) else np.zeros(0, np.int64)
    cand = np.unique(cand)
    reason = np.zeros(len(cand), np.uint8)
    # snap to the reference (front) camera so that images are never interpolated
    front_t, front_ord = _sorted_valid(scan.stamps["camera.front"])
    fi, _ = _nearest(front_t, cand)
    t = np.where(fi >= 0, front_t[np.maximum(fi, 0)], cand) if len(front_t) else cand
    t, first = np.unique(t, return_index=True)
    cand, reason = cand[first], reason[first]
    ok_pose = track_.covered(t)
    reason[~ok_pose] = reasons.NO_POSE
    img_ord = np.full((len(t), 4), -1, np.int64)
    img_t = np.zeros((len(t), 4), np.int64)
    for c_i, c in enumerate(CAMERAS):
        s, o = _sorted_valid(scan.stamps[f"camera.{c}"])
        i, d = _nearest(s, t)
        ok = (i >= 0) & (d <= int(ex.image_skew_s * 1e9))
        img_ord[:, c_i] = np.where(ok, o[np.maximum(i, 0)] if len(o) else -1, -1)
        img_t[:, c_i] = np.where(ok, s[np.maximum(i, 0)] if len(s) else 0, 0)
        reason[(reason == 0) & ~ok] = reasons.NO_IMAGE
    vs, vo = _sorted_valid(scan.stamps["voxel_map"])
    vi, vd = _nearest(vs, t)
    vok = (vi >= 0) & (vd <= int(ex.voxel_skew_s * 1e9))
    reason[(reason == 0) & ~vok] = reasons.NO_VOXEL
    map_near: dict[str, tuple[NDArray, NDArray, NDArray]] = {}
    for r, code in (("micro", reasons.NO_MAP_MICRO), ("short", reasons.NO_MAP_SHORT)):
        meta = scan.map_meta[f"map.{r}"]
        stamps = [m[0] if m[1] else -1 for m in meta]
        ms, mo = _sorted_valid(stamps)
        # the X-Racer map at t is the latest one stamped <= t (what the robot had then)
        mi = np.searchsorted(ms, t, side="right") - 1
        mok = (mi >= 0) & (t - ms[np.maximum(mi, 0)] <= int(ex.map_skew_s * 1e9)) if len(ms) else np.zeros(len(t), bool)
        mi = np.where(mok, mi, 0)
        reason[(reason == 0) & ~mok] = code
        map_near[r] = (ms, mo, mi)
    keep = reason == 0
    t_k = t[keep]
    vk = np.unique(vi[keep])  # kept voxel maps, in stamp order
    map_ord: dict[str, NDArray] = {}
    map_t: dict[str, NDArray] = {}
    sample_map: dict[str, NDArray] = {}
    period = _period_ns(cfg)
    for r, (ms, mo, mi) in map_near.items():
        # thinning: the earliest valid map of each period (a rule each slice can apply alone)
        bins = ms // period
        first_in_bin = np.nonzero(np.r_[True, bins[1:] != bins[:-1]])[0] if len(ms) else np.zeros(0, np.int64)
        ks = np.union1d(first_in_bin, mi[keep]).astype(np.int64)
        map_ord[r] = mo[ks] if len(ks) else np.zeros(0, np.int64)
        map_t[r] = ms[ks] if len(ks) else np.zeros(0, np.int64)
        sample_map[r] = np.searchsorted(ks, mi[keep]) if len(ks) else np.zeros(0, np.int64)
    return _Plan(
        t=t_k, cand_t=t, cand_reason=reason,
        image_ord=img_ord[keep], image_t=img_t[keep],
        voxel_t=vs[vi[keep]] if len(vs) else np.zeros(0, np.int64), voxel_index=np.searchsorted(vk, vi[keep]),
        voxel_ord=vo[vk] if len(vo) else np.zeros(0, np.int64), voxel_map_t=vs[vk] if len(vs) else np.zeros(0, np.int64),
        map_ord=map_ord, map_t=map_t, sample_map=sample_map,
    )


# -- decoding of kept messages -----------------------------------------------------------
def decode_image(msg: object, msgtype: str) -> NDArray[np.uint8]:
    """Return an RGB uint8 image (H, W, 3) from a CompressedImage or Image message."""
    from PIL import Image

    if msgtype.endswith("CompressedImage"):
        try:
            img = Image.open(io.BytesIO(bytes(msg.data))).convert("RGB")  # type: ignore[attr-defined]
        except Exception as err:  # noqa: BLE001 - PIL raises several types
            raise DecodeError(f"CompressedImage ({msg.format!r}) does not decode: {err}") from err  # type: ignore[attr-defined]
        return np.asarray(img)
    enc = str(msg.encoding).lower()  # type: ignore[attr-defined]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)  # type: ignore[attr-defined]
    raw = np.asarray(msg.data, dtype=np.uint8)  # type: ignore[attr-defined]
    chans = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
    if enc not in chans:
        raise DecodeError(f"Image encoding {enc!r} unsupported; expected one of {sorted(chans)}")
    arr = raw[: h * step].reshape(h, step)[:, : w * chans[enc]].reshape(h, w, chans[enc])
    if enc.startswith("bgr"):
        arr = arr[..., [2, 1, 0]]
    if chans[enc] == 1:
        arr = np.repeat(arr, 3, axis=-1)
    return np.ascontiguousarray(arr[..., :3])


def resize_image(img: NDArray[np.uint8], width: int, height: int) -> NDArray[np.uint8]:
    """Return ``img`` resized (bilinear) to width x height."""
    if img.shape[1] == width and img.shape[0] == height:
        return img
    from PIL import Image

    return np.asarray(Image.fromarray(img).resize((width, height), Image.BILINEAR))


def rescale_K(K: NDArray, src_wh: tuple[int, int], dst_wh: tuple[int, int]) -> NDArray:
    """Return intrinsics K for an image resized from src to dst size (pixel centres at integers)."""
    sx, sy = dst_wh[0] / src_wh[0], dst_wh[1] / src_wh[1]
    K2 = np.array(K, dtype=np.float64, copy=True)
    K2[0, 0] *= sx
    K2[1, 1] *= sy
    K2[0, 1] *= sx
    K2[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K2[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K2


def decode_pointcloud(msg: object) -> NDArray[np.float32]:
    """Return the finite xyz points (N, 3) of a PointCloud2."""
    fields = {f.name: f for f in msg.fields}  # type: ignore[attr-defined]
    if not all(k in fields for k in "xyz"):
        raise DecodeError(f"PointCloud2 has fields {sorted(fields)}; expected x, y, z")
    kinds = {7: "f4", 8: "f8"}
    if any(fields[k].datatype not in kinds for k in "xyz"):
        raise DecodeError("PointCloud2 x/y/z must be FLOAT32 or FLOAT64")
    endian = ">" if msg.is_bigendian else "<"  # type: ignore[attr-defined]
    n = int(msg.width) * int(msg.height)  # type: ignore[attr-defined]
    dt = np.dtype({"names": list("xyz"), "formats": [endian + kinds[fields[k].datatype] for k in "xyz"],
                   "offsets": [fields[k].offset for k in "xyz"], "itemsize": int(msg.point_step)})  # type: ignore[attr-defined]
    raw = np.asarray(msg.data, dtype=np.uint8)  # type: ignore[attr-defined]
    rec = raw[: n * dt.itemsize].view(dt)
    pts = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float32)
    return pts[np.all(np.isfinite(pts), axis=1)]


def _chain(static: dict[tuple[str, str], NDArray], parent: str, child: str) -> NDArray | None:
    """Return T_parent_child through the static TF tree, or None."""
    edges: dict[str, list[tuple[str, NDArray]]] = defaultdict(list)
    for (p, c), T in static.items():
        edges[p].append((c, T))
        edges[c].append((p, invert(T)))
    todo = [(parent, np.eye(4))]
    seen = {parent}
    while todo:
        node, T = todo.pop()
        if node == child:
            return T
        for nxt, Tn in edges[node]:
            if nxt not in seen:
                seen.add(nxt)
                todo.append((nxt, T @ Tn))
    return None


# -- the stage ---------------------------------------------------------------------------
def hash_bag(path: Path) -> str:
    """Return the sha256 of a bag file, or of a rosbag2 folder's files in name order."""
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    buf = bytearray(1 << 20)  # one reused buffer: fresh blocks cost page faults
    view = memoryview(buf)
    for f in files:
        with f.open("rb", buffering=0) as fh:
            while n := fh.readinto(buf):
                h.update(view[:n])
    return h.hexdigest()


SLICE_S = 20.0  # longest record-time slice of a pass [s]: bounds the memory of one job


def _slices(bags: BagSet, workers: int, slices: int | None) -> list[tuple[int | None, int | None]]:
    """Return record-time slices [start, stop) covering the bags; the ends are open."""
    lo, hi = bags.time_range()
    n = slices or max(2 * workers if workers > 1 else 1, int(np.ceil((hi - lo) * 1e-9 / SLICE_S)))
    edges = [lo + (hi - lo) * i // n for i in range(n + 1)]
    bounds: list[tuple[int | None, int | None]] = [(edges[i], edges[i + 1]) for i in range(n) if edges[i] < edges[i + 1]]
    if not bounds:
        return [(None, None)]
    bounds[0] = (None, bounds[0][1])
    bounds[-1] = (bounds[-1][0], None)
    return bounds


def _import_readers() -> None:
    """Import what a slice needs (a pool worker's warm-up)."""
    import mcap.reader  # noqa: F401
    import numcodecs  # noqa: F401
    import PIL.Image  # noqa: F401
    import rosbags.highlevel  # noqa: F401
    import zarr  # noqa: F401
    import zstandard  # noqa: F401


def run_extract(paths: list[Path], out: Path, cfg: GtgenConfig, workers: int = 2, slices: int | None = None,
                staging: bool = True, bag_sha256: list[str] | None = None) -> ExtractResult:
    """Read the bags of one drive into the drive store ``out`` (written atomically).

    The bags are read as record-time slices on ``workers`` processes (``slices`` fixes
    their number, for tests), once: each slice stages what the plan will likely keep.
    ``staging=False`` stages nothing and reads the kept messages in a second pass (the
    two-pass reference). The store depends on none of the three. ``bag_sha256``, the
    bags' hashes if the caller has them already, spares hashing them again.
    """
    from concurrent.futures import ThreadPoolExecutor

    import zarr

    if bag_sha256 is not None and len(bag_sha256) != len(paths):
        raise ValueError(f"{len(bag_sha256)} bag hashes given for {len(paths)} bags")
    tmp = st.partial_path(out)
    shutil.rmtree(tmp, ignore_errors=True)
    jobs: ProcessJobs | None = None
    hasher = ThreadPoolExecutor(max_workers=1)  # hashing releases the GIL: overlaps the read
    try:
        jobs = ProcessJobs(workers, warm=_import_readers)  # workers start while the bags open
        with BagSet(paths) as bags:
            topics = bags.topics()
            roles = _roles(cfg, topics)
            bounds = _slices(bags, workers, slices)
        hashes = [hasher.submit(hash_bag, p) for p in paths] if bag_sha256 is None else []
        root = zarr.open_group(str(tmp), mode="w")
        stage = str(tmp) if staging else None
        parts = list(jobs.map(_scan_slice, [(paths, cfg, roles, a, b, stage, k) for k, (a, b) in enumerate(bounds)],
                              "extract: reading"))
        counts = [p.counts() for p in parts]  # before merging: the merge grows parts[0]
        staged = [p.staged for p in parts] if staging else []
        scan = parts[0]
        for part in parts[1:]:
            scan.extend(part)
        for r in RANGES:
            meta = scan.map_meta.get(f"map.{r}", [])
            if not any(ok for _, ok in meta):
                st_ = scan.stats[cfg.topics.map_topic(r)]
                raise DecodeError(f"{st_.topic}: none of its {st_.count} GridMaps is usable: {st_.first_error or 'no message'}")
        track_, warnings = _poses(cfg, scan)
        plan = _select(cfg, track_, scan)
        if len(plan.t) == 0:
            raise BagError(f"no sample passed selection out of {len(plan.cand_t)} candidates: {_reason_counts(plan.cand_reason)}")
        extr = _extrinsics(cfg, scan)
        _write_small(root, cfg, scan, track_, plan, extr)
        reread = _write_large(root, tmp, paths, cfg, roles, scan, track_, plan, bounds, counts, staged, jobs)
        result = ExtractResult(
            store=out,
            topics=[s.summary() for s in scan.stats.values()],
            n_candidates=len(plan.cand_t),
            n_samples=len(plan.t),
            rejected=_reason_counts(plan.cand_reason),
            maps_kept={r: len(plan.map_t[r]) for r in RANGES},
            skew_s=_skews(plan),
            warnings=warnings,
            reread=reread,
            bag_sha256=bag_sha256 or [h.result() for h in hashes],
        )
        from gtgen.config import save_config

        root.attrs.update(st.jsonable({
            "store": st.DRIVE_STORE, "version": st.DRIVE_VERSION, "complete": True,
            "bags": [{"path": str(p.resolve()), "sha256": h} for p, h in zip(paths, result.bag_sha256)],
            "config": cfg.model_dump(mode="json"),
            "report": {"topics": result.topics, "n_candidates": result.n_candidates, "n_samples": result.n_samples,
                       "rejected": result.rejected, "maps_kept": result.maps_kept, "skew_s": result.skew_s,
                       "reread": reread, "warnings": warnings},
            "reasons": reasons.REASONS,
            "image_size": [cfg.extract.image_width, cfg.extract.image_height],
            "cameras": list(CAMERAS),
        }))
        save_config(cfg, tmp / "gtgen-config.yaml")
        st.finalize(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        hasher.shutdown(wait=True)
        if jobs is not None:
            jobs.close()
    return result


def _reason_counts(codes: NDArray) -> dict[str, int]:
    u, c = np.unique(codes, return_counts=True)
    return {reasons.name(k): int(v) for k, v in zip(u, c) if k != reasons.OK}


def _skews(plan: _Plan) -> dict[str, float]:
    if len(plan.t) == 0:
        return {}
    img = np.abs(plan.image_t - plan.t[:, None]) * 1e-9
    vox = np.abs(plan.voxel_t - plan.t) * 1e-9
    return {"image_max": round(float(img.max()), 4), "image_mean": round(float(img.mean()), 4),
            "voxel_max": round(float(vox.max()), 4), "voxel_mean": round(float(vox.mean()), 4)}


def _poses(cfg: GtgenConfig, scan: _Scan) -> tuple[PoseTrack, list[str]]:
    src = scan.odom if scan.odom else scan.tf_dyn
    warnings: list[str] = []
    if not src:
        raise TopicError(f"role 'odometry': no usable message on '{cfg.topics.odometry}' (nor odom->base TF on '{cfg.topics.tf}')")
    t = np.array([s[0] for s in src], np.int64)
    track_, ooo, dups = PoseTrack.from_unsorted(t, np.array([s[1] for s in src]), np.array([s[2] for s in src]),
                                               int(cfg.extract.pose_tolerance_s * 1e9))
    if ooo:
        warnings.append(f"odometry: {ooo} out-of-order stamps (sorted)")
    if dups:
        warnings.append(f"odometry: {dups} duplicate stamps (dropped)")
    if len(track_) < 2:
        raise PoseError(f"odometry has {len(track_)} distinct stamps; expected at least 2")
    gaps = np.diff(track_.t_ns) * 1e-9
    big = gaps > 2 * cfg.extract.pose_tolerance_s
    if big.any():
        warnings.append(f"odometry: {int(big.sum())} gaps longer than {2 * cfg.extract.pose_tolerance_s:.2f} s (max {gaps.max():.2f} s); samples there are rejected")
    for s in scan.stats.values():
        if s.record_skew_max_s > cfg.extract.record_skew_warn_s:
            warnings.append(f"{s.topic}: header stamps differ from record times by up to {s.record_skew_max_s:.1f} s (header stamps are used)")
    return track_, warnings


def _extrinsics(cfg: GtgenConfig, scan: _Scan) -> dict[str, tuple[NDArray, NDArray, tuple[int, int]]]:
    out = {}
    W, H = cfg.extract.image_width, cfg.extract.image_height
    for c in CAMERAS:
        info = scan.info.get(c)
        if info is None:
            raise TopicError(f"role 'camera_info.{c}': no CameraInfo on '{cfg.topics.cameras[c].info}'")
        Kraw = np.asarray(getattr(info, "k", None) if hasattr(info, "k") else info.K, dtype=np.float64).reshape(3, 3)
        src = (int(info.width), int(info.height))
        K = rescale_K(Kraw, src, (W, H))
        frame = scan.frames.get(f"camera.{c}") or info.header.frame_id.lstrip("/")
        T = _chain(scan.static, cfg.topics.base_frame, frame)
        if T is None:
            raise TopicError(f"camera '{c}': no static transform from '{cfg.topics.base_frame}' to '{frame}' in '{cfg.topics.tf_static}'")
        out[c] = (K, T, src)
    return out


def _create(root, path: str, shape: tuple, chunks: tuple | None = None, flat: bool = False):
    """Create drive-store array ``path``; ``flat`` keys its chunks 'c.i.j...' (one folder)."""
    sp = st.spec(path)
    chunks = chunks or tuple(max(1, s) for s in shape)
    keys = {"name": "default", "separator": "." if flat else "/"}
    return root.create_array(path, shape=shape, dtype=sp.dtype, chunks=chunks, fill_value=sp.fill_value(), compressors=compressors(),
                             chunk_key_encoding=keys)


def _write_small(root, cfg: GtgenConfig, scan: _Scan, track_: PoseTrack, plan: _Plan, extr) -> None:
    _create(root, "poses/t_ns", track_.t_ns.shape)[:] = track_.t_ns
    _create(root, "poses/pos_odom_m", track_.pos.shape)[:] = track_.pos
    _create(root, "poses/quat_odom_xyzw", track_.quat.shape)[:] = track_.quat
    g = sorted(scan.gnss, key=lambda x: x[0])
    G = len(g)
    cols = {
        "gnss/t_ns": np.array([x[0] for x in g], np.int64).reshape(G),
        "gnss/lat_deg": np.array([x[1] for x in g], np.float64).reshape(G),
        "gnss/lon_deg": np.array([x[2] for x in g], np.float64).reshape(G),
        "gnss/alt_m": np.array([x[3] for x in g], np.float64).reshape(G),
        "gnss/var_enu_m2": np.array([x[4] for x in g], np.float64).reshape(G, 3),
        "gnss/status": np.array([x[5] for x in g], np.int8).reshape(G),
    }
    for k, v in cols.items():
        a = _create(root, k, v.shape, chunks=tuple(max(1, s) for s in v.shape))
        if v.size:
            a[:] = v
    _create(root, "candidates/t_ns", plan.cand_t.shape)[:] = plan.cand_t
    _create(root, "candidates/reason", plan.cand_reason.shape)[:] = plan.cand_reason
    S = len(plan.t)
    pos, quat = track_.interpolate(plan.t)
    dist = np.interp(plan.t.astype(np.float64), track_.t_ns.astype(np.float64), track_.distance())
    _create(root, "samples/t_ns", (S,))[:] = plan.t
    _create(root, "samples/pos_odom_m", (S, 3))[:] = pos
    _create(root, "samples/quat_odom_xyzw", (S, 4))[:] = quat
    _create(root, "samples/distance_m", (S,))[:] = dist
    for r in RANGES:
        _create(root, f"samples/map_index_{r}", (S,))[:] = plan.sample_map[r]
    _create(root, "samples/image_t_ns", (S, 4))[:] = plan.image_t
    _create(root, "samples/voxel_t_ns", (S,))[:] = plan.voxel_t
    _create(root, "samples/voxel_index", (S,))[:] = plan.voxel_index
    _create(root, "voxel_maps/t_ns", plan.voxel_map_t.shape)[:] = plan.voxel_map_t
    _create(root, "calib/K", (4, 3, 3))[:] = np.stack([extr[c][0] for c in CAMERAS])
    _create(root, "calib/T_base_cam", (4, 4, 4))[:] = np.stack([extr[c][1] for c in CAMERAS])


def _map_to_odom(cfg: GtgenConfig, static: dict[tuple[str, str], NDArray], center: NDArray, yaw: float, frame: str
                 ) -> tuple[NDArray, float]:
    """Return a grid's centre and yaw in odom, through tf_static if its frame differs."""
    if frame in ("", cfg.topics.odom_frame):
        return center, yaw
    T = _chain(static, cfg.topics.odom_frame, frame)
    if T is None:
        raise DecodeError(f"GridMap frame '{frame}' has no static transform to '{cfg.topics.odom_frame}'")
    Tc = T @ yaw_transform(*center, yaw)
    return Tc[:3, 3], float(np.arctan2(Tc[1, 0], Tc[0, 0]))


def _write_large(root, tmp: Path, paths: list[Path], cfg: GtgenConfig, roles: dict[str, str], scan: _Scan, track_: PoseTrack,
                 plan: _Plan, bounds: list, counts: list[dict[str, int]], staged: list[_Staged], jobs: ProcessJobs) -> int:
    """Put the plan's images, maps and voxel clouds in the store: staged ones by moving
    their chunk files, the rest read by a targeted pass over the slices that hold them.
    Return how many kept messages that pass read."""
    S = len(plan.t)
    W, H = cfg.extract.image_width, cfg.extract.image_height
    tp = cfg.topics
    _create(root, "samples/images", (S, 4, H, W, 3), chunks=(1, 1, H, W, 3), flat=True)
    for r in RANGES:
        shape, res = scan.map_shape[f"map.{r}"]
        for name in MAP_LAYERS:
            _create(root, f"maps/{r}/{name}", (len(plan.map_t[r]),) + shape, chunks=(1,) + shape, flat=True)
        root[f"maps/{r}"].attrs.update({"resolution_m": res, "shape": list(shape), "frame": tp.odom_frame})
    # which (role, ordinal) goes where
    want: dict[str, dict[int, list[int]]] = defaultdict(lambda: defaultdict(list))
    for c_i, c in enumerate(CAMERAS):
        for s_i, o in enumerate(plan.image_ord[:, c_i]):
            want[f"camera.{c}"][int(o)].append(s_i)
    for v, o in enumerate(plan.voxel_ord):
        want["voxel_map"][int(o)].append(v)
    for r in RANGES:
        for k_i, o in enumerate(plan.map_ord[r]):
            want[f"map.{r}"][int(o)].append(k_i)
    big_roles = {t: r for t, r in roles.items() if r.startswith(("camera.", "map.")) or r == "voxel_map"}
    firsts: list[dict[str, int]] = []  # per slice: ordinal of each role's first message in it
    first = {role: 0 for role in big_roles.values()}
    for n in counts:
        firsts.append(dict(first))
        for role in big_roles.values():
            first[role] += n[role]
    starts = {role: np.array([f[role] for f in firsts], np.int64) for role in big_roles.values()}

    def locate(role: str, o: int) -> tuple[_Staged | None, int]:
        k = int(np.searchsorted(starts[role], o, side="right")) - 1
        return (staged[k] if staged else None), o - int(starts[role][k])

    centers = {r: np.zeros((len(plan.map_t[r]), 3)) for r in RANGES}
    yaws = {r: np.zeros(len(plan.map_t[r])) for r in RANGES}
    missing: dict[str, dict[int, list[int]]] = defaultdict(dict)
    made: set[Path] = set()
    seps: dict[str, str] = {}

    def place(src: Path, dst_path: str, coords: list[tuple[int, ...]]) -> None:
        if dst_path not in seps:
            seps[dst_path] = check_encoded_chunks(root[dst_path])
        for n, c in enumerate(coords):  # the last use takes the file, earlier ones link to it
            place_chunk(src, chunk_file(tmp, dst_path, c, seps[dst_path]), move=n == len(coords) - 1, made=made)

    for c_i, c in enumerate(CAMERAS):
        role = f"camera.{c}"
        for o, targets in want[role].items():
            stg, i = locate(role, o)
            if stg is None or i not in stg.ordinals[role]:
                missing[role][o] = targets
                continue
            place(stg.chunk(role, i), "samples/images", [(s_i, c_i, 0, 0, 0) for s_i in targets])
    for r in RANGES:
        role = f"map.{r}"
        for o, targets in want[role].items():
            stg, i = locate(role, o)
            if stg is None or i not in stg.ordinals[role] or stg.map_shape.get(role) != scan.map_shape[role][0]:
                missing[role][o] = targets
                continue
            for name in MAP_LAYERS:
                place(stg.chunk(role, i, name), f"maps/{r}/{name}", [(k_i, 0, 0) for k_i in targets])
            center, yaw = _map_to_odom(cfg, scan.static, *stg.map_pose[(role, i)])
            centers[r][targets] = center
            yaws[r][targets] = yaw
    P = cfg.shards.max_voxel_points
    V = len(plan.voxel_ord)
    vox = _create(root, "voxel_maps/points_odom_m", (V, P, 3), chunks=(1, P, 3), flat=True)
    n_points = np.zeros(V, np.int64)
    raw: list[tuple[int, Path, int]] = []  # (index, .npy, stamp) of voxel maps staged in base_link
    for o, targets in want["voxel_map"].items():
        stg, i = locate("voxel_map", o)
        got = stg.voxels.get(i) if stg else None
        if got is None:
            missing["voxel_map"][o] = targets
        elif got[0] < 0:
            raw += [(v, stg.raw_voxels(i), got[1]) for v in targets]
        else:
            place(stg.chunk("voxel_map", i), "voxel_maps/points_odom_m", [(v, 0, 0) for v in targets])
            n_points[targets] = got[0]
    seen = 0
    with _Writes() as writes:
        work = []
        for k, ((a, b), n) in enumerate(zip(bounds, counts)):
            part = {role: {o: t for o, t in missing[role].items() if firsts[k][role] <= o < firsts[k][role] + n[role]}
                    for role in big_roles.values()}
            if any(part.values()):
                work.append((paths, cfg, big_roles, str(tmp), a, b, firsts[k], part, scan.static, track_))
        for got in jobs.map(_write_slice, work, "extract: reading what no slice staged") if work else ():
            seen += got.selected
            for (r, k_i), (c, y) in got.maps.items():
                centers[r][k_i] = c
                yaws[r][k_i] = y
            for v, pts in got.voxels.items():
                n_points[v] = len(pts)
                writes.submit(vox.__setitem__, v, _padded(pts, P))
        for v, f, t in raw:
            pts = _nearest_points(_base_to_odom(np.load(f), t, track_), P)
            n_points[v] = len(pts)
            writes.submit(vox.__setitem__, v, _padded(pts, P))
    n_missing = sum(len(v) for v in missing.values())
    log.debug("extract: %d kept messages not staged: %s", n_missing, {r: len(v) for r, v in missing.items() if v})
    if seen != n_missing:
        raise BagError(f"bags ended before every selected message was read ({seen} of {n_missing} messages)")
    _create(root, "voxel_maps/n_points", (V,))[:] = n_points
    for r in RANGES:
        _create(root, f"maps/{r}/t_ns", plan.map_t[r].shape)[:] = plan.map_t[r]
        _create(root, f"maps/{r}/center_odom_m", centers[r].shape)[:] = centers[r]
        _create(root, f"maps/{r}/yaw_odom_rad", yaws[r].shape)[:] = yaws[r]
    shutil.rmtree(tmp / STAGE, ignore_errors=True)
    return n_missing


@dataclass
class _SliceOut:
    selected: int
    maps: dict[tuple[str, int], tuple[NDArray, float]]
    voxels: dict[int, NDArray]  # kept voxel map index -> points in odom


class _Writes:
    """Array writes on two background threads (compression releases the GIL), so that
    encoding overlaps with reading the bag; at most a few writes are in flight."""

    def __enter__(self) -> _Writes:
        from concurrent.futures import ThreadPoolExecutor

        self.pool = ThreadPoolExecutor(max_workers=2)
        self.pending: list = []
        return self

    def submit(self, fn, *args) -> None:
        """Run ``fn(*args)`` on the pool."""
        self.pending.append(self.pool.submit(fn, *args))
        while len(self.pending) > 8:
            self.pending.pop(0).result()

    def drain(self) -> None:
        while self.pending:
            self.pending.pop(0).result()

    def __exit__(self, *exc: object) -> None:
        try:
            self.drain()
        finally:
            self.pool.shutdown(wait=True)


def _write_slice(paths: list[Path], cfg: GtgenConfig, roles: dict[str, str], store: str, start: int | None, stop: int | None,
                 first: dict[str, int], want: dict[str, dict[int, list[int]]], static: dict, track_: PoseTrack) -> _SliceOut:
    """The targeted second pass over [start, stop) (a process-pool job): decode the kept
    messages in ``want``, write images and maps into their chunks; return map poses and
    voxel points."""
    import zarr

    tp = cfg.topics
    W, H = cfg.extract.image_width, cfg.extract.image_height
    layer_names = (tp.layers.elevation, tp.layers.risk, tp.layers.confidence)
    root = zarr.open_group(store, mode="r+")
    images = root["samples/images"]
    maps = {r: {name: root[f"maps/{r}/{name}"] for name in MAP_LAYERS} for r in RANGES}
    out = _SliceOut(0, {}, {})
    if not any(want.values()):
        return out
    ordinal = dict(first)
    with BagSet(paths) as bags, _Writes() as writes, Runs(writes.submit) as runs:
        for topic, msgtype, _, msg, err in bags.messages(list(roles), start, stop):
            role = roles[topic]
            o = ordinal[role]
            ordinal[role] += 1
            targets = want[role].get(o)
            if not targets:
                continue
            out.selected += 1
            if msg is None:
                raise DecodeError(f"{topic}: message {o} was selected but does not decode: {err}")
            if role.startswith("camera."):
                c_i = CAMERAS.index(role.split(".")[1])
                img = resize_image(decode_image(msg, msgtype), W, H)
                for s_i in targets:
                    runs.put(images, s_i, img, (c_i,))
            elif role == "voxel_map":
                pts = _voxel_points(msg, cfg, track_)
                for v in targets:
                    out.voxels[v] = pts
            else:
                r = role.split(".")[1]
                g = decode_gridmap(msg, list(layer_names))
                arr = maps[r]
                if g.shape != tuple(arr["elevation_m"].shape[1:]):
                    raise DecodeError(f"{topic}: GridMap size changed from {tuple(arr['elevation_m'].shape[1:])} to {g.shape}")
                center, yaw = _map_to_odom(cfg, static, g.center_m, g.yaw_rad, g.frame_id)
                for k_i in targets:
                    for name, layer in zip(MAP_LAYERS, layer_names):
                        runs.put(arr[name], k_i, g.layers[layer])
                    out.maps[(r, k_i)] = (center, yaw)
    return out


def _voxel_points(msg, cfg: GtgenConfig, track_: PoseTrack) -> NDArray[np.float32]:
    """Return a voxel map's points in odom, at most ``shards.max_voxel_points`` (the nearest)."""
    tp = cfg.topics
    pts = decode_pointcloud(msg)
    frame = msg.header.frame_id.lstrip("/")
    if frame not in ("", tp.odom_frame):
        if frame != tp.base_frame:
            raise DecodeError(f"voxel map frame '{frame}' unsupported; expected '{tp.odom_frame}' or '{tp.base_frame}'")
        pts = _base_to_odom(pts, stamp_ns(msg.header), track_)
    return _nearest_points(pts, cfg.shards.max_voxel_points)


def _padded(pts: NDArray[np.float32], n: int) -> NDArray[np.float32]:
    """Return ``pts`` (at most ``n``) as an (n, 3) block, NaN after the last point."""
    out = np.full((n, 3), np.nan, np.float32)
    out[: len(pts)] = pts
    return out


def _base_to_odom(pts: NDArray[np.float32], t: int, track_: PoseTrack) -> NDArray[np.float32]:
    T = track_.transforms(np.array([t]))[0]
    return (pts @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def _nearest_points(pts: NDArray[np.float32], n: int) -> NDArray[np.float32]:
    """Return the ``n`` points nearest the cloud's xy centroid (the far ones matter least), in order."""
    if len(pts) <= n:
        return pts
    c = pts[:, :2].mean(axis=0)
    d2 = np.square(pts[:, 0] - c[0]) + np.square(pts[:, 1] - c[1])
    return pts[np.sort(np.argpartition(d2, n - 1)[:n])]
