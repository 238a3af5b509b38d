"""Drive the simulated sensors over the path and write bags, DEM tiles and truth."""

from __future__ import annotations

import io
import json
import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gtgen.bag.decode.image import encode_jpeg, resize_image
from gtgen.bag.messages import MessageFactory, open_mcap_writer
from gtgen.config import LIDARS, GtgenConfig, SynthConfig, save_config
from gtgen.errors import ConfigError, GtgenError
from gtgen.geometry import make_transform, matrix_to_quat, quat_to_matrix, rescale_K, rpy_to_quat
from gtgen.runtime.output import stage_output
from gtgen.runtime.pool import Pool
from gtgen.runtime.progress import track
from gtgen.synth import camera, lidar, sensors
from gtgen.synth.drive import gnss_errors, gnss_outage
from gtgen.synth.world import SynthWorld

log = logging.getLogger(__name__)

MAP_LATENCY_NS = 50_000_000
GNSS_FRAME = "gnss_link"
LIDAR_FRAME = "lidar"
VOXEL_M = 0.4
JPEG_QUALITY = 90  # of the simulated cameras' CompressedImage frames
VOXEL_HALF_M = 100.0


def camera_frame(name: str) -> str:
    """Return the optical frame id of camera ``name``."""
    return f"cam_{name}_optical"


@dataclass
class SynthResult:
    """What ``run_synth`` wrote."""

    out: Path
    bags: list[Path]
    dem_tiles: list[Path]
    counts: dict[str, int] = field(default_factory=dict)
    duration_s: float = 0.0
    distance_m: float = 0.0


class _Sinks:
    """Writes every message to each requested bag flavour."""

    def __init__(self, tmp: Path, formats: str) -> None:
        self.writers: list[tuple[MessageFactory, object, dict[str, object]]] = []
        self.tmp = tmp
        if formats in ("mcap", "both"):
            self.writers.append((MessageFactory(ros1=False), open_mcap_writer(tmp / "ros2"), {}))
        if formats in ("bag", "both"):
            from rosbags.rosbag1 import Writer as Writer1

            w1 = Writer1(tmp / "drive.bag")
            w1.set_compression(Writer1.CompressionFormat.LZ4)
            w1.open()
            self.writers.append((MessageFactory(ros1=True), w1, {}))
        self.counts: dict[str, int] = {}

    def write_raw(self, topic: str, msgtype: str, t_ns: int, blobs: list[bytes]) -> None:
        """Write serialized messages (one per flavour, in writer order) at record time ``t_ns``."""
        for (fac, w, conns), blob in zip(self.writers, blobs):
            if topic not in conns:
                kw = {"latching": 1} if fac.ros1 and topic.endswith("static") else {}
                conns[topic] = w.add_connection(topic, msgtype, typestore=fac.store, **kw)
            w.write(conns[topic], int(t_ns), blob)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self, out_tmp: Path) -> list[Path]:
        paths = []
        for fac, w, _ in self.writers:
            w.close()
            if fac.ros1:
                paths.append(out_tmp / "drive.bag")
            else:
                # keep only the self-contained .mcap file: a bare MCAP with its schemas
                mcap = next((self.tmp / "ros2").glob("*.mcap"))
                mcap.rename(out_tmp / "drive.mcap")
                shutil.rmtree(self.tmp / "ros2")
                paths.append(out_tmp / "drive.mcap")
        return paths


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise ConfigError(f"output '{out}' exists and is not empty; choose another OUT or pass --overwrite")
    parent = out.resolve().parent
    if parent.exists() and not parent.is_dir():
        raise ConfigError(f"cannot write OUT '{out}': '{parent}' is a file, not a folder")
    if not parent.exists():
        try:
            parent.mkdir(parents=True)
        except OSError as err:
            raise ConfigError(f"cannot create the parent folder of OUT '{out}': {err.strerror}") from err
    if not os.access(parent, os.W_OK):
        raise ConfigError(f"output folder '{parent}' is not writable")


def run_synth(cfg: GtgenConfig, out: Path, overwrite: bool = False) -> SynthResult:
    """Write a synthetic drive into folder ``out``; all or nothing (written aside, then renamed)."""
    _check_out(out, overwrite)
    with stage_output(out) as tmp:
        tmp.mkdir()
        result = _write_drive(cfg, tmp)
        save_config(cfg, tmp / "gtgen-config.yaml")
    result.out = out
    result.bags = [out / p.name for p in result.bags]
    result.dem_tiles = [out / "dem" / p.name for p in result.dem_tiles]
    return result


