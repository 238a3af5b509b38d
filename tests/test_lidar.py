"""Raw lidar scans: the real HDL-64E cloud decoded and staged, synthetic scans against the
true terrain, the drive store's compact rows, the N-scan input against an independent
accumulation, and a training step on it."""

from __future__ import annotations

import statistics
import struct
from pathlib import Path

import numpy as np
import pytest

from conftest import REALDATA, needs_realdata, shared, small_config
from test_train import SMALL_TRAIN

HDL64 = REALDATA / "swri_hdl64_single_scan.bag"
SCANS = {"synth": {"scan_rate_hz": 5.0, "duration_s": 8}}


@pytest.fixture(scope="module")
def scan_cfg():
    return small_config(**SCANS)


@pytest.fixture(scope="session")
def scan_dataset(tmp_path_factory) -> Path:
    """A small drive with raw scans, through synth, extract, fuse and dem-align (read only:
    one copy for both xdist workers)."""
    from gtgen.dataset.dem_align import run_dem_align
    from gtgen.extract import run_extract
    from gtgen.fuse.run import run_fuse
    from gtgen.synth import run_synth

    def build(base: Path) -> None:
        cfg = small_config(**SCANS)
        run_synth(cfg, base / "drive")
        run_extract([base / "drive" / "drive.mcap"], base / "drive.zarr", cfg, workers=1)
        run_fuse(base / "drive.zarr", base / "fused.zarr", cfg, workers=1)
        run_dem_align(base / "drive.zarr", base / "fused.zarr", None, base / "dataset.zarr", cfg, workers=1)

    return shared(tmp_path_factory, "lidar/scans", build)


# -- the real HDL-64E scan ------------------------------------------------------------
@needs_realdata()
def test_real_hdl64_cloud_decodes_and_stages(tmp_path):
    """x, y, z, intensity, ring and 8 bytes of padding in 32-byte points: the decoder reads x,
    y, z at their offsets (oracle: struct.unpack of single points), and the extract pass
    stages it as a lidar scan, in int16 cm about its median (the frame is map-like)."""
    from numcodecs import Zstd

    from gtgen.bag.decode.pointcloud import decode_scan
    from gtgen.bag.reader import BagSet
    from gtgen.extract.lidar import expand
    from gtgen.extract.scan import scan_messages
    from gtgen.extract.stage import Stager

    cfg = small_config(topics={"lidar": ["/pointcloud2"]}, extract={"max_scan_points": 131072})
    with BagSet([HDL64]) as bags:
        msg = next(m for _, _, _, m, _ in bags.messages(["/pointcloud2"]))
        assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "ring"] and msg.point_step == 32
        pts, dt = decode_scan(msg)
        assert pts.shape == (124914, 3) and dt is None
        raw = bytes(msg.data)
        for i in (0, 1, 4000, 124913):
            np.testing.assert_array_equal(pts[i], struct.unpack_from("<3f", raw, 32 * i))
        with Stager(str(tmp_path), 0, cfg, "camera.front") as stager:
            scan = scan_messages(bags.records(["/pointcloud2"], None, None), cfg, {"/pointcloud2": "lidar.0"}, stager)
    assert scan.stats["/pointcloud2"].decode_failures == 0 and scan.frames["lidar.0"] == "near_field"
    n, shift = stager.result.scans[("lidar.0", 0)]
    assert n == len(pts) and np.abs(shift - np.median(pts, axis=0)).max() < 0.01
    row = np.frombuffer(Zstd().decode(stager.result.chunk("lidar.0", 0).read_bytes()), "<i2").reshape(131072, 3)
    assert np.abs(expand(row, n) + shift - pts).max() <= 0.005 + 1e-4  # to the cm
    assert np.ptp(pts[:, 0]) > 150  # a real 360-degree scan, not a toy


