"""Writing the drive store: the small arrays at once, then the plan's images, maps and
voxel clouds, staged ones by moving their chunk files and the rest by a targeted second
pass over the slices that hold them. One chunk per image, map and voxel map, so slices
never write the same chunk."""

from __future__ import annotations

import logging
import shutil
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.gridmap import decode_gridmap
from gtgen.bag.decode.image import image_source
from gtgen.bag.decode.pointcloud import decode_scan
from gtgen.bag.decode.tf import frame_id
from gtgen.bag.poses import PoseTrack
from gtgen.bag.reader import BagSet, stamp_ns
from gtgen.bag.tf import TfBuffer
from gtgen.config import RANGES, GtgenConfig
from gtgen.errors import BagError, DecodeError
from gtgen.extract import mapped
from gtgen.extract.calib import map_to_odom
from gtgen.extract.images import StoredCamera, capacity, read_source
from gtgen.extract.inventory import Scan
from gtgen.extract.lidar import compact, deskew
from gtgen.extract.roles import is_large
from gtgen.extract.select import Plan
from gtgen.extract.stage import STAGE, Staged
from gtgen.extract.voxels import padded, thinned_points, to_odom_frame, voxel_points
from gtgen.runtime.pool import BackgroundWrites, Pool
from gtgen.storage.chunks import Runs
from gtgen.storage.drive import DriveSamples, DriveWriter, Fixes, Scans
from gtgen.storage.schema import MAP_LAYERS

log = logging.getLogger(__name__)

Want = dict[str, dict[int, list[int]]]  # role -> {message ordinal: indices it fills}


def write_small(w: DriveWriter, scan: Scan, track: PoseTrack, plan: Plan, cams: list[StoredCamera], K: NDArray,
                T_base_cam: NDArray) -> None:
    """Write the poses, GNSS fixes, candidates, per-sample rows and calibration."""
    w.write_poses(track.t_ns, track.pos, track.quat)
    g = sorted(scan.gnss, key=lambda x: x[0])
    G = len(g)
    w.write_gnss(Fixes(
        np.array([x[0] for x in g], np.int64).reshape(G), np.array([x[1] for x in g], np.float64).reshape(G),
        np.array([x[2] for x in g], np.float64).reshape(G), np.array([x[3] for x in g], np.float64).reshape(G),
        np.array([x[4] for x in g], np.float64).reshape(G, 3), np.array([x[5] for x in g], np.int8).reshape(G),
    ))
    w.write_candidates(plan.cand_t, plan.cand_reason)
    pos, quat = track.interpolate(plan.t)
    dist = np.interp(plan.t.astype(np.float64), track.t_ns.astype(np.float64), track.distance())
    samples = DriveSamples(plan.t, pos, quat, dist, {r: plan.sample_map[r] for r in RANGES}, plan.image_t, plan.voxel_t,
                           plan.voxel_index, T_base_cam)
    w.write_samples(samples, plan.voxel_map_t, K, np.array([cam.size for cam in cams], np.int64).reshape(-1, 2))


def _wanted(plan: Plan) -> Want:
    """Return which message ordinal of each large role fills which samples, maps, voxel maps."""
    want: Want = defaultdict(lambda: defaultdict(list))
    for c_i, c in enumerate(plan.cameras):
        for s_i, o in enumerate(plan.image_ord[:, c_i]):
            want[f"camera.{c}"][int(o)].append(s_i)
    for v, o in enumerate(plan.voxel_ord):
        want["voxel_map"][int(o)].append(v)
    for r in RANGES:
        for k_i, o in enumerate(plan.map_ord[r]):
            want[f"map.{r}"][int(o)].append(k_i)
    base = 0
    for role, ords in sorted(plan.scan_ord.items(), key=lambda x: int(x[0].split(".")[1])):
        for j, o in enumerate(ords):
            want[role][int(o)].append(base + j)
        base += len(ords)
    return want


@dataclass
class Slices:
    """The read's slices: their record-time bounds, the first ordinal of each large role
    in each, and what each staged."""

    bounds: list[tuple[int | None, int | None]]
    counts: list[dict[str, int]]
    staged: list[Staged]

    def __post_init__(self) -> None:
        roles = [r for r in (self.counts[0] if self.counts else {}) if is_large(r)]
        self.firsts: list[dict[str, int]] = []
        first = dict.fromkeys(roles, 0)
        for n in self.counts:
            self.firsts.append(dict(first))
            for role in roles:
                first[role] += n[role]
        self._starts = {role: np.array([f[role] for f in self.firsts], np.int64) for role in roles}

    def locate(self, role: str, o: int) -> tuple[Staged | None, int]:
        """Return (what the slice holding ordinal ``o`` staged, the ordinal within it)."""
        k = int(np.searchsorted(self._starts[role], o, side="right")) - 1
        return (self.staged[k] if self.staged else None), o - int(self._starts[role][k])


