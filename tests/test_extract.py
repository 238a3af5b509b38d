"""gtgen extract: every bag flavour, real recordings, and bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from bagtools import rewrite_mcap
from conftest import REALDATA, SMALL, needs_realdata, run_cli, small_config
from gtgen.bag.decode.gridmap import decode_gridmap
from gtgen.bag.reader import BagSet
from gtgen.errors import BagError, DecodeError, GtgenError, InputNotFoundError, StoreError, TopicError
from gtgen.extract import run_extract
from gtgen.runtime.output import Temporaries, partials
from gtgen.storage.drive import DriveStore
from gtgen.storage.schema import DRIVE


# -- real recordings ----------------------------------------------------------------------
@needs_realdata()
def test_real_gridmap_decodes_with_header_in_info():
    with BagSet([REALDATA / "anybotics_grid_map_demo.bag"]) as b:
        (_, _, t_rec, msg, err), = list(b.messages(["/grid_map"]))
    g = decode_gridmap(msg)
    assert err is None and g.frame_id == "map" and g.shape == (40, 120)
    assert int(np.isfinite(g.layers["elevation"]).sum()) == 906 and g.layers["elevation"].size == 4800
    assert 2016 == 1970 + g.stamp_ns // (365.2425 * 86400 * 10**9)  # header stamp in 2016
    assert t_rec > 4 * 10**18  # record time in 2100: header stamps are the data time


@needs_realdata()
def test_real_gridmap_layout_matches_grid_map_convention():
    """grid_map index (0, 0) is the +x/+y corner: after decoding, the finite cells of the
    demo map must sit on the same side as in grid_map's own column-major buffer."""
    with BagSet([REALDATA / "anybotics_grid_map_demo.bag"]) as b:
        (_, _, _, msg, _), = list(b.messages(["/grid_map"]))
    raw = np.asarray(msg.data[0].data).reshape((40, 120), order="F")
    g = decode_gridmap(msg)
    np.testing.assert_array_equal(np.isfinite(g.layers["elevation"]), np.isfinite(raw[::-1, ::-1]))


@needs_realdata()
def test_real_gnss_track_decodes():
    with BagSet([REALDATA / "robot_localization_test1.bag"]) as b:
        fixes = [m for _, _, _, m, _ in b.messages(["/fix"])]
    assert len(fixes) == 989
    lat = np.array([f.latitude for f in fixes])
    lon = np.array([f.longitude for f in fixes])
    assert 42.3 < lat.mean() < 42.4 and -71.25 < lon.mean() < -71.1  # Watertown, MA
    assert fixes[0].header.frame_id == "/gps" and np.isfinite([f.altitude for f in fixes]).all()


@needs_realdata()
def test_real_camera_info_ros1_field_names():
    with BagSet([REALDATA / "ubiquity_fiducials_aruco_images.bag"]) as b:
        infos = [m for t, _, _, m, _ in b.messages([t for t, i in b.topics().items() if i.msgtype.endswith("CameraInfo")])]
    assert len(infos) == 15
    ci = infos[0]
    assert (ci.width, ci.height, ci.distortion_model) == (1280, 960, "plumb_bob")
    K = np.asarray(ci.K).reshape(3, 3)
    assert K[0, 0] > 100 and K[2, 2] == 1 and len(ci.D) >= 4 and len(ci.P) == 12 and len(ci.R) == 9


@needs_realdata()
def test_real_empty_gridmap_is_reported_not_crashed(tmp_path):
    with BagSet([REALDATA / "anybotics_grid_map_ros_test_multitopic"]) as b:
        (_, _, _, msg, _), = list(b.messages(["/grid_map"]))
    with pytest.raises(DecodeError, match=r"GridMap has layers \[\]"):
        decode_gridmap(msg, ["elevation"])
    p = run_cli("extract", REALDATA / "anybotics_grid_map_ros_test_multitopic", "-o", tmp_path / "d.zarr")
    assert p.returncode == 1 and "role 'map.micro'" in p.stderr and "Traceback" not in p.stderr
    assert "['/grid_map']" in p.stderr  # names the GridMap topic the bag does have