def test_decoder_rows_padding_and_time(tmp_path):
    """Organised clouds with padded rows, a per-point time field, and a bad one."""
    from types import SimpleNamespace as NS

    from gtgen.bag.decode.pointcloud import decode_scan
    from gtgen.errors import DecodeError

    dt = np.dtype({"names": ["x", "y", "z", "time"], "formats": ["<f4"] * 4, "offsets": [0, 4, 8, 16], "itemsize": 24})
    a = np.zeros((2, 3), dt)
    a["x"], a["y"], a["z"], a["time"] = np.arange(6).reshape(2, 3), 1.0, np.nan, 0.05
    a["z"][0] = 2.0
    rows = [a[i].tobytes() + b"\xff" * 8 for i in range(2)]  # 8 bytes past each row's points
    fields = [NS(name=n, offset=o, datatype=7, count=1) for n, o in zip(dt.names, (0, 4, 8, 16))]
    msg = NS(fields=fields, is_bigendian=False, width=3, height=2, point_step=24, row_step=80, data=np.frombuffer(b"".join(rows), np.uint8),
             header=NS(stamp=NS(sec=1, nanosec=0)))
    pts, t = decode_scan(msg)
    np.testing.assert_array_equal(pts, [[0, 1, 2], [1, 1, 2], [2, 1, 2]])  # row 1's NaN z dropped
    np.testing.assert_allclose(t, 0.05)
    with pytest.raises(DecodeError, match="data bytes"):
        decode_scan(NS(**{**msg.__dict__, "data": msg.data[:100]}))


def test_deskew_undoes_the_sensor_motion():
    """A sensor moving at 10 m/s along x sees a fixed wall: each point measured at its own
    time, motion-corrected to the stamp, lands where the wall was at the stamp."""
    from gtgen.bag.poses import PoseTrack
    from gtgen.bag.tf import TfBuffer
    from gtgen.extract.lidar import deskew

    t = np.arange(0, 11) * 20_000_000
    track = PoseTrack(t, np.column_stack([10.0 * t * 1e-9, np.zeros(11), np.zeros(11)]), np.tile([0, 0, 0, 1.0], (11, 1)))
    tf = TfBuffer({}, {("odom", "lidar"): track})
    dt = np.linspace(0, 0.1, 500).astype(np.float32)
    wall = np.column_stack([np.full(500, 20.0), np.linspace(-5, 5, 500), np.zeros(500)])  # in odom
    seen = (wall - np.column_stack([10.0 * dt, np.zeros(500), np.zeros(500)])).astype(np.float32)  # in the moving sensor
    fixed = deskew(seen, dt, tf, "odom", "lidar", 0)
    assert np.abs(fixed - wall).max() < 10.0 * 0.1 / 32 + 1e-3  # one time bin of motion at most
    assert np.abs(seen - wall).max() > 0.9