def _cat(xs: list[NDArray], dt: type, shape: tuple[int, ...] = ()) -> NDArray:
    return np.concatenate(xs).astype(dt) if xs else np.zeros((0, *shape), dt)


class _Large:
    """Fills the store's images, maps and voxel clouds (see ``write_large``)."""

    def __init__(self, w: DriveWriter, cfg: GtgenConfig, scan: Scan, plan: Plan, slices: Slices, tf: TfBuffer,
                 cams: list[StoredCamera]) -> None:
        self.w, self.tmp, self.cfg, self.scan, self.plan, self.slices, self.tf = w, w.path, cfg, scan, plan, slices, tf
        self.cams = cams
        self.jpeg_nbytes = np.zeros((len(plan.t), len(cams)), np.int64)
        self.centers = {r: np.zeros((len(plan.map_t[r]), 3)) for r in RANGES}
        self.yaws = {r: np.zeros(len(plan.map_t[r])) for r in RANGES}
        self.z0 = {r: np.zeros(len(plan.map_t[r])) for r in RANGES}
        self.n_points = np.zeros(len(plan.voxel_ord), np.int64)
        self.missing: Want = defaultdict(dict)
        self.raw: list[tuple[int, Path, int, str]] = []  # (index, .npy, stamp, frame) of voxel maps staged in their frame
        self.lidars = sorted(plan.scan_ord, key=lambda r: int(r.split(".")[1]))
        self.scan_meta = self._scan_meta()
        self.raw_scans: list[tuple[list[int], Path, str]] = []  # (scan indexes, .npy, role) of scans staged with per-point times

    def _scan_meta(self) -> Scans:
        """The kept scans' rows (points counted as they are placed), sensor poses from TF."""
        p, odom = self.plan, self.cfg.topics.odom_frame
        t = [p.scan_t[r] for r in self.lidars]
        T = [self.tf.lookup(odom, self.scan.frames.get(r, ""), tt)[0] if self.scan.frames.get(r, "") not in ("", odom)
             else np.broadcast_to(np.eye(4), (len(tt), 4, 4)) for r, tt in zip(self.lidars, t)]
        return Scans(_cat(t, np.int64), _cat([np.full(len(tt), int(r.split(".")[1])) for r, tt in zip(self.lidars, t)], np.uint8),
                     np.zeros(sum(len(tt) for tt in t), np.int64), _cat([p.scan_dist[r] for r in self.lidars], np.float64),
                     _cat(T, np.float64, (4, 4)))

    def create_arrays(self) -> None:
        maps = {r: (len(self.plan.map_t[r]), *self.scan.map_shape[f"map.{r}"], self.cfg.topics.odom_frame) for r in RANGES}
        self.w.create_large(len(self.plan.t), len(self.cams), capacity(self.cfg), maps, len(self.plan.voxel_ord), self.cfg.shards.max_voxel_points,
                            len(self.scan_meta), self.cfg.extract.max_scan_points)
        self.vox = self.w.voxels()

    def place_staged(self, want: Want, pool: Pool) -> None:
        """Move what the slices staged into place (the images converted to their stored
        JPEG files on the pool); note in ``missing`` what they did not stage."""
        jobs: list[tuple[str, int, list[int]]] = []  # (staged frame, camera, samples)
        for c_i, cam in enumerate(self.cams):
            role = f"camera.{cam.name}"
            for o, targets in want[role].items():
                stg, i = self.slices.locate(role, o)
                if stg is None or i not in stg.ordinals[role]:
                    self.missing[role][o] = targets
                    continue
                jobs.append((str(stg.image(role, i)), c_i, targets))
        per = max(1, -(-len(jobs) // (4 * pool.workers)))
        work = [(str(self.tmp), self.cams, jobs[a : a + per]) for a in range(0, len(jobs), per)]
        for got in pool.map(store_images, work, "extract: storing images") if work else ():
            for (s_i, c_i), n in got.items():
                self.jpeg_nbytes[s_i, c_i] = n
        made = self.cfg.topics.from_lidar()  # made by the mapping pass, not read
        for r in RANGES:
            if r not in made:
                self._place_maps(r, want[f"map.{r}"])
        for o, targets in (want["voxel_map"] if "voxel_map" not in made else {}).items():
            stg, i = self.slices.locate("voxel_map", o)
            got = stg.voxels.get(i) if stg else None
            if got is None:
                self.missing["voxel_map"][o] = targets
            elif got[0] < 0:
                self.raw += [(v, stg.raw_voxels(i), got[1], got[2]) for v in targets]
            else:
                self.w.place_voxels(stg.chunk("voxel_map", i), targets)
                self.n_points[targets] = got[0]
        for role in self.lidars:
            for o, targets in want[role].items():
                stg, i = self.slices.locate(role, o)
                got = stg.scans.get((role, i)) if stg else None
                if got is None:
                    self.missing[role][o] = targets
                elif got[0] < 0:
                    self.raw_scans.append((targets, stg.raw_scan(role, i), role))
                else:
                    self.w.place_scan(stg.chunk(role, i), targets)
                    self._counted(targets, *got)

    def _place_maps(self, r: str, want: dict[int, list[int]]) -> None:
        role = f"map.{r}"
        for o, targets in want.items():
            stg, i = self.slices.locate(role, o)
            if stg is None or i not in stg.ordinals[role] or stg.map_shape.get(role) != self.scan.map_shape[role][0]:
                self.missing[role][o] = targets
                continue
            for name in MAP_LAYERS:
                self.w.place_map(stg.chunk(role, i, name), r, name, targets)
            pose = map_to_odom(self.cfg, self.tf, *stg.map_pose[(role, i)], int(self.plan.map_t[r][targets[0]]))
            self.centers[r][targets], self.yaws[r][targets], self.z0[r][targets] = pose

    def read_missing(self, pool: Pool, paths: list[Path], roles: dict[str, str]) -> int:
        """Read what no slice staged in a targeted pass, and the raw base-frame voxel maps;
        return how many kept messages that pass read."""
        big = {t: r for t, r in roles.items() if is_large(r)}
        P = self.cfg.shards.max_voxel_points
        work = []
        for k, ((a, b), n) in enumerate(zip(self.slices.bounds, self.slices.counts)):
            first = self.slices.firsts[k]
            part = {role: {o: t for o, t in self.missing[role].items() if first[role] <= o < first[role] + n[role]}
                    for role in big.values()}
            if any(part.values()):
                work.append((paths, self.cfg, big, str(self.tmp), a, b, first, part, self.tf, self.plan.map_t, self.cams))
        seen = 0
        with BackgroundWrites() as writes:
            for got in pool.map(read_slice, work, "extract: reading what no slice staged") if work else ():
                seen += got.selected
                for (s_i, c_i), n in got.jpeg_nbytes.items():
                    self.jpeg_nbytes[s_i, c_i] = n
                for (r, k_i), pose in got.maps.items():
                    self.centers[r][k_i], self.yaws[r][k_i], self.z0[r][k_i] = pose
                for v, pts in got.voxels.items():
                    self.n_points[v] = len(pts)
                    writes.submit(self.vox.__setitem__, v, padded(pts, P))
                for ls, (row, n, shift) in got.scans.items():
                    self._put_scan(writes, list(ls), row, n, shift)
            for v, f, t, frame in self.raw:
                pts = thinned_points(to_odom_frame(np.load(f), self.cfg, self.tf, frame, t), P, self.cfg.shards.far_voxel_m)
                self.n_points[v] = len(pts)
                writes.submit(self.vox.__setitem__, v, padded(pts, P))
            for ls, f, role in self.raw_scans:
                raw = np.load(f)
                pts = deskew(raw[:, :3], raw[:, 3], self.tf, self.cfg.topics.odom_frame, self.scan.frames.get(role, ""), int(self.scan_meta.t_ns[ls[0]]))
                self._put_scan(writes, ls, *compact(pts, self.cfg.extract.max_scan_points))
        n_missing = sum(len(v) for v in self.missing.values())
        log.debug("extract: %d kept messages not staged: %s", n_missing, {r: len(v) for r, v in self.missing.items() if v})
        if seen != n_missing:
            raise BagError(f"bags ended before every selected message was read ({seen} of {n_missing} messages)")
        return n_missing

    def _counted(self, ls: list[int], n: int, shift: NDArray) -> None:
        """Note scans ``ls``'s points and move their pose to their rows' origin (``lidar.compact``)."""
        self.scan_meta.n_points[ls] = n
        T = self.scan_meta.T_odom_sensor
        T[ls, :3, 3] += T[ls, :3, :3] @ shift

    def _put_scan(self, writes: BackgroundWrites, ls: list[int], row: NDArray, n: int, shift: NDArray) -> None:
        arr = self.w.scan_array()
        self._counted(ls, n, shift)
        for sc in ls:
            writes.submit(arr.__setitem__, sc, row)

    def finish(self) -> None:
        self.w.finish_large(self.n_points, self.jpeg_nbytes, {r: (self.plan.map_t[r], self.centers[r], self.yaws[r], self.z0[r]) for r in RANGES},
                            self.scan_meta)
        shutil.rmtree(self.tmp / STAGE, ignore_errors=True)


def write_large(w: DriveWriter, paths: list[Path], cfg: GtgenConfig, roles: dict[str, str], scan: Scan,
                tf: TfBuffer, track: PoseTrack, plan: Plan, slices: Slices, pool: Pool, lidar: list[str],
                cams: list[StoredCamera]) -> int:
    """Put the plan's images (as ``cams`` store them), maps, voxel clouds and raw scans in the
    store (the maps and voxel maps made from the raw scans on ``lidar`` by the mapping pass);
    return how many kept messages no slice had staged (read in a second pass)."""
    large = _Large(w, cfg, scan, plan, slices, tf, cams)
    large.create_arrays()
    large.place_staged(_wanted(plan), pool)
    reread = large.read_missing(pool, paths, roles)
    if cfg.topics.from_lidar():
        centers, n_points = mapped.map_pass(w, paths, cfg, lidar, tf, track, plan, pool)
        for r, c in centers.items():
            large.centers[r] = c
        if "voxel_map" in cfg.topics.from_lidar():
            large.n_points = n_points
    large.finish()
    return reread


def store_images(store: str, cams: list[StoredCamera], jobs: list[tuple[str, int, list[int]]]) -> dict[tuple[int, int], int]:
    """Write staged frames as their stored JPEG files (a process-pool job): ``jobs`` gives
    (staged frame file, camera index, samples); return {(sample, camera): JPEG bytes}."""
    w = DriveWriter.reopen(Path(store))
    out = {}
    for file, c_i, targets in jobs:
        jpeg = cams[c_i].stored(read_source(Path(file)))
        w.put_image(cams[c_i].padded(jpeg), c_i, targets)
        out.update({(s_i, c_i): len(jpeg) for s_i in targets})
        Path(file).unlink()
    return out


@dataclass
class SliceOut:
    """What a targeted pass over one slice read: map poses, voxel points, stored JPEG sizes."""

    selected: int
    maps: dict[tuple[str, int], tuple[NDArray, float, float]]  # (range, kept index) -> centre, yaw, height in odom
    voxels: dict[int, NDArray]  # kept voxel map index -> points in odom
    jpeg_nbytes: dict[tuple[int, int], int]  # (sample, camera) -> bytes of its stored JPEG
    scans: dict[tuple[int, ...], tuple[NDArray, int, NDArray]] = field(default_factory=dict)  # kept scan indexes -> (stored row, points, origin shift)


def read_slice(paths: list[Path], cfg: GtgenConfig, roles: dict[str, str], store: str, start: int | None, stop: int | None,
               first: dict[str, int], want: Want, tf: TfBuffer, map_t: dict[str, NDArray], cams: list[StoredCamera]) -> SliceOut:
    """The targeted second pass over [start, stop) (a process-pool job): decode the kept
    messages in ``want``, write images and maps into their chunks; return map poses,
    voxel points and the stored JPEG sizes."""
    tp = cfg.topics
    layer_names = (tp.layers.elevation, tp.layers.risk, tp.layers.confidence)
    w = DriveWriter.reopen(Path(store))
    maps = {r: {name: w.map_layer(r, name) for name in MAP_LAYERS} for r in RANGES}
    out = SliceOut(0, {}, {}, {})
    if not any(want.values()):
        return out
    ordinal = dict(first)
    with BagSet(paths) as bags, BackgroundWrites() as writes, Runs(writes.submit) as runs:
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
                c_i = next(i for i, cam in enumerate(cams) if cam.name == role.split(".")[1])
                jpeg = cams[c_i].stored(image_source(msg, msgtype))
                w.put_image(cams[c_i].padded(jpeg), c_i, targets)
                out.jpeg_nbytes.update({(s_i, c_i): len(jpeg) for s_i in targets})
            elif role == "voxel_map":
                pts = voxel_points(msg, cfg, tf)
                for v in targets:
                    out.voxels[v] = pts
            elif role.startswith("lidar."):
                pts, dt = decode_scan(msg)
                if dt is not None:
                    pts = deskew(pts, dt, tf, tp.odom_frame, frame_id(msg.header.frame_id), stamp_ns(msg.header))  # type: ignore[attr-defined]
                out.scans[tuple(targets)] = compact(pts, cfg.extract.max_scan_points)
            else:
                r = role.split(".")[1]
                g = decode_gridmap(msg, list(layer_names))
                arr = maps[r]
                if g.shape != tuple(arr["elevation_m"].shape[1:]):
                    raise DecodeError(f"{topic}: GridMap size changed from {tuple(arr['elevation_m'].shape[1:])} to {g.shape}")
                pose = map_to_odom(cfg, tf, g.center_m, g.yaw_rad, g.frame_id, int(map_t[r][targets[0]]))
                for k_i in targets:
                    for name, layer in zip(MAP_LAYERS, layer_names):
                        runs.put(arr[name], k_i, g.layers[layer])
                    out.maps[(r, k_i)] = pose
    return out
