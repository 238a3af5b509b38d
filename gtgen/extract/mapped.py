"""Maps and voxel maps made from raw lidar inside extract, for what no stack publishes
(``topics.map_<range>: null``, ``topics.voxel_map: null``; see ``gtgen.mapping``).

Why inside extract and not a stage of its own: extract decides which maps a drive keeps
(``extract.map_rate_hz`` and each sample's map at t), so the mapping makes exactly those
and nothing else, at the reference sensor's stamps, with no maps written out and read back;
everything after extract (fuse, dem-align, the dataset) reads them as it reads X-Racer's.

``declare`` gives the plan a map of each lidar-made range (and a voxel map) at every stamp
of the reference sensor (a camera, else the first lidar), as if a stack published them there; after the plan, ``map_pass`` reads the
raw scans again in time segments on the pool (each starting ``mapping.memory_s`` early so
its cells are warm; maps do not depend on the split) and writes the kept maps and voxel
maps into the store.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.pointcloud import decode_scan
from gtgen.bag.decode.tf import frame_id
from gtgen.bag.poses import PoseTrack
from gtgen.bag.reader import BagSet, stamp_ns
from gtgen.bag.tf import TfBuffer
from gtgen.config import RANGES, GtgenConfig
from gtgen.extract.inventory import Scan
from gtgen.extract.lidar import deskew
from gtgen.extract.select import Plan, reference_stamps
from gtgen.extract.voxels import padded, thinned_points
from gtgen.mapping.mapper import Mapper
from gtgen.runtime.pool import Pool
from gtgen.storage.drive import DriveWriter
from gtgen.storage.schema import MAP_LAYERS

REORDER_NS = 500_000_000  # scans are put in stamp order within this much of record time


def declare(cfg: GtgenConfig, scan: Scan) -> None:
    """Give ``scan`` a usable map of each lidar-made range, and a voxel map, at every usable
    stamp of the reference sensor (the sample candidates' times: ``extract.reference``) from
    the first raw scan on, in odom."""
    made = cfg.topics.from_lidar()
    first = min((min((s for s in v if s >= 0), default=np.iinfo(np.int64).max) for r, v in scan.stamps.items() if r.startswith("lidar.")),
                default=np.iinfo(np.int64).min)
    t = [int(s) for s in reference_stamps(cfg, scan) if s >= first]
    odom = cfg.topics.odom_frame
    for r in RANGES:
        if r in made:
            g = cfg.grids.get(r)
            grid = ((g.size, g.size), g.resolution_m)
            scan.map_meta[f"map.{r}"] = [(s, True, odom, grid) for s in t]
            scan.map_shape[f"map.{r}"] = grid
    if "voxel_map" in made:
        scan.stamps["voxel_map"] = list(t)
        scan.voxel_frames = [odom] * len(t)


@dataclass
class Targets:
    """What one segment makes: per lidar-made range the kept maps' indices and stamps, and
    the voxel maps'."""

    maps: dict[str, tuple[NDArray[np.int64], NDArray[np.int64]]] = field(default_factory=dict)
    voxels: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None

    def times(self) -> NDArray[np.int64]:
        ts = [t for _, t in self.maps.values()] + ([self.voxels[1]] if self.voxels is not None else [])
        return np.unique(np.concatenate(ts)) if ts else np.zeros(0, np.int64)


@dataclass
class SegmentOut:
    """What a segment made (its maps and voxel maps are in the store already): the maps'
    centres in odom and the voxel maps' point counts."""

    centers: dict[tuple[str, int], NDArray] = field(default_factory=dict)
    voxels: dict[int, int] = field(default_factory=dict)
    sweeps: int = 0  # scans added
    skipped: int = 0  # scans no pose or transform placed (or stamped too far out of order)


def map_pass(w: DriveWriter, paths: list[Path], cfg: GtgenConfig, topics: list[str], tf: TfBuffer, track: PoseTrack,
             plan: Plan, pool: Pool) -> tuple[dict[str, NDArray], NDArray[np.int64]]:
    """Make the plan's lidar-made maps and voxel maps into store ``w``; return per range the
    kept maps' centres in odom (K, 3) and the voxel maps' point counts (V,)."""
    made = cfg.topics.from_lidar()
    ranges = [r for r in RANGES if r in made]
    all_t = np.unique(np.concatenate([plan.map_t[r] for r in ranges] + ([plan.voxel_map_t] if "voxel_map" in made else [])))
    n_seg = max(1, min(len(all_t), 2 * pool.workers))
    cuts = all_t[np.linspace(0, len(all_t), n_seg + 1).astype(int)[1:-1]] if len(all_t) else np.zeros(0, np.int64)
    edges = np.r_[np.iinfo(np.int64).min, cuts, np.iinfo(np.int64).max]
    jobs = []
    for a, b in zip(edges[:-1], edges[1:]):
        tg = Targets()
        for r in ranges:
            k = np.nonzero((plan.map_t[r] >= a) & (plan.map_t[r] < b))[0]
            tg.maps[r] = (k, plan.map_t[r][k])
        if "voxel_map" in made:
            k = np.nonzero((plan.voxel_map_t >= a) & (plan.voxel_map_t < b))[0]
            tg.voxels = (k, plan.voxel_map_t[k])
        if len(tg.times()):
            jobs.append((paths, cfg, topics, str(w.path), tg, tf, track))
    centers = {r: np.zeros((len(plan.map_t[r]), 3)) for r in ranges}
    n_points = np.zeros(len(plan.voxel_map_t), np.int64)
    for out in pool.map(map_segment, jobs, "extract: mapping the lidar"):
        for (r, k), c in out.centers.items():
            centers[r][k] = c
        for v, n in out.voxels.items():
            n_points[v] = n
    return centers, n_points


def map_segment(paths: list[Path], cfg: GtgenConfig, topics: list[str], store: str, tg: Targets, tf: TfBuffer,
                track: PoseTrack) -> SegmentOut:
    """Map one segment (a process-pool job): feed the scans from ``memory_s`` before its first
    target to its last, in stamp order, and make each target once the scans pass it (a map
    at t holds the scans stamped up to t). Scans within ``BATCH_NS`` go in together, each put
    in odom with its own pose. Each map and voxel map goes into the store as it is made (a
    row each), so a segment's memory does not grow with its length."""
    times = tg.times()
    mapper = Mapper(cfg, tuple(tg.maps), voxels=tg.voxels is not None)
    w = DriveWriter.reopen(Path(store))
    arrays = {r: {name: w.map_layer(r, name) for name in MAP_LAYERS} for r in tg.maps}
    vox = w.voxels() if tg.voxels is not None else None
    out = SegmentOut()
    start = int(times[0] - cfg.mapping.memory_s * 1e9 - REORDER_NS)
    todo = list(times)
    heap: list[tuple[int, int, NDArray, str]] = []
    batch = _Batch()
    n = 0

    def flush() -> None:
        if batch.pts:
            mapper.add_odom(np.concatenate(batch.pts), np.concatenate(batch.rng), batch.center, batch.t)
            batch.__init__()  # type: ignore[misc]

    def feed(item: tuple[int, int, NDArray, str]) -> None:
        t, _, pts, frame = item
        if todo and todo[0] < t:
            flush()
            while todo and todo[0] < t:
                _make(todo.pop(0), mapper, tg, arrays, vox, cfg, track, out)
        if batch.pts and t - batch.t0 >= BATCH_NS:
            flush()
        if t < max(mapper.t_ns, batch.t):
            out.skipped += 1  # later than the reorder buffer allowed
            return
        _add(batch, mapper, cfg, tf, track, pts, frame, t, out)

    with BagSet(paths) as bags:
        for _topic, _type, rec_t, msg, _err in bags.messages(topics, start, int(times[-1] + REORDER_NS)):
            if msg is None:
                continue
            t = stamp_ns(msg.header)  # type: ignore[attr-defined]
            if t < start or t > times[-1]:
                continue
            frame = frame_id(msg.header.frame_id)  # type: ignore[attr-defined]
            pts, dt = decode_scan(msg)
            if dt is not None:  # per-point times: each point put where the sensor was at the stamp
                pts = deskew(pts, dt, tf, cfg.topics.odom_frame, frame, t)
            heapq.heappush(heap, (t, n, pts, frame))
            n += 1
            while heap and heap[0][0] < rec_t - REORDER_NS:
                feed(heapq.heappop(heap))
    while heap:
        feed(heapq.heappop(heap))
    flush()
    while todo:
        _make(todo.pop(0), mapper, tg, arrays, vox, cfg, track, out)
    return out


BATCH_NS = 100_000_000  # scans stamped within this go into the cells together (three lidars' sweeps)


@dataclass
class _Batch:
    """Scans in odom waiting to go into the cells together."""

    pts: list[NDArray] = field(default_factory=list)
    rng: list[NDArray] = field(default_factory=list)
    t0: int = 0  # the first scan's stamp
    t: int = np.iinfo(np.int64).min  # the last scan's stamp
    center: NDArray = field(default_factory=lambda: np.zeros(2))


def _add(batch: _Batch, mapper: Mapper, cfg: GtgenConfig, tf: TfBuffer, track: PoseTrack, pts: NDArray, frame: str, t: int,
         out: SegmentOut) -> None:
    """Put one scan in ``frame`` at ``t`` into ``batch`` in odom (skipped where no pose or
    transform is known)."""
    T_bs, ok = tf.lookup(cfg.topics.base_frame, frame, np.array([t]))
    if not ok[0] or not track.covered(np.array([t]))[0]:
        out.skipped += 1
        return
    T_ob = track.transforms(np.array([t]))[0]
    pb = pts.astype(np.float64) @ T_bs[0, :3, :3].T + T_bs[0, :3, 3]
    odom, rng = mapper.to_odom(pb, T_bs[0, :3, 3], T_ob)
    if not batch.pts:
        batch.t0 = t
    batch.pts.append(odom)
    batch.rng.append(rng)
    batch.t, batch.center = t, T_ob[:2, 3]
    out.sweeps += 1


def _make(t: int, mapper: Mapper, tg: Targets, arrays: dict, vox: Any, cfg: GtgenConfig, track: PoseTrack, out: SegmentOut) -> None:
    """Make every target stamped ``t`` into the store (``arrays``: the map layers per range,
    ``vox``: the voxel clouds): maps centred on the vehicle there, the voxel map."""
    center = track.interpolate(np.array([t]), strict=False)[0][0, :2]
    for r, (k, ts) in tg.maps.items():
        for k_i in k[ts == t]:
            lay = mapper.map(r, center, t)
            for name, layer in zip(MAP_LAYERS, (lay.elevation, lay.risk, lay.confidence)):
                arrays[r][name][int(k_i)] = layer
            out.centers[(r, int(k_i))] = np.array([lay.center[0], lay.center[1], 0.0])
    if tg.voxels is not None:
        k, ts = tg.voxels
        for v in k[ts == t]:
            pts = thinned_points(mapper.voxel_points(t, center), cfg.shards.max_voxel_points, cfg.shards.far_voxel_m)
            vox[int(v)] = padded(pts, cfg.shards.max_voxel_points)
            out.voxels[int(v)] = len(pts)