# -- synthetic scans ------------------------------------------------------------------
def test_synthetic_scans_hit_the_true_terrain_within_their_noise(drive_dir, cfg):
    """Noise-free casts lie on the world's true surface (its 0.1 m bilinear layers) to
    within the render raster's 0.25 m cells (99% within 5 cm on open ground); published returns differ from them along the
    ray by the range noise, with the configured dropouts; obstacles are hit too."""
    from gtgen.geometry import make_transform, quat_to_matrix, rpy_to_quat
    from gtgen.synth import lidar
    from gtgen.synth.camera import RenderRaster
    from gtgen.synth.run import load_world

    world = load_world(drive_dir)
    sc = cfg.synth.model_copy(update={"scan_beams": 32, "scan_azimuth_deg": 1.0, "scan_noise_m": 0.05, "scan_dropout": 0.1})
    raster = RenderRaster(world.terrain, world.bounds)
    k = len(world.t_ns) // 2
    q = rpy_to_quat(*world.poses.rpy[k])
    T = make_transform(quat_to_matrix(q), world.poses.pos[k]) @ lidar.T_base_lidar("front_tilted")
    rays, ring = lidar.beam_rays(sc)
    assert rays.shape == (32 * 360, 3) and set(ring.tolist()) == set(range(32))
    hits = lidar.cast(raster, T, rays, sc.scan_range_m)
    ok = np.isfinite(hits.range_m)
    assert ok.mean() > 0.5
    P = T[:3, 3] + hits.range_m[ok, None] * (rays[ok] @ T[:3, :3].T)
    ground, surface = world.terrain.sample(P[:, 0], P[:, 1], ("ground", "surface"))
    dz = P[:, 2] - surface
    # on open ground (by the world's layers and the raster's): a hit on the side of a crown's
    # or rock's 0.25 m raster column lies where the finer layers have ground already
    bare = (surface - ground < 0.01) & ~hits.obstacle[ok]
    assert bare.mean() > 0.8 and np.median(np.abs(dz[bare])) < 0.02 and np.percentile(np.abs(dz[bare]), 99) < 0.05
    assert (hits.obstacle[ok] & (surface - ground > 0.3)).any()  # trees, rocks or bushes
    # the shared-profile cast against marching each ray alone (the oracle)
    naive = lidar.cast_naive(raster, T, rays, sc.scan_range_m)
    both = ok & np.isfinite(naive.range_m)
    assert np.mean(ok == np.isfinite(naive.range_m)) > 0.97
    # the same hit to the mm for 90% of the rays; the rest cross the raster's 0.25 m staircase
    # at another step of the same cell or two (both on the surface)
    e = np.abs(hits.range_m[both] - naive.range_m[both])
    assert np.mean(e < 0.01) > 0.85 and np.mean(e < 0.5) > 0.98
    pts = lidar.scan_points(sc, raster, T, np.random.default_rng(0))
    assert abs(len(pts) / ok.sum() - (1 - sc.scan_dropout)) < 0.03
    xyz = np.column_stack([pts["x"], pts["y"], pts["z"]]).astype(np.float64)
    # each return on its ray: the published range minus the exact one is the noise
    idx = {(int(r), round(float(a), 3)): i for i, (r, a) in enumerate(zip(ring, np.arctan2(rays[:, 1], rays[:, 0])))}
    which = np.array([idx[(int(r), round(float(a), 3))] for r, a in zip(pts["ring"], np.arctan2(xyz[:, 1], xyz[:, 0]))])
    err = np.linalg.norm(xyz, axis=1) - hits.range_m[which]
    assert abs(err.std() - sc.scan_noise_m) < 0.2 * sc.scan_noise_m and abs(err.mean()) < 0.01


# -- drive store and the N-scan input -----------------------------------------------
def test_extract_stores_compact_scans_with_their_poses(scan_dataset, scan_cfg):
    """Three lidars' scans, kept at least shards.scan_travel_m apart (and each sample's
    newest), as int16 cm rows with their sensor's pose; a few bytes a point on disk."""
    from gtgen.extract.lidar import FILL
    from gtgen.storage.drive import DriveStore
    from gtgen.synth import lidar
    from gtgen.synth.run import load_world

    d = DriveStore(scan_dataset / "drive.zarr")
    s = d.scans
    assert sorted(set(s.lidar.tolist())) == [0, 1, 2] and len(s) > 20
    for lid in range(3):
        sel = s.lidar == lid
        assert np.all(np.diff(s.t_ns[sel]) > 0)
    rows = d.scan_rows(np.arange(3))
    for j in range(3):
        assert (rows[j, : s.n_points[j]] != FILL).all() and (rows[j, s.n_points[j] :] == FILL).all()
    # the stored pose is the mount on the odometry pose at the stamp
    poses = d.poses()
    i = int(np.searchsorted(poses.t_ns, s.t_ns[0]))
    from gtgen.geometry import make_transform, quat_to_matrix

    T = make_transform(quat_to_matrix(poses.quat_odom_xyzw[i]), poses.pos_odom_m[i]) @ lidar.T_base_lidar("front")
    np.testing.assert_allclose(s.T_odom_sensor[0], T, atol=1e-6)
    files = list((scan_dataset / "drive.zarr" / "scans" / "points_cm").glob("c.*"))
    per_point = sum(f.stat().st_size for f in files) / s.n_points.sum()
    assert len(files) == len(s) and per_point < 6.0  # below the 6 raw bytes of int16 xyz
    assert load_world(scan_dataset / "drive") is not None