# -- synthetic drives ------------------------------------------------------------------------
def test_extract_store_contents(drive_store, cfg):
    g = DriveStore(drive_store).group
    S = g["samples/t_ns"].shape[0]
    assert S > 10
    assert g["samples/jpeg"].shape == (S, 4, 3 * 48 * 30)
    vi, n = g["samples/voxel_index"][:], g["voxel_maps/n_points"][:]
    V, P = g["voxel_maps/points_odom_m"].shape[:2]
    assert np.all(np.diff(vi) >= 0) and set(vi.tolist()) == set(range(V)) and np.all((n > 0) & (n <= P))
    assert np.all(np.diff(g["voxel_maps/t_ns"][:]) > 0)
    pts = g["voxel_maps/points_odom_m"][int(vi[3])]
    assert np.isfinite(pts[: n[vi[3]]]).all() and np.isnan(pts[n[vi[3]] :]).all()
    d = g["samples/distance_m"][:]
    assert np.all(np.diff(d) > 0.5 * cfg.extract.stride_m)
    # intrinsics rescaled from 64 x 40 to 48 x 30
    K = g["calib/K"][0]
    assert abs(K[0, 2] - ((31.5 + 0.5) * 0.75 - 0.5)) < 1e-9
    rep = g.attrs["report"]
    assert rep["n_samples"] == S and {t["role"] for t in rep["topics"]} >= {"map.micro", "odometry", "gnss"}
    for r in ("micro", "short"):
        t = g[f"maps/{r}/t_ns"][:]
        assert np.all(np.diff(t) > 0)
        cur = g[f"samples/map_index_{r}"][:]
        ts = g["samples/t_ns"][:]
        assert np.all(t[cur] <= ts) and np.all(ts - t[cur] <= cfg.extract.map_skew_s * 1e9)


def test_ros1_and_ros2_bags_give_the_same_store(drive_dir, drive_store, cfg, tmp_path):
    out = tmp_path / "from_bag.zarr"
    run_extract([drive_dir / "drive.bag"], out, cfg, workers=1)
    a, b = DriveStore(drive_store).group, DriveStore(out).group
    for name in ("samples/t_ns", "samples/pos_odom_m", "maps/micro/t_ns", "gnss/lat_deg", "voxel_maps/points_odom_m", "samples/T_base_cam"):
        np.testing.assert_array_equal(a[name][:], b[name][:], err_msg=name)
    np.testing.assert_array_equal(a["maps/micro/elevation_m"][3], b["maps/micro/elevation_m"][3])
    np.testing.assert_array_equal(a["samples/jpeg"][2], b["samples/jpeg"][2])


def test_circular_buffer_maps_decode_to_the_same_grid(drive_dir):
    """Maps published with non-zero start indices land on the odom lattice like the others."""
    seen = set()
    with BagSet([drive_dir / "drive.mcap"]) as b:
        prev = None
        for _, _, _, msg, _ in b.messages(["/xracer/map/short"]):
            g = decode_gridmap(msg, ["elevation", "confidence"])
            shifted = bool(msg.outer_start_index or msg.inner_start_index)
            seen.add(shifted)
            if prev is not None:
                # consecutive maps overlap: the same odom cell has nearly the same height
                d = np.round((g.center_m - prev.center_m)[:2] / g.resolution_m).astype(int)
                a = prev.layers["elevation"][max(d[0], 0):, max(d[1], 0):]
                bb = g.layers["elevation"][max(-d[0], 0):, max(-d[1], 0):]
                n = min(a.shape[0], bb.shape[0]), min(a.shape[1], bb.shape[1])
                ca = prev.layers["confidence"][max(d[0], 0):, max(d[1], 0):][: n[0], : n[1]]
                cb = g.layers["confidence"][max(-d[0], 0):, max(-d[1], 0):][: n[0], : n[1]]
                both = (ca > 0.5) & (cb > 0.5)
                assert np.median(np.abs(a[: n[0], : n[1]][both] - bb[: n[0], : n[1]][both])) < 0.1
            prev = g
    assert seen == {True, False}