def _write_drive(cfg: GtgenConfig, tmp: Path) -> SynthResult:
    sc = cfg.synth
    world = SynthWorld(sc)
    from gtgen.synth.dem import write_dem_tiles

    tiles = write_dem_tiles(world, tmp / "dem")
    raster = camera.RenderRaster(world.terrain, world.bounds)
    sinks = _Sinks(tmp, sc.formats)
    try:
        _simulate(cfg, world, raster, sinks)
        bags = sinks.close(tmp)
    except BaseException:
        for _, w, _ in sinks.writers:
            try:
                w.close()
            except Exception:  # noqa: BLE001 - already failing; the temp folder is removed
                pass
        raise
    _write_truth(cfg, world, tmp / "truth")
    return SynthResult(
        out=tmp, bags=bags, dem_tiles=tiles, counts=sinks.counts,
        duration_s=sc.duration_s, distance_m=float(world.path.dist[-1]),
    )


def _period(base_hz: float, hz: float, name: str) -> int:
    p = int(round(base_hz / hz))
    if p < 1:
        raise ConfigError(f"synth.{name} = {hz} Hz is faster than odom_rate_hz = {base_hz} Hz; expected at most {base_hz}")
    return p


class _Ticker:
    """Builds every message of one odometry tick; a pure function of the tick index.

    Randomness is drawn from generators seeded by (seed, stream, tick), so the bytes do
    not depend on how ticks are spread over worker processes.
    """

    def __init__(self, cfg: GtgenConfig, world: SynthWorld, raster: camera.RenderRaster, formats: str) -> None:
        from pyproj import Transformer

        sc, tp = cfg.synth, cfg.topics
        self.cfg, self.world, self.raster = cfg, world, raster
        self.factories = [MessageFactory(ros1=r) for r in ((False,) if formats == "mcap" else (True,) if formats == "bag" else (False, True))]
        self.to_wgs84 = Transformer.from_crs(sc.crs, "EPSG:4326", always_xy=True)
        self.n = len(world.t_ns)
        self.map_p = _period(sc.odom_rate_hz, sc.map_rate_hz, "map_rate_hz")
        self.gnss_p = _period(sc.odom_rate_hz, sc.gnss_rate_hz, "gnss_rate_hz")
        self.cam_p = _period(sc.odom_rate_hz, sc.camera_rate_hz, "camera_rate_hz")
        self.vox_p = _period(sc.odom_rate_hz, sc.voxel_rate_hz, "voxel_rate_hz")
        self.scan_p = _period(sc.odom_rate_hz, sc.scan_rate_hz, "scan_rate_hz") if sc.scan_rate_hz > 0 else 0
        self.T_base_lidar = {n: lidar.T_base_lidar(n) for n in LIDARS}
        gnss_idx = np.arange(0, self.n, self.gnss_p)
        self.gnss_err = gnss_errors(sc, world.t_ns[gnss_idx])
        self.gnss_off = gnss_outage(sc, world.t_ns[gnss_idx])
        self.gnss_sigma = float(np.hypot(sc.gnss_bias_m, sc.gnss_noise_m))
        self.K = camera.camera_intrinsic(sc)
        self.T_base_cam = {c: camera.camera_extrinsic(c) for c in tp.cameras}
        poses = world.poses
        self.q_true = rpy_to_quat(poses.rpy[:, 0], poses.rpy[:, 1], poses.rpy[:, 2])
        ro = world.odom.rpy_odom
        self.q_odom = rpy_to_quat(ro[:, 0], ro[:, 1], ro[:, 2])
        dt = 1.0 / sc.odom_rate_hz
        self.vel_odom = np.gradient(world.odom.p_odom, dt, axis=0)
        self.yaw_rate = np.gradient(np.unwrap(ro[:, 2]), dt)
        self._views: dict[int, sensors.LidarView] = {}  # the last two lidar views, by tick
        self._lattice: dict[int, sensors.LidarView] = {}  # the views of the memory's lattice ticks still within its span
        self.drift = stack_drift(sc, -(-self.n // self.map_p))

    def _msg(self, out: list, topic: str | None, msgtype: str, t_rec: int, build) -> None:
        if topic is None:  # a role the config leaves to gtgen.mapping (topics.map_<range>, voxel_map: null)
            return
        out.append((topic, msgtype, int(t_rec), [f.serialize(build(f), msgtype) for f in self.factories]))

    def static_messages(self) -> list:
        tp = self.cfg.topics
        t0 = int(self.world.t_ns[0])
        static = [(tp.base_frame, camera_frame(c), T[:3, 3], matrix_to_quat(T[:3, :3])) for c, T in self.T_base_cam.items()]
        static.append((tp.base_frame, LIDAR_FRAME, np.array(sensors.LIDAR_MOUNT), np.array([0, 0, 0, 1.0])))
        static.append((tp.base_frame, GNSS_FRAME, np.zeros(3), np.array([0, 0, 0, 1.0])))
        static += [(tp.base_frame, lidar.lidar_frame(n), T[:3, 3], matrix_to_quat(T[:3, :3])) for n, T in self.T_base_lidar.items()]
        out: list = []
        self._msg(out, tp.tf_static, "tf2_msgs/msg/TFMessage", t0, lambda f: f.tf_message([f.transform_stamped(t0, *s) for s in static]))
        return out

    def _view(self, k: int) -> sensors.LidarView:
        """Return the lidar view at tick ``k`` (a pure function of the tick). The views of the
        memory's lattice ticks are kept while a later map can still ask for them (a map asks
        for up to ``stack_memory_views - 1`` of them, most of them asked for by earlier maps
        too); of the others, the last two."""
        lattice = self._memory_step()
        cache = self._lattice if lattice and k % lattice == 0 else self._views
        view = cache.get(k)
        if view is None:
            origin = self.world.poses.pos[k] + np.array([0.0, 0.0, self.cfg.synth.lidar_height_m])
            view = cache[k] = sensors.lidar_view(self.cfg.synth, self.world.terrain, origin)
            if cache is self._views:
                while len(self._views) > 2:
                    del self._views[min(self._views)]
            else:  # older than the memory's longest span before the newest asked for: no map asks again
                span = int(np.ceil(self.cfg.synth.stack_memory_s * self.cfg.synth.odom_rate_hz)) + lattice
                for j in [j for j in self._lattice if j < max(self._lattice) - span]:
                    del self._lattice[j]
        return view

    def _memory_step(self) -> int:
        """Return the ticks between the memory's lattice ticks (0: the maps hold no memory)."""
        sc = self.cfg.synth
        n = sc.stack_memory_views - 1
        if sc.confidence_model != "density" or n < 1:
            return 0
        return max(1, int(round(sc.stack_memory_s * sc.odom_rate_hz / (n + 1) / self.map_p))) * self.map_p

    def _memory_ticks(self, k: int, speed: float) -> list[int]:
        """Return the ticks of the earlier poses of the stack's memory at tick ``k``: at most
        ``stack_memory_views - 1`` of them, on a fixed lattice of ticks that spreads that
        many over ``stack_memory_s`` (so consecutive maps share them), within the memory's
        span at ``speed``."""
        sc = self.cfg.synth
        n, step = sc.stack_memory_views - 1, self._memory_step()  # [ticks]
        if step == 0:
            return []
        span = sensors.stack_memory_s(sc, speed) * sc.odom_rate_hz  # [ticks]
        last = (k - 1) // step * step  # the lattice tick before k
        ks = [last - i * step for i in range(n)]
        return [j for j in ks if j >= 0 and k - j <= span]

    def _memory(self, k: int, speed: float) -> tuple[sensors.LidarView, ...]:
        """Return the views at the earlier poses of the stack's memory at tick ``k``."""
        return tuple(self._view(j) for j in self._memory_ticks(k, speed))

    def _registration(self, k: int) -> np.ndarray | None:
        """Return the registration error of the maps of map tick ``k``: (x, y, z [m], slope
        in x, slope in y [m/m]) in the world frame, the drift over the stack's memory plus
        this map's jitter; None when the stack registers perfectly (no draw then)."""
        sc = self.cfg.synth
        sd = np.array([sc.stack_jitter_xy_m, sc.stack_jitter_xy_m, sc.stack_jitter_z_m,
                       *np.tan(np.deg2rad([sc.stack_jitter_tilt_deg] * 2))])
        if self.drift is None and not sd.any():
            return None
        jitter = np.random.default_rng([sc.seed, 19, k]).standard_normal(5) * sd
        return jitter if self.drift is None else self.drift[k // self.map_p] + jitter

    def tick(self, k: int) -> list:
        """Return [(topic, msgtype, record time, [bytes per flavour])] of tick ``k``."""
        out: list = []
        self._odometry(out, k)
        if k % self.gnss_p == 0 and not self.gnss_off[k // self.gnss_p]:
            self._gnss(out, k)
        view = self._view(k) if (k % self.map_p == 0 or k % self.vox_p == 0) else None
        if k % self.map_p == 0:
            self._maps(out, k, view)
        if k % self.vox_p == 0:
            self._voxel_map(out, k, view)
        if k % self.cam_p == 0:
            self._cameras(out, k)
        if self.scan_p and k % self.scan_p == 0:
            self._scans(out, k)
        return out

    def _scans(self, out: list, k: int) -> None:
        """One scan of each lidar, cast from the true pose at the tick (on topics.lidar, in order)."""
        sc, tp = self.cfg.synth, self.cfg.topics
        t = int(self.world.t_ns[k])
        T_wb = make_transform(quat_to_matrix(self.q_true[k]), self.world.poses.pos[k])
        for i, (name, topic) in enumerate(zip(LIDARS, tp.lidar)):
            pts = lidar.scan_points(sc, self.raster, T_wb @ self.T_base_lidar[name], np.random.default_rng([sc.seed, 14, k, i]))
            frame, seq = lidar.lidar_frame(name), k // self.scan_p
            self._msg(out, topic, "sensor_msgs/msg/PointCloud2", t, lambda f, frame=frame, pts=pts, seq=seq: f.pointcloud(t, frame, pts, seq))

    def _odometry(self, out: list, k: int) -> None:
        tp, odom = self.cfg.topics, self.world.odom
        t = int(self.world.t_ns[k])
        p_o, q_o = odom.p_odom[k], self.q_odom[k]
        v_body = quat_to_matrix(q_o).T @ self.vel_odom[k]
        w_body = np.array([0.0, 0.0, self.yaw_rate[k]])
        self._msg(out, tp.odometry, "nav_msgs/msg/Odometry", t, lambda f: f.odometry(t, tp.odom_frame, tp.base_frame, p_o, q_o, v_body, w_body, k))
        self._msg(out, tp.tf, "tf2_msgs/msg/TFMessage", t, lambda f: f.tf_message([f.transform_stamped(t, tp.odom_frame, tp.base_frame, p_o, q_o)]))

    def _gnss(self, out: list, k: int) -> None:
        sc, tp, world = self.cfg.synth, self.cfg.topics, self.world
        t = int(world.t_ns[k])
        g = k // self.gnss_p
        e = self.gnss_err[g].copy()
        rng = np.random.default_rng([sc.seed, 12, g])
        if rng.random() < 0.01:  # occasional multipath outlier
            e[:2] += rng.normal(0, 12.0, 2)
        E, N = world.utm(world.poses.pos[k, :2]) + e[:2]
        lon, lat = self.to_wgs84.transform(E, N)
        alt = world.poses.pos[k, 2] + sc.geoid_offset_m + e[2]
        s2 = self.gnss_sigma**2
        cov = np.array([s2, s2, 2.25 * s2])
        self._msg(out, tp.gnss, "sensor_msgs/msg/NavSatFix", t, lambda f: f.navsatfix(t, GNSS_FRAME, lat, lon, alt, cov, 0, g))

    def _maps(self, out: list, k: int, view: sensors.LidarView) -> None:
        cfg, sc, tp, world = self.cfg, self.cfg.synth, self.cfg.topics, self.world
        odom = world.odom
        t = int(world.t_ns[k])
        m = k // self.map_p
        z_off = float(odom.p_odom[k, 2] - world.poses.pos[k, 2])
        rng = np.random.default_rng([sc.seed, 10, k])
        names = tp.layers
        speed = float(world.path.speed[world.pose_idx[k]])
        memory = self._memory(k, speed)
        reg = self._registration(k)
        for rng_name in ("micro", "short"):
            grid = cfg.grids.get(rng_name)
            center = np.round(odom.p_odom[k, :2] / grid.resolution_m) * grid.resolution_m
            cells = sensors.map_cells_world(grid, center, odom, k)
            fill_m = sc.stack_fill_micro_m if rng_name == "micro" else sc.stack_fill_short_m
            if reg is None:
                layers = sensors.xracer_map(sc, world.terrain, view, cells, z_off, rng, grid.resolution_m, speed, memory, fill_m)
            else:  # the map shows the terrain of a place off by its registration error, tilted about the vehicle
                u, v = cells
                layers = sensors.xracer_map(sc, world.terrain, view, (u + reg[0], v + reg[1]), z_off, rng, grid.resolution_m, speed, memory, fill_m)
                p = world.poses.pos[k]
                layers.elevation += (reg[2] + reg[3] * (u - p[0]) + reg[4] * (v - p[1])).astype(np.float32)
            start = (0, 0)
            if sc.circular_buffer_every and m % sc.circular_buffer_every == 1:
                start = tuple(int(x) for x in rng.integers(1, grid.size, 2))
            named = {names.elevation: layers.elevation, names.risk: layers.risk, names.confidence: layers.confidence}
            self._msg(
                out, tp.map_topic(rng_name), "grid_map_msgs/msg/GridMap", t + MAP_LATENCY_NS,
                lambda f, res=grid.resolution_m, center=center, named=named, start=start: f.gridmap(t, tp.odom_frame, res, center, named, start, m),
            )

    def _voxel_map(self, out: list, k: int, view: sensors.LidarView) -> None:
        """The voxel map aggregates, in odom, the returns of the stack's memory (the current
        lidar pose and the earlier ones its maps hold, each with its share of the memory's
        revolutions) or with ``voxel_map_memory: two_sweeps`` the last two sweeps it was given."""
        tp, odom = self.cfg.topics, self.world.odom
        t = int(self.world.t_ns[k])
        sc = self.cfg.synth
        rng = np.random.default_rng([sc.seed, 17, k])  # thins the points by the returns (density model)

        def points(j: int, v: sensors.LidarView, share: int = 1) -> np.ndarray:
            revs = sensors.stack_revolutions(sc, float(self.world.path.speed[self.world.pose_idx[j]])) / share
            return odom.world_to_odom(j, sensors.view_points(v, rng, revs))

        if sc.voxel_map_memory == "stack":
            ticks = [k, *self._memory_ticks(k, float(self.world.path.speed[self.world.pose_idx[k]]))]
            pts = [points(j, self._view(j), len(ticks)) for j in ticks]
        else:
            pts = [points(k, view)]
            if k >= self.vox_p:
                kp = k - self.vox_p
                pts.append(points(kp, self._view(kp)))
        allp = np.vstack(pts)
        inside = np.all(np.abs(allp[:, :2] - odom.p_odom[k, :2]) < VOXEL_HALF_M, axis=1)
        vx = sensors.voxelize(allp[inside], VOXEL_M)
        self._msg(out, tp.voxel_map, "sensor_msgs/msg/PointCloud2", t, lambda f: f.pointcloud_xyz(t, tp.odom_frame, vx, k // self.vox_p))

    def _cameras(self, out: list, k: int) -> None:
        sc, tp, poses = self.cfg.synth, self.cfg.topics, self.world.poses
        t = int(self.world.t_ns[k])
        T_wb = make_transform(quat_to_matrix(self.q_true[k]), poses.pos[k])
        size, rsize = (sc.image_width, sc.image_height), (sc.render_width, sc.render_height)
        K_render = rescale_K(self.K, size, rsize)
        for c, topics in tp.cameras.items():
            lens = camera.camera_lens(sc, c)
            img = camera.render(self.raster, T_wb @ self.T_base_cam[c], K_render, rsize, lens if lens.distorted else None)
            # the camera's frame: the render upsampled (a smooth world; rays cost, pixels do not)
            jpeg = encode_jpeg(resize_image(img, *size), JPEG_QUALITY)
            frame = camera_frame(c)
            seq = k // self.cam_p
            D = np.asarray(sc.distortion if lens.distorted else np.zeros(5))
            self._msg(out, topics.image, "sensor_msgs/msg/CompressedImage", t, lambda f, frame=frame, jpeg=jpeg, seq=seq: f.compressed_image(t, frame, jpeg, seq))
            self._msg(out, topics.info, "sensor_msgs/msg/CameraInfo", t, lambda f, frame=frame, seq=seq, D=D: f.camera_info(t, frame, *size, self.K, seq, D))


def stack_drift(sc: SynthConfig, n_maps: int) -> np.ndarray | None:
    """Return the registration drift of each of ``n_maps`` published maps (n_maps, 5): (x,
    y, z [m], slope in x, slope in y [m/m]), the change of a random walk over the stack's
    memory (``stack_memory_s`` of maps), so its std is ``stack_drift_*`` and consecutive
    maps share most of it; None when every ``stack_drift_*`` is 0 (no draw then)."""
    sd = np.array([sc.stack_drift_xy_m, sc.stack_drift_xy_m, sc.stack_drift_z_m, *np.tan(np.deg2rad([sc.stack_drift_tilt_deg] * 2))])
    if not sd.any():
        return None
    memory = max(1, int(round(sc.stack_memory_s * sc.map_rate_hz)))  # [maps]
    walk = np.cumsum(np.random.default_rng([sc.seed, 18]).standard_normal((n_maps + memory, 5)) * (sd / np.sqrt(memory)), axis=0)
    return walk[memory:] - walk[:-memory]


_TICKER: _Ticker | None = None  # the worker's ticker, made by _start_worker


def _start_worker(cfg: GtgenConfig, world: SynthWorld, raster: camera.RenderRaster) -> None:
    """Make this worker's ticker (its world and raster map their large arrays from files)."""
    global _TICKER
    _TICKER = _Ticker(cfg, world, raster, cfg.synth.formats)


def _tick_chunk(ks: range) -> list:
    if _TICKER is None:
        raise GtgenError("synth worker without a ticker: the pool was started without _start_worker")
    return [m for k in ks for m in _TICKER.tick(k)]


def _simulate(cfg: GtgenConfig, world: SynthWorld, raster: camera.RenderRaster, sinks: _Sinks) -> None:
    """Tick the drive on the process pool, writing every message in tick order. The
    terrain's tile pool and the render raster reach the workers as files they map (not
    as pickles of hundreds of MB each)."""
    ticker = _Ticker(cfg, world, raster, cfg.synth.formats)
    for topic, msgtype, t_rec, blobs in ticker.static_messages():
        sinks.write_raw(topic, msgtype, t_rec, blobs)
    chunk = 5
    chunks = [range(i, min(i + chunk, ticker.n)) for i in range(0, ticker.n, chunk)]
    workers = min(cfg.synth.workers, len(chunks))
    if workers > 1:
        world.terrain.share(sinks.tmp / "shared")
        raster.share(sinks.tmp / "shared")
    global _TICKER
    try:
        with Pool(workers, init=(_start_worker, (cfg, world, raster))) as pool:
            for msgs in track(pool.imap(_tick_chunk, chunks), "synth: simulating drive", total=len(chunks)):
                for topic, msgtype, t_rec, blobs in msgs:
                    sinks.write_raw(topic, msgtype, t_rec, blobs)
    finally:
        _TICKER = None  # set here when the pool has one worker
        shutil.rmtree(sinks.tmp / "shared", ignore_errors=True)


def _write_truth(cfg: GtgenConfig, world: SynthWorld, folder: Path) -> None:
    folder.mkdir()
    meta = {
        "what": "gtgen synthetic drive truth; SynthWorld(synth config) rebuilds terrain, obstacles and poses",
        "synth": cfg.synth.model_dump(mode="json"),
        "crs": cfg.synth.crs,
        "origin_e_m": cfg.synth.origin_e_m,
        "origin_n_m": cfg.synth.origin_n_m,
        "geoid_offset_m": cfg.synth.geoid_offset_m,
        "t0_ns": int(world.t_ns[0]),
        "distance_m": float(world.path.dist[-1]),
    }
    (folder / "truth.json").write_text(json.dumps(meta, indent=2, sort_keys=True))
    buf = io.BytesIO()
    np.savez(
        buf,
        t_ns=world.t_ns,
        pos_world_m=world.poses.pos,
        rpy_world_rad=world.poses.rpy,
        pos_odom_m=world.odom.p_odom,
        rpy_odom_rad=world.odom.rpy_odom,
    )
    (folder / "trajectory.npz").write_bytes(buf.getvalue())


def load_world(out: Path) -> SynthWorld:
    """Return the SynthWorld of a synth output folder (from ``truth/truth.json``)."""

    meta_path = out / "truth" / "truth.json"
    if not meta_path.is_file():
        raise GtgenError(f"'{out}' holds no synth truth (expected {meta_path})")
    from pydantic import ValidationError

    synth = json.loads(meta_path.read_text())["synth"]
    known = {k: v for k, v in synth.items() if k in SynthConfig.model_fields}
    known.setdefault("world", "easy")  # a drive made before the paper world: the easy world's keys it lacks
    if len(known) < len(synth):  # a drive made by another gtgen: keys this one has no knob for
        log.info("synth truth '%s': ignoring keys %s", meta_path, sorted(set(synth) - set(known)))
    try:
        return SynthWorld(SynthConfig.model_validate(known))
    except ValidationError as err:
        raise GtgenError(f"synth truth '{meta_path}' does not describe a drive this gtgen can rebuild: {err.errors()[0]['msg']}") from err