def _oracle(d, cfg, k):
    """The N-scan input of drive sample k, accumulated naively: chains by a loop over
    scans, each point transformed alone, a dict as the voxel filter."""
    from gtgen.geometry import quat_to_yaw

    s, sh = d.scans, cfg.shards
    t, pos = int(d.samples.t_ns[k]), d.samples.pos_odom_m[k]
    yaw = float(quat_to_yaw(d.samples.quat_odom_xyzw[k]))
    chain = {}
    for lid in sorted(set(s.lidar.tolist())):
        mine = [i for i in range(len(s)) if s.lidar[i] == lid and s.t_ns[i] <= t]
        picked = []
        all_t = sorted(int(s.t_ns[i]) for i in range(len(s)) if s.lidar[i] == lid)
        periods = [b - a for a, b in zip(all_t, all_t[1:])]
        allowed = max(cfg.extract.scan_skew_s * 1e9, 2 * statistics.median(periods) if periods else 0)  # two periods
        if mine and t - s.t_ns[mine[-1]] <= allowed:
            picked = [mine[-1]]
            for i in reversed(mine):
                if len(picked) == sh.max_scans:
                    break
                if s.distance_m[i] <= s.distance_m[picked[-1]] - sh.scan_travel_m and i < picked[-1]:
                    picked.append(i)
        chain[lid] = picked
    c, sn = np.cos(yaw), np.sin(yaw)
    seen, pts, ages = set(), [], []
    half = cfg.grids.short.length_m / 2
    for a in range(sh.max_scans):
        for lid in sorted(chain):
            if a >= len(chain[lid]):
                continue
            i = chain[lid][a]
            T = s.T_odom_sensor[i]
            for p in d.scan_rows(np.array([i]))[0, : s.n_points[i]].astype(np.float64) * 0.01:
                q = T[:3, :3] @ p + T[:3, 3] - pos
                x, y = c * q[0] + sn * q[1], -sn * q[0] + c * q[1]
                if abs(x) >= half or abs(y) >= half:
                    continue
                key = tuple(int(v) for v in np.floor(np.array([x, y, q[2]]) / sh.scan_voxel_m))
                if key not in seen and len(pts) < sh.max_scan_points:
                    seen.add(key)
                    pts.append((x, y, q[2]))
                    ages.append(a)
    counts = [sum(1 for g in ages if g <= a) for a in range(sh.max_scans)]
    return np.array(pts), np.array(counts), chain