# -- bad input ----------------------------------------------------------------------------------
@pytest.mark.parametrize("make, err, needle", [
    (lambda d, t: t / "missing.mcap", InputNotFoundError, "does not exist"),
    (lambda d, t: _zero(t / "empty.mcap"), BagError, "empty (0 bytes)"),
    (lambda d, t: _truncate(d / "drive.mcap", t / "cut.mcap", 300), BagError, "truncated inside its header or first chunk"),
    (lambda d, t: _truncate(d / "drive.bag", t / "cut.bag", 300), BagError, "truncated inside its header or first chunk"),
    (lambda d, t: _zero(t / "x.txt"), BagError, "suffix '.txt'"),
])
def test_bad_bags_raise_clear_errors(drive_dir, tmp_path, cfg, make, err, needle):
    path = make(drive_dir, tmp_path)
    out = tmp_path / "d.zarr"
    with pytest.raises(err, match=needle.replace("(", r"\(").replace(")", r"\)")) as exc:
        run_extract([path], out, cfg, workers=1)
    assert "\n" not in str(exc.value)
    assert not out.exists() and not partials(out)


def _zero(p):
    p.write_bytes(b"")
    return p


def _truncate(src, dst, n=None):
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * 0.4) if n is None else n])
    return dst


def test_missing_topic_names_role_and_candidates(drive_dir, tmp_path):
    cfg = small_config(topics={"map_micro": "/elevation_mapping/map"})
    with pytest.raises(TopicError) as exc:
        run_extract([drive_dir / "drive.mcap"], tmp_path / "d.zarr", cfg, workers=1)
    msg = str(exc.value)
    assert "role 'map.micro'" in msg and "/elevation_mapping/map" in msg and "/xracer/map/micro" in msg


def test_unknown_layer_names(drive_dir, tmp_path):
    cfg = small_config(topics={"layers": {"elevation": "height"}})
    with pytest.raises(GtgenError) as exc:
        run_extract([drive_dir / "drive.mcap"], tmp_path / "d.zarr", cfg, workers=1)
    assert "height" in str(exc.value) and "elevation" in str(exc.value)
    assert not (tmp_path / "d.zarr").exists()


def test_out_of_order_and_duplicate_odometry(drive_dir, drive_store, cfg, tmp_path):
    def edit(topic, t, msg):
        if topic == "/xracer/odometry":
            k = (msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec) // 20_000_000
            if k % 7 == 0:
                yield t, msg
                yield t, msg  # duplicate stamp
                return
            if k % 11 == 0:
                yield t + 60_000_000, msg  # recorded late: out of order
                return
        yield t, msg

    bag = rewrite_mcap(drive_dir / "drive.mcap", tmp_path / "messy.mcap", edit)
    res = run_extract([bag], tmp_path / "m.zarr", cfg, workers=1)
    assert any("duplicate" in w for w in res.warnings)
    a, b = DriveStore(drive_store).group, DriveStore(tmp_path / "m.zarr").group
    np.testing.assert_array_equal(a["poses/t_ns"][:], b["poses/t_ns"][:])
    np.testing.assert_array_equal(a["samples/t_ns"][:], b["samples/t_ns"][:])


