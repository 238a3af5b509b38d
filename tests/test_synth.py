"""gtgen synth: determinism, readable bags, maps/cameras/DEM consistent with the truth."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli, small_config
from gtgen.bag.decode.gridmap import decode_gridmap
from gtgen.bag.reader import BagSet
from gtgen.geometry import make_transform, quat_to_matrix, rpy_to_quat
from gtgen.synth import run_synth
from gtgen.synth.camera import camera_extrinsic, camera_intrinsic
from gtgen.synth.run import load_world


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_same_seed_same_bytes_other_seed_other_drive(tmp_path):
    cfg = small_config(synth={"duration_s": 2.0, "workers": 2})
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    run_synth(cfg, a)
    run_synth(small_config(synth={"duration_s": 2.0, "workers": 1}), b)  # worker count must not matter
    run_synth(small_config(synth={"duration_s": 2.0, "seed": 1}), c)
    fa, fb, fc = _files(a), _files(b), _files(c)
    fa.pop("gtgen-config.yaml"), fb.pop("gtgen-config.yaml"), fc.pop("gtgen-config.yaml")
    fa.pop("truth/truth.json"), fb.pop("truth/truth.json")  # records the worker count
    assert fa.keys() == fb.keys() and all(fa[k] == fb[k] for k in fa)
    assert fa["drive.mcap"] != fc["drive.mcap"]


def test_the_paper_worlds_stack_errors_are_seeded_whatever_the_workers(tmp_path):
    over = {"world": "paper", "duration_s": 1.0, "formats": "mcap"}
    run_synth(small_config(synth={**over, "workers": 2}), tmp_path / "a")
    run_synth(small_config(synth={**over, "workers": 1}), tmp_path / "b")
    assert (tmp_path / "a" / "drive.mcap").read_bytes() == (tmp_path / "b" / "drive.mcap").read_bytes()


def test_bags_open_with_rosbags_and_mcap(drive_dir, cfg):
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    sc = cfg.synth
    n_odom = int(round(sc.duration_s * sc.odom_rate_hz)) + 1
    expect = {
        "/xracer/odometry": n_odom,
        "/tf": n_odom,
        "/tf_static": 1,
        "/gnss/fix": int(np.ceil(n_odom / (sc.odom_rate_hz / sc.gnss_rate_hz))),
        "/xracer/map/micro": int(np.ceil(n_odom / (sc.odom_rate_hz / sc.map_rate_hz))),
        "/xracer/map/short": int(np.ceil(n_odom / (sc.odom_rate_hz / sc.map_rate_hz))),
        "/xracer/voxel_map": int(np.ceil(n_odom / (sc.odom_rate_hz / sc.voxel_rate_hz))),
        "/cam_front/image/compressed": int(np.ceil(n_odom / (sc.odom_rate_hz / sc.camera_rate_hz))),
    }
    for bag in ("drive.mcap", "drive.bag"):
        with AnyReader([drive_dir / bag]) as r:
            counts = {c.topic: c.msgcount for c in r.connections}
            types = {c.topic: c.msgtype for c in r.connections}
            for topic, n in expect.items():
                assert counts[topic] == n, (bag, topic)
            assert types["/xracer/map/micro"] == "grid_map_msgs/msg/GridMap"
            assert types["/gnss/fix"] == "sensor_msgs/msg/NavSatFix"
            odom = [c for c in r.connections if c.topic == "/xracer/odometry"]
            stamps = [t for _, t, _ in r.messages(connections=odom)]
            assert np.allclose(np.diff(stamps), 1e9 / sc.odom_rate_hz, atol=2e6)
    with (drive_dir / "drive.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        names = {s.name for s in summary.schemas.values()}
        assert "grid_map_msgs/msg/GridMap" in names


def test_confident_map_cells_match_truth_within_noise(drive_dir, cfg):
    world = load_world(drive_dir)
    odom_t = world.t_ns
    checked = 0
    with BagSet([drive_dir / "drive.bag"]) as bags:
        for _, _, _, msg, _ in bags.messages(["/xracer/map/micro"]):
            g = decode_gridmap(msg, ["elevation", "confidence"])
            k = int(np.searchsorted(odom_t, g.stamp_ns))
            n = g.shape[0]
            c = -0.5 * n * g.resolution_m + (np.arange(n) + 0.5) * g.resolution_m
            X, Y = np.meshgrid(g.center_m[0] + c, g.center_m[1] + c, indexing="ij")
            w = world.odom.odom_to_world(k, np.stack([X, Y, np.zeros_like(X)], -1))
            truth = world.terrain.sample(w[..., 0], w[..., 1], ("ground",))[0]
            truth_odom = truth - world.poses.pos[k, 2] + world.odom.p_odom[k, 2]
            near = (g.layers["confidence"] > 0.5) & np.isfinite(g.layers["elevation"])
            err = g.layers["elevation"][near] - truth_odom[near]
            assert near.sum() > 500
            assert abs(np.median(err)) < 0.02
            assert np.std(err) < 3 * (cfg.synth.elevation_noise_m + cfg.synth.elevation_noise_per_m * 20)
            checked += 1
            if checked == 3:  # includes a message with non-zero circular-buffer start indices
                break


def test_planted_trees_appear_where_the_camera_model_projects_them(drive_dir, cfg):
    """Trees planted beside the path must be green where CameraInfo K and tf_static put them."""
    from PIL import Image

    world = load_world(drive_dir)
    K = camera_intrinsic(cfg.synth)
    ob = world.obstacles
    topics = {f"/cam_{c}/image/compressed": camera_extrinsic(c) for c in ("front", "left", "right", "back")}
    hits, checked = 0, 0
    with BagSet([drive_dir / "drive.mcap"]) as bags:
        for topic, _, _, msg, _ in bags.messages(list(topics)):
            t = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            k = int(np.searchsorted(world.t_ns, t))
            img = np.asarray(Image.open(io.BytesIO(bytes(msg.data))).convert("RGB")).astype(int)
            T_wc = make_transform(quat_to_matrix(rpy_to_quat(*world.poses.rpy[k])), world.poses.pos[k]) @ topics[topic]
            for (u, v), h, cr in zip(ob.tree_uv, ob.tree_height, ob.canopy_radius):
                if cr < 2.0:  # the renderer marches in steps of ~7% of the range
                    continue
                ground = world.terrain.sample(np.array([u]), np.array([v]), ("ground",))[0][0]
                p = np.linalg.inv(T_wc) @ np.array([u, v, ground + 0.78 * h, 1.0])
                if not 4 < p[2] < 25:
                    continue
                px = K @ (p[:3] / p[2])
                x, y = int(round(px[0])), int(round(px[1]))
                if 2 <= x < img.shape[1] - 2 and 2 <= y < img.shape[0] - 2:
                    patch = img[y - 1 : y + 2, x - 1 : x + 2].reshape(-1, 3)
                    # crown green, maybe hazed toward the sky's blue; sky has B > G, ground R > G
                    greenish = (patch[:, 1] > patch[:, 0] + 25) & (patch[:, 1] + 10 >= patch[:, 2])
                    checked += 1
                    hits += greenish.mean() >= 0.5
    assert checked >= 3, "too few trees in view to check the camera geometry"
    assert hits / checked >= 0.9, f"only {hits} of {checked} projected trees are green in the images"


def test_dem_georeferencing_roundtrips_to_truth(drive_dir, cfg):
    import rasterio
    from pyproj import Transformer

    world = load_world(drive_dir)
    tiles = sorted((drive_dir / "dem").glob("*.tif"))
    assert len(tiles) >= 2
    fwd = Transformer.from_crs(cfg.synth.crs, "EPSG:4326", always_xy=True)
    back = Transformer.from_crs("EPSG:4326", cfg.synth.crs, always_xy=True)
    with rasterio.open(tiles[0]) as ds:
        assert ds.crs.to_epsg() == 26910 and ds.nodata == -999999.0 and ds.res == (1.0, 1.0)
        band = ds.read(1)
        rows, cols = np.array([3, 100, 150]), np.array([7, 50, 190])
        E, N = rasterio.transform.xy(ds.transform, rows, cols)  # pixel centres
    lon, lat = fwd.transform(E, N)
    E2, N2 = back.transform(lon, lat)
    np.testing.assert_allclose(E2, E, atol=1e-6)
    np.testing.assert_allclose(N2, N, atol=1e-6)
    truth = world.terrain.sample(np.asarray(E) - cfg.synth.origin_e_m, np.asarray(N) - cfg.synth.origin_n_m, ("ground",))[0]
    np.testing.assert_allclose(band[rows, cols], truth, atol=5 * cfg.synth.dem_noise_m)


def test_a_dem_tile_border_crosses_the_drive(drive_dir, cfg):
    import rasterio

    world = load_world(drive_dir)
    utm = world.utm(world.path.uv)
    edges_e = set()
    for p in (drive_dir / "dem").glob("*.tif"):
        with rasterio.open(p) as ds:
            edges_e.update([ds.bounds.left, ds.bounds.right])
    inner = [e for e in edges_e if utm[:, 0].min() < e < utm[:, 0].max()]
    edges_n = set()
    for p in (drive_dir / "dem").glob("*.tif"):
        with rasterio.open(p) as ds:
            edges_n.update([ds.bounds.bottom, ds.bounds.top])
    inner += [n for n in edges_n if utm[:, 1].min() < n < utm[:, 1].max()]
    assert inner, "no tile border inside the drive's extent"


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--duration", "-3"], "Invalid value for '--duration': -3.0 is not a valid synth.duration_s"),
        (["--format", "zip"], "Invalid value for '--format': 'zip' is not a valid synth.formats: Input should be 'mcap', 'bag' or 'both'"),
    ],
)
def test_bad_arguments_one_line_error(tmp_path, args, needle):
    p = run_cli("synth", tmp_path / "o", *args)
    usage, error = p.stderr.strip().splitlines()  # a usage error: the usage line, then the error
    assert p.returncode == 2 and usage.startswith("Usage: gtgen synth") and needle in error and "Traceback" not in p.stderr
    assert not (tmp_path / "o").exists()


def test_unwritable_out(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    p = run_cli("synth", f / "sub", "--duration", "1")
    assert p.returncode != 0 and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
    ro = tmp_path / "ro"
    ro.mkdir()
    (ro / "x").write_text("occupied")
    p = run_cli("synth", ro, "--duration", "1")
    assert p.returncode != 0 and "exists and is not empty" in p.stderr


def test_fast_sampling_and_marching_equal_their_oracles(drive_dir, cfg):
    """Pooled tile sampling and block marching give the same numbers as the naive forms."""
    from gtgen.synth.camera import RenderRaster, march, march_naive

    world = load_world(drive_dir)
    terrain = world.terrain
    rng = np.random.default_rng(0)
    c = world.path.uv[len(world.path.uv) // 2]
    ang = rng.uniform(0, np.pi)
    i, j = np.meshgrid(np.arange(-150, 150) * 0.2, np.arange(-120, 120) * 0.2, indexing="ij")
    u = c[0] + np.cos(ang) * i - np.sin(ang) * j
    v = c[1] + np.sin(ang) * i + np.cos(ang) * j
    fast = terrain.sample(u, v, ("ground", "risk", "surface"))
    slow = terrain.sample_grouped(u, v, ("ground", "risk", "surface"))
    assert all(np.array_equal(a, b) for a, b in zip(fast, slow))
    # on tile nodes the bilinear sample is the exact evaluation
    g = terrain.eval_grid(c[0] - 3.0, c[1] - 3.0, 0.1, 20, 20)
    uu, vv = np.meshgrid(c[0] - 3.0 + (np.arange(20) + 0.5) * 0.1, c[1] - 3.0 + (np.arange(20) + 0.5) * 0.1, indexing="ij")
    # the grid form of the smooth ground (one matrix product of the waves) is the pointwise one
    # (its oracle), here across a ditch's line too
    pt = terrain._ditch_pt[0]
    gu, gv = pt[0] - 30 + np.arange(300) * 0.2, pt[1] - 20 + np.arange(200) * 0.2
    GU, GV = np.meshgrid(gu, gv, indexing="ij")
    assert np.abs(terrain.smooth_grid(gu, gv) - terrain.smooth(GU, GV)).max() < 1e-9
    assert np.abs(terrain.sample(uu, vv, ("ground",))[0] - g["ground"]).max() < 2e-3

    raster = RenderRaster(terrain, (c[0] - 200, c[1] - 200, c[0] + 200, c[1] + 200))
    o = np.array([200.0, 200.0, terrain.sample(np.array([c[0]]), np.array([c[1]]))[0][0] + 1.7], np.float32)
    d = rng.normal(size=(3000, 3)).astype(np.float32)
    d[:, 2] = np.abs(d[:, 2]) * rng.choice([-0.3, 0.05], 3000)  # mostly down, some above the horizon
    rays = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    k, hit = march(raster, o, rays)
    k0, hit0 = march_naive(raster, o, rays)
    assert np.array_equal(hit, hit0) and np.array_equal(k, k0)
    assert 0 < hit.sum() < len(hit)  # both hits and sky rays are exercised

    # map cells as outer sums are the cells through odom_to_world
    from gtgen.synth.sensors import map_cells_world

    grid, k = cfg.grids.get("micro"), len(world.t_ns) // 2
    cu, cv = map_cells_world(grid, world.odom.p_odom[k, :2] + 0.3, world.odom, k)
    cc = -0.5 * grid.length_m + (np.arange(grid.size) + 0.5) * grid.resolution_m
    X, Y = np.meshgrid(world.odom.p_odom[k, 0] + 0.3 + cc, world.odom.p_odom[k, 1] + 0.3 + cc, indexing="ij")
    w = world.odom.odom_to_world(k, np.stack([X, Y, np.zeros_like(X)], -1))
    np.testing.assert_allclose(cu, w[..., 0], atol=1e-9)
    np.testing.assert_allclose(cv, w[..., 1], atol=1e-9)


def _density_setup(**over):
    """A flat-ish world without obstacles but one bush, seen by the density model."""
    from gtgen.config import SynthConfig
    from gtgen.synth.sensors import lidar_view
    from gtgen.synth.terrain import Obstacles, Terrain

    sc = SynthConfig(seed=3, hill_amplitude_m=0.0, crest_amplitude_m=0.0, valley_depth_m=0.0, ditch_depth_m=0.0, **over)
    none = np.zeros(0)
    bush = Obstacles(np.zeros((0, 2)), none, none, np.zeros((0, 2)), none, none, none,
                     bush_uv=np.array([[12.0, 0.0]]), bush_radius=np.array([1.5]), bush_height=np.array([2.5]))
    t = Terrain(sc, bush)
    origin = np.array([0.0, 0.0, 240.0 + sc.lidar_height_m])
    return sc, t, lidar_view(sc, t, origin)


def _map(sc, t, view, cell_m, speed, seed=0):
    from gtgen.synth.sensors import xracer_map

    c = np.arange(-60.0, 60.0, cell_m) + cell_m / 2
    U, V = np.meshgrid(c, c, indexing="ij")
    return U, V, xracer_map(sc, t, view, (U, V), 0.0, np.random.default_rng(seed), cell_m, speed)


def test_paper_world_maps_are_confident_where_returns_are_dense():
    sc, t, view = _density_setup()
    U, V, m = _map(sc, t, view, 0.2, 6.0)
    r = np.hypot(U, V)
    conf = m.confidence > 0.1
    near, mid, far = (r > 4) & (r < 15) & (U < 0), (r > 25) & (r < 35), (r > 45) & (r < 55)
    assert conf[near].mean() > 0.9 > conf[mid].mean() > conf[far].mean()  # falls with range
    assert conf[far].mean() < 0.3
    # shadowed behind the bush (2.5 m tall, 12 m ahead): nothing confident 16-30 m behind it on its bearing
    behind = (U > 16) & (U < 30) & (np.abs(V) < 0.5)
    assert not conf[behind].any() and conf[(U < -16) & (U > -30) & (np.abs(V) < 0.5)].mean() > 0.3
    # thinner at speed; coarser cells (more returns each) confident farther out
    _, _, fast = _map(sc, t, view, 0.2, 12.0)
    assert (fast.confidence > 0.1)[mid].mean() < conf[mid].mean()
    _, _, coarse = _map(sc, t, view, 0.8, 6.0)
    rc = np.hypot(*np.meshgrid(*(np.arange(-60.0, 60.0, 0.8) + 0.4,) * 2, indexing="ij"))
    assert (coarse.confidence > 0.1)[(rc > 45) & (rc < 55)].mean() > 2 * conf[far].mean()
    # where cells are seen, they are the ground within the noise
    seen = conf & (r < 30) & (r > 3)
    assert np.abs(m.elevation[seen] - 240.0).max() < 6 * (sc.elevation_noise_m + sc.elevation_noise_per_m * 30)


def test_easy_world_stays_available_by_config():
    from gtgen.config import EASY_WORLD, SynthConfig, build_config
    from gtgen.synth.world import SynthWorld

    easy = SynthConfig(world="easy", seed=2)
    assert all(getattr(easy, k) == v for k, v in EASY_WORLD.items())
    assert SynthConfig(world="easy", trees_per_ha=9).trees_per_ha == 9  # an explicit key wins
    assert build_config({"synth": {"world": "easy"}}).synth.confidence_model == "range"
    # a later layer's world replaces an earlier one's
    assert build_config({"synth": {"world": "easy"}}, {"synth": {"world": "paper"}}).synth == SynthConfig()
    paper = SynthWorld(SynthConfig(seed=2, duration_s=20))
    old = SynthWorld(easy.model_copy(update={"duration_s": 20}))
    assert len(paper.obstacles.bush_uv) > 0 == len(old.obstacles.bush_uv)
    assert len(paper.obstacles.rock_uv) > 2 * len(old.obstacles.rock_uv)


def test_the_stacks_memory_keeps_what_it_saw_from_earlier_poses():
    """Cells only the earlier poses saw (behind the bush from here, beside the track there)
    are in the map with memory, none of them without."""
    from gtgen.synth.sensors import lidar_view, xracer_map

    sc, t, view = _density_setup()
    U, V, now = _map(sc, t, view, 0.2, 6.0)
    past = lidar_view(sc, t, np.array([23.0, 6.0, 240.0 + sc.lidar_height_m]))  # beside the shadow
    with_memory = xracer_map(sc, t, view, (U, V), 0.0, np.random.default_rng(0), 0.2, 6.0, (past,))
    behind = (U > 16) & (U < 30) & (np.abs(V) < 0.5)
    assert not (now.confidence > 0.1)[behind].any() and (with_memory.confidence > 0.1)[behind].mean() > 0.5


def test_region_shares_are_of_the_labelled_cells():
    from gtgen.report.stats import PAPER_REGION_SHARE_PCT, region_shares

    assert region_shares({"no_label": 0.5, "obs_pc": 0.1, "obs_f": 0.3, "unobs": 0.1}) == {"obs_pc": 20.0, "obs_f": 60.0, "unobs": 20.0}
    assert region_shares({"no_label": 1.0, "obs_pc": 0.0, "obs_f": 0.0, "unobs": 0.0}) == {"obs_pc": None, "obs_f": None, "unobs": None}
    assert all(abs(sum(p.values()) - 100) < 0.2 for p in PAPER_REGION_SHARE_PCT.values())


def test_the_stack_extrapolates_unseen_cells_as_a_guess_that_errs_more_farther_out():
    """A filled cell continues the seen ground along its slope (a fit that flattens toward
    the edge of what was seen), is a guess (its weight falls from 1 to 0 over the fill
    distance), reaches only stack_fill_*_m, and errs more the farther it is."""
    from gtgen.synth.sensors import extrapolate

    cell = 0.2
    c = (np.arange(200) + 0.5) * cell
    X, Y = np.meshgrid(c, c, indexing="ij")
    plane = (0.1 * X - 0.05 * Y).astype(np.float32)
    seen = X < 20.0
    filled, guess = extrapolate(np.where(seen, plane, np.nan).astype(np.float32), cell, 6.0, np.zeros(2))
    assert np.isfinite(filled[X < 25.9]).all() and np.isnan(filled[X > 26.1]).all()  # 6 m beyond what was seen
    band = {d: (X > 20 + d - 0.1) & (X < 20 + d + 0.1) & (Y > 5) & (Y < 35) for d in (0.2, 1.0, 5.0)}
    assert np.median(filled[band[5.0]]) > np.median(filled[band[1.0]]) + 0.1  # up the slope it saw
    err = np.abs(filled - plane)
    assert err[band[0.2]].mean() < 0.02 and err[band[1.0]].mean() < err[band[5.0]].mean() / 3  # errs more farther out
    assert (guess[seen] == 0).all() and 0.9 < guess[band[0.2]].min() and guess[(X > 25.6) & (X < 25.9)].max() < 0.1
    tilted, _ = extrapolate(np.where(seen, plane, np.nan).astype(np.float32), cell, 6.0, np.array([0.1, 0.0]))
    assert abs(float(np.median((tilted - filled)[band[5.0]])) - 0.5) < 0.03  # the slope error times 5 m


def test_paper_world_maps_guess_around_what_they_see_and_say_so():
    from gtgen.synth.sensors import xracer_map

    sc, t, view = _density_setup()
    U, V, held = _map(sc, t, view, 0.2, 6.0)  # no fill_m: the last ground seen along each ray is held
    filled = xracer_map(sc, t, view, (U, V), 0.0, np.random.default_rng(0), 0.2, 6.0, (), sc.stack_fill_micro_m)
    guess = np.isfinite(filled.elevation) & (filled.confidence < sc.stack_fill_confidence) & (filled.confidence > 0)
    assert guess.sum() > 1000 and (filled.risk[guess] == 0).all()
    assert (filled.confidence[np.isfinite(filled.elevation)] > 0).mean() > 0.99  # every guess says it is one
    # on flat ground a guess errs by the noise of the seen cell it continues and its slope error times its reach
    bound = sc.elevation_noise_m + sc.elevation_noise_per_m * 60 + sc.stack_fill_slope_sd * sc.stack_fill_micro_m
    assert np.abs(filled.elevation[guess] - 240.0).mean() < bound
    assert (held.confidence[np.isfinite(held.elevation)] == 0).any()  # a held cell does not say it is a guess


def test_the_stacks_registration_drifts_over_its_memory_and_the_easy_world_has_none():
    from gtgen.config import SynthConfig
    from gtgen.synth.run import stack_drift

    sc = SynthConfig(seed=4)
    d = stack_drift(sc, 20000)
    assert abs(d[:, 0].std() / sc.stack_drift_xy_m - 1) < 0.1 and abs(d[:, 2].std() / sc.stack_drift_z_m - 1) < 0.1
    assert abs(np.rad2deg(np.arctan(d[:, 3].std())) / sc.stack_drift_tilt_deg - 1) < 0.1
    memory = int(round(sc.stack_memory_s * sc.map_rate_hz))
    lag1 = np.corrcoef(d[:-1, 2], d[1:, 2])[0, 1]
    lag_mem = np.corrcoef(d[:-memory, 2], d[memory:, 2])[0, 1]
    assert lag1 > 0.9 and abs(lag_mem) < 0.1  # consecutive maps share it; a memory apart, they do not
    assert np.array_equal(d, stack_drift(sc, 20000))  # seeded
    assert stack_drift(SynthConfig(world="easy"), 100) is None


def test_a_worker_draws_each_lidar_view_once_and_the_maps_as_drawn_afresh(monkeypatch):
    """A worker of two ticks every other map; the memory's lattice views its maps share are
    drawn once (they were drawn again for almost every map), and the maps are those of a
    ticker that draws every view afresh (the oracle)."""
    from gtgen.synth import run as synth_run
    from gtgen.synth import sensors

    cfg = small_config(synth={"world": "paper", "duration_s": 8.0, "scan_rate_hz": 0})
    world = synth_run.SynthWorld(cfg.synth)
    worker, fresh = synth_run._Ticker(cfg, world, None, "mcap"), synth_run._Ticker(cfg, world, None, "mcap")
    drawn: list[tuple] = []
    real = sensors.lidar_view
    monkeypatch.setattr(sensors, "lidar_view", lambda sc, t, origin: drawn.append(tuple(origin)) or real(sc, t, origin))
    ticks = range(0, worker.n, 2 * worker.map_p)
    mine = []
    for k in ticks:
        worker._maps(mine, k, worker._view(k))
    assert len(drawn) == len(set(drawn)) and len(drawn) <= len(ticks) + len(range(0, worker.n, worker._memory_step()))
    assert worker._memory_step() > 0 and any(len(worker._memory_ticks(k, 1.0)) > 1 for k in ticks)
    for k, i in zip(ticks, range(0, len(mine), 2)):
        fresh._views.clear(), fresh._lattice.clear()
        theirs: list = []
        fresh._maps(theirs, k, fresh._view(k))
        assert theirs == mine[i:i + 2]