def test_n_scan_input_equals_an_independent_accumulation(scan_dataset, scan_cfg):
    from gtgen.storage import schema as sc
    from gtgen.storage.dataset import DatasetStore
    from gtgen.storage.drive import DriveStore

    d = DriveStore(scan_dataset / "drive.zarr")
    ds = DatasetStore(scan_dataset / "dataset.zarr")
    assert ds.has_scans and ds.scan_dims == (scan_cfg.shards.max_scan_points, scan_cfg.shards.max_scans)
    for spec in sc.SCAN_ARRAYS:  # as documented: one row per sample, sharded
        a = ds.array(spec.path)
        assert a.dtype == np.dtype(spec.dtype) and a.chunks[0] == 1 and a.shards[0] == sc.SAMPLES_PER_SHARD, spec.path
    t_ds = ds.meta("t_ns")
    pts_r, counts_r = ds.scan_input()
    for j in sorted({0, len(t_ds) // 2, len(t_ds) - 1}):
        k = int(np.searchsorted(d.samples.t_ns, t_ds[j]))
        want, counts, chain = _oracle(d, scan_cfg, k)
        assert max(len(c) for c in chain.values()) == (scan_cfg.shards.max_scans if j else 1)  # the first sample has no past
        got = pts_r[j]
        np.testing.assert_array_equal(counts_r[j], counts)
        n = counts[-1]
        np.testing.assert_allclose(got[:n], want, atol=2e-4 + scan_cfg.shards.precision.points_m / 2)  # stored at 1 cm steps
        assert np.isnan(got[n:]).all()


def test_train_step_and_experiments_plan_on_scans(scan_dataset, tmp_path):
    """geometry: scans trains a step (the loader's points are the last n scans' prefix), and
    gtgen experiments plans Tab. III's N-scan rows on a dataset with scans."""
    from gtgen.config import load_config
    from gtgen.storage.dataset import DatasetStore
    from gtgen.train.data import ShardDataset
    from gtgen.train.experiments import _plan
    from gtgen.train.trainer import train

    path = scan_dataset / "dataset.zarr"
    cfg = load_config(None, SMALL_TRAIN, {"train": {"geometry": "scans", "n_scans": 2}})
    res = train(path, tmp_path / "run", cfg, max_steps=1)
    assert res.steps == 1 and np.isfinite(res.last_loss)
    ds = ShardDataset(path, cfg.train)
    x = ds[ds.indices.tolist().index(len(ds) - 1)] if len(ds) else None
    assert x is not None
    store = DatasetStore(path)
    pts, counts = store.scan_input()
    k = int(x["index"])
    assert int(x["n_points"]) == counts[k][1]
    np.testing.assert_array_equal(x["points"][: counts[k][1]].numpy(), pts[k][: counts[k][1]])
    from gtgen.errors import TrainError

    with pytest.raises(TrainError, match="stores the last 4 scans"):
        ShardDataset(path, load_config(None, SMALL_TRAIN, {"train": {"geometry": "scans", "n_scans": 5}}).train)
    plan = _plan(store.has_scans, ("III",))
    assert not plan.skipped and any(r.startswith("scans-") for r in plan.needed)


@needs_realdata()
def test_extract_reads_the_real_hdl64_scan_beside_a_drive(drive_dir, drive_store, cfg, tmp_path):
    """The real cloud (x, y, z, intensity, ring and 8 bytes of padding a point, bytes as
    recorded) re-stamped at a sample time of the session drive, in a second bag of the
    drive with a static TF base_link -> near_field: extract stores all its points, and put
    back in odom through the stored pose they are the cloud through TF, to the cm."""
    from gtgen.bag.messages import MessageFactory, open_mcap_writer
    from gtgen.bag.reader import BagSet
    from gtgen.extract import run_extract
    from gtgen.extract.lidar import expand
    from gtgen.geometry import make_transform, quat_to_matrix
    from gtgen.storage.drive import DriveStore

    with BagSet([HDL64]) as bags:
        msg = next(m for _, _, _, m, _ in bags.messages(["/pointcloud2"]))
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "ring"], "formats": ["<f4", "<f4", "<f4", "<f4", "<u2"],
                   "offsets": [0, 4, 8, 16, 20], "itemsize": 32})
    raw = np.frombuffer(bytes(msg.data), dt)
    cloud = np.column_stack([raw["x"], raw["y"], raw["z"]]).astype(np.float64)
    samples = DriveStore(drive_store).samples
    k = len(samples) // 2
    t = int(samples.t_ns[k])
    fac = MessageFactory(ros1=False)
    w = open_mcap_writer(tmp_path / "ros2")
    pc = w.add_connection("/pointcloud2", "sensor_msgs/msg/PointCloud2", typestore=fac.store)
    out_msg = fac.pointcloud(t, "near_field", raw, 0)
    assert bytes(out_msg.data) == bytes(msg.data)  # padding bytes and all
    w.write(pc, t, fac.serialize(out_msg, "sensor_msgs/msg/PointCloud2"))
    st = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=fac.store)
    p_bn, q_bn = np.array([-429.1, 1226.2, -1.0]), np.array([0.0, 0.0, np.sin(0.2), np.cos(0.2)])
    w.write(st, int(samples.t_ns[0]), fac.serialize(fac.tf_message([fac.transform_stamped(int(samples.t_ns[0]), "base_link", "near_field", p_bn, q_bn)]),
                                                   "tf2_msgs/msg/TFMessage"))
    w.close()
    extra = next((tmp_path / "ros2").glob("*.mcap"))
    c = cfg.model_copy(update={"topics": cfg.topics.model_copy(update={"lidar": ["/pointcloud2"]}),
                               "extract": cfg.extract.model_copy(update={"max_scan_points": 131072})})
    run_extract([drive_dir / "drive.mcap", extra], tmp_path / "drive.zarr", c, workers=1)
    d = DriveStore(tmp_path / "drive.zarr")
    s = d.scans
    assert len(s) == 1 and s.t_ns[0] == t and s.n_points[0] == len(cloud) == 124914
    T_odom_base = make_transform(quat_to_matrix(samples.quat_odom_xyzw[k]), samples.pos_odom_m[k])
    want = cloud @ (T_odom_base @ make_transform(quat_to_matrix(q_bn), p_bn))[:3, :3].T + (T_odom_base @ make_transform(quat_to_matrix(q_bn), p_bn))[:3, 3]
    T = s.T_odom_sensor[0]
    got = expand(d.scan_rows(np.array([0]))[0], int(s.n_points[0])) @ T[:3, :3].T + T[:3, 3]
    assert np.abs(got - want).max() < 0.01