def test_odometry_gap_rejects_samples_with_reason(drive_dir, cfg, tmp_path):
    t0 = None

    def edit(topic, t, msg):
        nonlocal t0
        t0 = t if t0 is None else t0
        if topic == "/xracer/odometry" and 3e9 < t - t0 < 4.5e9:
            return
        yield t, msg

    bag = rewrite_mcap(drive_dir / "drive.mcap", tmp_path / "gap.mcap", edit)
    res = run_extract([bag], tmp_path / "g.zarr", cfg, workers=1)
    assert res.rejected.get("no_pose", 0) >= 1
    assert any("gaps" in w for w in res.warnings)
    g = DriveStore(tmp_path / "g.zarr").group
    t = g["samples/t_ns"][:]
    assert not np.any((t - t0 > 3.05e9) & (t - t0 < 4.45e9))


def test_all_nan_maps_are_not_used(drive_dir, cfg, tmp_path):
    count = {"n": 0}

    def edit(topic, t, msg):
        if topic == "/xracer/map/micro":
            count["n"] += 1
            if count["n"] % 2 == 0:
                for arr in msg.data:
                    arr.data = np.full_like(arr.data, np.nan)
        yield t, msg

    bag = rewrite_mcap(drive_dir / "drive.mcap", tmp_path / "nan.mcap", edit)
    res = run_extract([bag], tmp_path / "n.zarr", cfg, workers=1)
    micro = next(s for s in res.topics if s["role"] == "map.micro")
    assert "all-NaN" in micro["first_error"]
    g = DriveStore(tmp_path / "n.zarr").group
    conf = g["maps/micro/confidence"]
    assert all(np.nanmax(conf[i]) > 0 for i in range(conf.shape[0]))


def test_failed_extract_leaves_no_store_a_later_stage_accepts(drive_dir, tmp_path, cfg):
    out = tmp_path / "d.zarr"
    with Temporaries(out) as temps:  # a run that did not finish (killed: its partial store stays)
        left = temps.name("partial")
        zarr.open_group(str(left), mode="w").attrs["store"] = "gtgen-drive"
        with pytest.raises(StoreError, match=f"did not finish left only '{left.name}'"):
            DriveStore(out)
    zarr.open_group(str(out), mode="w").attrs.update({"store": "gtgen-drive", "version": DRIVE.version, "complete": False})
    with pytest.raises(StoreError, match="incomplete"):
        DriveStore(out)
    zarr.open_group(str(out), mode="w").attrs.update({"store": "gtgen-drive", "version": 0, "complete": True})
    with pytest.raises(StoreError, match="version 0"):
        DriveStore(out)


def test_cli_extract_summary_and_missing_file(drive_dir, tmp_path):
    p = run_cli("extract", drive_dir / "drive.mcap", "--workers", "1", "-c", SMALL, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "samples kept" in p.stdout and "/xracer/map/micro" in p.stdout
    assert (tmp_path / "gtgen_ws" / "drive.zarr").is_dir()  # the workspace default
    p = run_cli("extract", tmp_path / "nope.mcap", cwd=tmp_path)
    assert p.returncode == 1 and p.stderr.strip() == f"error: bag '{tmp_path / 'nope.mcap'}' does not exist"


def test_store_does_not_depend_on_workers_or_slices(drive_dir, drive_store, cfg, tmp_path):
    """Record-time slices on a process pool give the very arrays of one in-process pass."""
    one, many, ref = tmp_path / "one.zarr", tmp_path / "many.zarr", tmp_path / "ref.zarr"
    assert run_extract([drive_dir / "drive.mcap"], one, cfg, workers=1, n_slices=1).reread == 0
    run_extract([drive_dir / "drive.mcap"], many, cfg, workers=1, n_slices=7)
    run_extract([drive_dir / "drive.mcap"], ref, cfg, workers=1, n_slices=3, staging=False)  # two passes
    _assert_same_arrays(ref, one, many, drive_store)  # drive_store: 2 workers


def _arrays(path):
    return {k: v[...] for k, v in zarr.open_group(str(path), mode="r").members(max_depth=None) if isinstance(v, zarr.Array)}


def _assert_same_arrays(ref, *others):
    a = _arrays(ref)
    assert len(a) > 20
    for other in others:
        b = _arrays(other)
        assert a.keys() == b.keys()
        for k in a:
            assert np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), k