def test_a_lidar_slower_than_the_skew_gives_every_sample_its_latest_scan():
    """A 2 Hz lidar (period 0.5 s, longer than extract.scan_skew_s 0.2 s): every sample gets
    its latest scan whatever its phase; a lidar that stopped gives none (before, 40 % of the
    demo's samples, those more than 0.2 s after a scan, had an empty N-scan input)."""
    from gtgen.dataset.scans import chains
    from gtgen.storage.drive import Scans

    t = np.arange(0, 10_000_000_000, 500_000_000, dtype=np.int64)  # 0 .. 9.5 s
    t = np.concatenate([t[:12], t[16:]])  # a 2.5 s gap after 5.5 s
    scans = Scans(t, np.zeros(len(t), np.uint8), np.ones(len(t), np.int64), t / 1e9 * 8.0, np.tile(np.eye(4), (len(t), 1, 1)))
    samples = np.array([0.1, 0.49, 2.3, 4.99, 6.3, 7.2, 9.9]) * 1e9
    got = chains(scans, samples.astype(np.int64), 3, 2.0, 200_000_000)[:, 0, 0]
    newest = np.searchsorted(t, samples, side="right") - 1
    assert (got[[0, 1, 2, 3, 4, 6]] == newest[[0, 1, 2, 3, 4, 6]]).all(), got  # 6.3 s: 0.8 s old, within two periods
    assert got[5] == -1  # 7.2 s: the newest scan is 1.7 s old, in the gap


def test_first_per_voxel_by_hashing_equals_the_sorting_oracle():
    """The N-scan input's voxel filter (pandas' hash of the voxel keys) keeps the same
    points in the same order as np.unique's sort, negative coordinates and ties included."""
    from gtgen.dataset.scans import first_per_voxel, first_per_voxel_naive

    rng = np.random.default_rng(7)
    pts = np.concatenate([rng.uniform(-90, 90, (20000, 3)), rng.uniform(-1, 1, (5000, 3))])
    pts[::7] = pts[3]  # many copies of one point: the first stays
    for voxel in (0.1, 0.4, 3.0):
        got = first_per_voxel(pts, voxel)
        np.testing.assert_array_equal(got, first_per_voxel_naive(pts, voxel))
        assert got.dtype == np.int64 and 0 < len(got) < len(pts)
    assert len(first_per_voxel(np.zeros((0, 3)), 0.2)) == 0