def test_single_pass_reads_again_what_no_slice_staged(drive_dir, cfg, tmp_path):
    """Maps recorded 3 s after their stamps: a slice meets maps whose frames the slice
    before it held, so its guesses miss; a targeted second pass reads those maps and the
    store equals the two-pass reference."""
    late = rewrite_mcap(drive_dir / "drive.mcap", tmp_path / "late.mcap",
                        lambda topic, t, msg: [(t + 3_000_000_000 if "/map/" in topic else t, msg)])
    a, ref = tmp_path / "a.zarr", tmp_path / "ref.zarr"
    res = run_extract([late], a, cfg, workers=1, n_slices=4)
    run_extract([late], ref, cfg, workers=1, n_slices=4, staging=False)
    assert 0 < res.reread < (4 * res.n_samples + sum(res.maps_kept.values())) / 2  # most still staged
    _assert_same_arrays(ref, a)


# -- the direct MCAP chunk reader against the mcap library (the oracle) ---------------------------
def test_voxel_maps_in_base_link_are_placed_by_the_pose_track(drive_dir, drive_store, cfg, tmp_path):
    """Voxel maps published in base_link are staged raw and moved to odom once the pose
    track is known: the same points as the odom-frame original, staged or read twice."""
    import dataclasses

    from gtgen.bag.decode.pointcloud import decode_pointcloud
    from gtgen.bag.poses import PoseTrack
    from gtgen.bag.reader import stamp_ns

    g = DriveStore(drive_store).group
    track = PoseTrack(g["poses/t_ns"][:], g["poses/pos_odom_m"][:], g["poses/quat_odom_xyzw"][:], 10**8)

    def to_base(topic, t, msg):
        if topic != cfg.topics.voxel_map:
            return [(t, msg)]
        T = track.transforms(np.array([stamp_ns(msg.header)]))[0]
        pts = ((decode_pointcloud(msg).astype(np.float64) - T[:3, 3]) @ T[:3, :3]).astype(np.float32)
        hdr = dataclasses.replace(msg.header, frame_id=cfg.topics.base_frame)
        return [(t, dataclasses.replace(msg, header=hdr, width=len(pts), height=1, row_step=12 * len(pts),
                                        data=np.frombuffer(pts.tobytes(), np.uint8)))]

    bag = rewrite_mcap(drive_dir / "drive.mcap", tmp_path / "base.mcap", to_base)
    staged, ref = tmp_path / "staged.zarr", tmp_path / "ref.zarr"
    run_extract([bag], staged, cfg, workers=1, n_slices=3)
    run_extract([bag], ref, cfg, workers=1, n_slices=3, staging=False)
    _assert_same_arrays(ref, staged)
    a, b = DriveStore(staged).group, g
    np.testing.assert_array_equal(a["voxel_maps/n_points"][:], b["voxel_maps/n_points"][:])
    np.testing.assert_allclose(a["voxel_maps/points_odom_m"][:], b["voxel_maps/points_odom_m"][:], atol=2e-3)


@pytest.mark.parametrize("name", ["drive.mcap", "drive.bag"])
def test_truncated_bag_at_seeded_offsets_never_a_traceback_or_a_hang(drive_dir, tmp_path, cfg, name):
    """A bag cut anywhere (10 seeded offsets per flavour) gives a store with its per-topic
    report or a one-line gtgen error; a watchdog turns a hang into a failure."""
    import signal

    data = (drive_dir / name).read_bytes()
    offsets = np.sort(np.random.default_rng(20).integers(1, len(data), 10))

    def hang(*_):
        raise TimeoutError("extract hung on a truncated bag")

    old = signal.signal(signal.SIGALRM, hang)
    try:
        for i, cut in enumerate(offsets):
            bag = tmp_path / f"cut_{i}{Path(name).suffix}"
            bag.write_bytes(data[:cut])
            signal.alarm(120)
            try:
                res = run_extract([bag], tmp_path / f"d{i}.zarr", cfg, workers=1)
                assert res.n_samples > 0 and all("decode_failures" in t for t in res.topics)
            except GtgenError as err:
                assert "\n" not in str(err) and str(err), (cut, err)
            finally:
                signal.alarm(0)
            bag.unlink()
    finally:
        signal.signal(signal.SIGALRM, old)


@pytest.fixture(scope="module")
def bag_store(drive_dir, tmp_path_factory, cfg):
    out = tmp_path_factory.mktemp("bag") / "drive.zarr"
    run_extract([drive_dir / "drive.bag"], out, cfg, workers=1)
    return out


@pytest.mark.parametrize("name", ["drive.mcap", "drive.bag"])
def test_a_bag_cut_short_gives_the_first_samples_of_the_whole_drive(drive_dir, drive_store, bag_store, tmp_path, cfg, name):
    """Cut at 5 seeded offsets after the first chunk (other offsets per format): extract
    succeeds, reports the lost bytes, and every sample whose data all lie before the cut
    equals the whole drive's."""
    from gtgen.bag.mcap import McapFile
    from gtgen.bag.rosbag1 import Ros1File

    full_path = drive_dir / name
    whole = (McapFile if name.endswith(".mcap") else Ros1File).open(full_path)
    first = min(c.offset + c.length for c in whole.chunks)
    data = full_path.read_bytes()
    full = DriveStore(drive_store if name.endswith(".mcap") else bag_store).group
    ft = full["samples/t_ns"][:]
    tol = int(cfg.extract.pose_tolerance_s * 1e9)
    needed = np.max(np.column_stack([
        full["samples/image_t_ns"][:].max(axis=1), full["samples/voxel_t_ns"][:], ft + tol,
        full["maps/micro/t_ns"][:][full["samples/map_index_micro"][:]] + 100_000_000,  # maps are recorded after their stamp
        full["maps/short/t_ns"][:][full["samples/map_index_short"][:]] + 100_000_000,
    ]), axis=1)
    checked = 0
    for cut in np.random.default_rng(10 + name.endswith(".bag")).integers(first + 1, len(data), 5):
        bag = tmp_path / f"cut{Path(name).suffix}"
        bag.write_bytes(data[:cut])
        with BagSet([bag]) as bags:
            t_last = bags.time_range()[1] - 1
        res = run_extract([bag], tmp_path / "cut.zarr", cfg, workers=1)
        assert any("cut short" in w for w in res.warnings)
        g = DriveStore(tmp_path / "cut.zarr").group
        gt = g["samples/t_ns"][:]
        safe = np.nonzero(needed < t_last)[0]
        assert np.isin(ft[safe], gt).all(), (cut, len(safe), len(gt))
        assert (gt[~np.isin(gt, ft)] > t_last - 1_000_000_000).all()  # a sample the whole drive lacks: only at the cut
        for k in safe:
            j = int(np.nonzero(gt == ft[k])[0][0])
            np.testing.assert_array_equal(g["samples/jpeg"][j], full["samples/jpeg"][k])
            np.testing.assert_array_equal(g["samples/pos_odom_m"][j], full["samples/pos_odom_m"][k])
            for r in ("micro", "short"):
                np.testing.assert_array_equal(g[f"maps/{r}/elevation_m"][int(g[f"samples/map_index_{r}"][j])],
                                              full[f"maps/{r}/elevation_m"][int(full[f"samples/map_index_{r}"][k])])
            v, w = int(g["samples/voxel_index"][j]), int(full["samples/voxel_index"][k])
            np.testing.assert_array_equal(g["voxel_maps/points_odom_m"][v], full["voxel_maps/points_odom_m"][w])
        checked += len(safe)
        shutil.rmtree(tmp_path / "cut.zarr")
    assert checked > len(ft)  # most cuts leave many samples to compare
