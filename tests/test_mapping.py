"""Grid maps from raw lidar (gtgen.mapping): the rolling cells against a naive per-sweep
oracle, and the layers' semantics on scenes with known ground, obstacles and vegetation."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import REALDATA, needs_realdata
from gtgen.config import GridSpec, GtgenConfig, MappingConfig
from gtgen.mapping.cells import RollingCells
from gtgen.mapping.mapper import Mapper


def _cfg(**mapping) -> GtgenConfig:
    cfg = GtgenConfig()
    cfg.grids.micro = GridSpec(size=60, resolution_m=0.2)
    cfg.grids.short = GridSpec(size=30, resolution_m=0.8)
    cfg.mapping = MappingConfig(**mapping)
    return cfg


def _pose(x: float, y: float, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def naive_cells(sweeps, n: int, res: float, m: MappingConfig, t_ns: int, center, sub: int = 1) -> dict:
    """The cell statistics by the rules of gtgen.mapping.cells, cell by cell and sweep by
    sweep, in plain Python: the oracle of RollingCells (with ``sub`` x ``sub`` sub-cell tops)."""
    state: dict[tuple[int, int], dict] = {}
    for pts, rng, c, t in sweeps:
        k = np.floor(pts[:, :2] / res).astype(int)
        x0, y0 = int(np.floor(c[0] / res)) - n // 2, int(np.floor(c[1] / res)) - n // 2
        cells: dict[tuple[int, int], list[int]] = {}
        for i, (kx, ky) in enumerate(k):
            if x0 <= kx < x0 + n and y0 <= ky < y0 + n:
                cells.setdefault((int(kx), int(ky)), []).append(i)
        for key, idx in cells.items():
            slot = (key[0] % n, key[1] % n)
            s = state.get(slot)
            if s is None or s["key"] != key or t - s["t"] > m.memory_s * 1e9:
                s = {"key": key, "zmin": np.inf, "sum": 0.0, "n": 0, "top": -np.inf, "r": np.inf, "sub": {}}
            z = [float(pts[i, 2]) for i in idx]
            low = min(z)
            if low < s["zmin"] - m.ground_band_m or (low > s["zmin"] + m.ground_band_m and s["n"] < m.min_points):
                s.update(zmin=low, sum=0.0, n=0, top=-np.inf, sub={})
            else:
                s["zmin"] = min(s["zmin"], low)
            for i, zi in zip(idx, z):
                if zi <= s["zmin"] + m.ground_band_m:
                    s["sum"] += zi
                    s["n"] += 1
                if zi <= s["zmin"] + m.overhang_m:
                    s["top"] = max(s["top"], zi)
                    q = (min(int(pts[i, 0] / res * sub - key[0] * sub), sub - 1), min(int(pts[i, 1] / res * sub - key[1] * sub), sub - 1))
                    s["sub"][q] = max(s["sub"].get(q, -np.inf), zi)
            s["r"] = min(s["r"], min(float(rng[i]) for i in idx))
            s["t"] = t
            state[slot] = s
    x0, y0 = int(np.floor(center[0] / res)) - n // 2, int(np.floor(center[1] / res)) - n // 2
    ground = np.full((n, n), np.nan)
    count = np.zeros((n, n), int)
    subtop = np.full((n, n, sub * sub), -np.inf)
    for i in range(n):
        for j in range(n):
            key = (x0 + i, y0 + j)
            s = state.get((key[0] % n, key[1] % n))
            if s is None or s["key"] != key or t_ns - s["t"] > m.memory_s * 1e9:
                continue
            if s["n"] >= m.min_points:
                ground[i, j] = s["sum"] / s["n"]
                count[i, j] = s["n"]
                for (a, b), v in s["sub"].items():
                    subtop[i, j, a * sub + b] = v
    return {"ground": ground, "n": count, "subtop": subtop}


@pytest.mark.parametrize("cover", [None, 0.25, 0.15])
def test_rolling_cells_equal_the_naive_oracle_as_the_vehicle_drives_and_forgets(cover):
    rng = np.random.default_rng(3)
    m = MappingConfig(memory_s=0.35, min_points=2, cover_cell_m=cover)
    n, res = 20, 0.5
    cells = RollingCells(n, res, m)
    sub = {None: 1, 0.25: 2, 0.15: 3}[cover]
    assert cells.sub == sub
    sweeps = []
    for s in range(8):  # 0.1 s apart, 1.5 m of travel each: the ring wraps and old cells expire
        c = np.array([1.5 * s, 0.3 * s])
        pts = np.column_stack([c + rng.uniform(-7, 7, (400, 2)), rng.normal(0, 0.1, 400) + (rng.random(400) < 0.2) * rng.uniform(0, 1.5, 400)])
        r = rng.uniform(1, 30, 400).astype(np.float32)
        t = s * 100_000_000
        cells.add(pts, r, c, t)
        sweeps.append((pts, r, c, t))
    for center in (np.array([10.5, 2.1]), np.array([8.0, 1.0])):
        got = cells.crop(center, n, sweeps[-1][3])
        want = naive_cells(sweeps, n, res, m, sweeps[-1][3], center, sub)
        np.testing.assert_array_equal(got["n"], want["n"])
        np.testing.assert_allclose(got["ground"], want["ground"], atol=1e-9)
        if sub > 1:
            np.testing.assert_allclose(got["subtop"], want["subtop"], atol=1e-6)
            assert np.isfinite(want["subtop"]).sum() > 200 and np.isinf(want["subtop"][np.isfinite(want["ground"])]).any()
        else:
            assert "subtop" not in got
        assert np.isfinite(want["ground"]).sum() > 50  # the test sees cells, old ones forgotten
        assert (want["n"] == 0).sum() > 50


def _scene(rng, n_sweeps=5):
    """Points of a flat ground at z = 0 with: a 0.6 m box (a rock) at x in [3, 4], a bush
    0.8 m tall whose leaves let some beams through at x in [-4, -3], and branches 4 m up
    at y in [3, 4] (an overhang); and the vehicle's own body."""
    pts = []
    for _ in range(n_sweeps):
        g = np.column_stack([rng.uniform(-6, 6, (6000, 2)), rng.normal(0, 0.01, 6000)])
        rock = g[:, 0] > 3
        rock &= g[:, 0] < 4
        g[rock, 2] += 0.6
        bush = np.column_stack([rng.uniform(-4, -3, (800, 1)), rng.uniform(-1, 1, (800, 1)), rng.uniform(0, 0.8, (800, 1))])
        branches = np.column_stack([rng.uniform(-6, 6, (500, 1)), rng.uniform(3, 4, (500, 1)), 4 + rng.normal(0, 0.05, (500, 1))])
        body = np.column_stack([rng.uniform(-2, 2, (300, 1)), rng.uniform(-1, 1, (300, 1)), rng.uniform(0.5, 2, (300, 1))])
        pts.append(np.vstack([g, bush, branches, body]))
    return pts


def test_layers_hold_ground_under_vegetation_and_flag_obstacles_not_overhangs():
    cfg = _cfg()
    mp = Mapper(cfg, ranges=("micro",))
    rng = np.random.default_rng(0)
    for s, pts in enumerate(_scene(rng)):
        mp.add(pts, np.array([0.0, 0.0, 2.0]), _pose(0, 0), s * 100_000_000)
    lay = mp.map("micro", np.zeros(2), 4 * 100_000_000)
    c = -0.5 * 60 * 0.2 + (np.arange(60) + 0.5) * 0.2 + lay.center[0]
    X, Y = np.meshgrid(c, c - lay.center[0] + lay.center[1], indexing="ij")
    seen = np.isfinite(lay.elevation)
    bare = seen & (np.abs(X) < 2.5) & (Y < -1.5) & (Y > -2.8)
    rock = seen & (X > 3.3) & (X < 3.7) & (np.abs(Y) < 1)
    bush = seen & (X > -3.8) & (X < -3.2) & (np.abs(Y) < 0.8)
    under = seen & (Y > 3.2) & (Y < 3.8) & (np.abs(X) < 2)
    body = (np.abs(X) < 1.8) & (np.abs(Y) < 0.8)
    assert bare.sum() > 50 and rock.sum() > 5 and bush.sum() > 5 and under.sum() > 10
    assert np.abs(lay.elevation[bare]).max() < 0.05
    assert lay.risk[bare].max() < 0.5
    assert np.abs(lay.elevation[rock] - 0.6).max() < 0.05  # the rock is ground, standing out as a step
    assert lay.risk[rock].min() >= 0.5 and lay.risk[(X > 3.05) & (X < 3.15) & (np.abs(Y) < 1) & seen].min() >= 0.5  # to its edge
    assert lay.risk[(X > 2.85) & (X < 2.95) & (np.abs(Y) < 1) & seen].max() < 0.5  # the ground below the edge is not
    assert np.abs(lay.elevation[bush]).max() < 0.1  # ground under the bush ...
    assert np.median(lay.top[bush]) > 0.6 and lay.risk[bush].min() >= 0.5  # ... and the bush an obstacle
    assert np.abs(lay.elevation[under]).max() < 0.05 and lay.risk[under].max() < 0.5  # branches overhead: no obstacle
    assert np.isnan(lay.top[body]).all()  # the body's points are masked out (the ground under it with them)
    assert lay.confidence.min() >= 0 and lay.confidence.max() <= 1
    assert (lay.confidence[~seen] == 0).all() and np.isnan(lay.risk[~seen]).all()


def test_confidence_falls_with_range_and_age():
    cfg = _cfg()
    mp = Mapper(cfg, ranges=("short",))
    rng = np.random.default_rng(1)
    g = np.column_stack([rng.uniform(-12, 12, (40000, 2)), np.zeros(40000)])
    mp.add(g, np.array([0.0, 0.0, 2.0]), _pose(0, 0), 0)
    fresh = mp.map("short", np.zeros(2), 0).confidence
    old = mp.map("short", np.zeros(2), 4_000_000_000).confidence
    c = -12 + (np.arange(30) + 0.5) * 0.8
    r = np.hypot(*np.meshgrid(c, c, indexing="ij"))
    near, far = fresh[(r > 3) & (r < 5)], fresh[(r > 9) & (r < 11)]
    assert near.mean() > far.mean() > 0
    assert np.all(old <= fresh) and old.max() < fresh.max() * 0.7


def test_sweeps_out_of_order_are_refused():
    mp = Mapper(_cfg(), ranges=("micro",))
    mp.add(np.zeros((1, 3)) + 5, np.zeros(3), _pose(0, 0), 10)
    with pytest.raises(ValueError, match="time order"):
        mp.add(np.zeros((1, 3)) + 5, np.zeros(3), _pose(0, 0), 5)


def test_body_box_must_be_low_below_high():
    with pytest.raises(ValueError, match="body_x_m"):
        MappingConfig(body_x_m=(1.0, -1.0))


@pytest.fixture(scope="module")
def lidar_only_bag(drive_dir, tmp_path_factory):
    """The small drive as a robot without a stack records it: its lidar's points (the stack's
    voxel map stands in for the sweeps here, in odom, which TF connects) on a raw-scan
    topic, and no GridMaps or voxel map."""
    from bagtools import rewrite

    def edit(topic, t, msg):
        if topic.startswith("/xracer/map/"):
            return []
        if topic == "/xracer/voxel_map":
            return [(t, msg)]
        return [(t, msg)]

    out = tmp_path_factory.mktemp("lidar_only") / "drive.mcap"
    rewrite(drive_dir / "drive.mcap", out, edit)
    return out


def _lidar_cfg(cfg):
    c = cfg.model_copy(deep=True)
    c.topics.map_micro = None
    c.topics.map_short = None
    c.topics.voxel_map = None
    c.topics.lidar = ["/xracer/voxel_map"]
    return c


def test_extract_maps_from_lidar_when_no_stack_publishes_maps(lidar_only_bag, drive_store, cfg, tmp_path):
    from gtgen.extract import run_extract
    from gtgen.storage.drive import DriveStore

    c = _lidar_cfg(cfg)
    res = run_extract([lidar_only_bag], tmp_path / "drive.zarr", c, workers=1)
    assert res.n_samples > 0
    got, ref = DriveStore(tmp_path / "drive.zarr"), DriveStore(drive_store)
    assert got.n_samples >= 0.8 * ref.n_samples
    for r in ("micro", "short"):
        m = got.maps(r)
        assert len(m) > 0
        e, risk, conf = m.layers(len(m) // 2)
        assert np.isfinite(e).mean() > 0.05 and 0 <= np.nanmin(risk) and np.nanmax(risk) <= 1
        assert conf.min() >= 0 and conf.max() <= 1
    assert got.voxel_counts().min() > 0  # no sample before the first scan


def test_a_lidar_made_map_needs_a_raw_scan_topic(drive_dir, cfg, tmp_path):
    from gtgen.errors import TopicError
    from gtgen.extract import run_extract

    c = _lidar_cfg(cfg)
    c.topics.lidar = ["/no/such/points"]
    with pytest.raises(TopicError, match=r"topics.map_micro, topics.map_short, topics.voxel_map null .*PointCloud2 topics found: \['/xracer/voxel_map'\]"):
        run_extract([drive_dir / "drive.mcap"], tmp_path / "d.zarr", c, workers=1)


@needs_realdata()
def test_a_real_hdl64_scan_maps_with_its_ground_blind_ring_and_walls():
    """One Velodyne HDL-64E scan (x, y, z, intensity, ring and padding; no TF): the sensor
    near (429.1, -1226.2), its roof about 3.1 m above the frame's zero and 1.9 m above the
    ground (the points within 3 m are the car itself, at the roof's height)."""
    from gtgen.bag.decode.pointcloud import decode_pointcloud
    from gtgen.bag.reader import BagSet
    from gtgen.mapping.mapper import map_scan

    with BagSet([REALDATA / "swri_hdl64_single_scan.bag"]) as bags:
        msg = next(m for _, _, _, m, _ in bags.messages(["/pointcloud2"]) if m is not None)
    pts = decode_pointcloud(msg)
    assert pts.shape == (124914, 3)
    lay = map_scan(pts, np.array([429.1, -1226.2, -3.1]), 1.9, GtgenConfig())["micro"]
    c = (np.arange(500) + 0.5) * 0.2 - 50 + lay.center[0] - 429.1
    r = np.hypot(c[:, None], ((np.arange(500) + 0.5) * 0.2 - 50 + lay.center[1] + 1226.2)[None, :])
    seen = np.isfinite(lay.elevation)
    assert not seen[r < 3].any()  # the blind ring (and the car, masked out)
    ring = seen & (r > 5) & (r < 10)
    assert ring.sum() > 300
    assert np.abs(np.median(lay.elevation[ring]) + 5.0) < 0.2  # the ground, 1.9 m under the sensor
    assert (lay.risk[ring] < 0.5).mean() > 0.9  # ground is safe ...
    assert (lay.risk[seen & (r > 10)] >= 0.5).sum() > 50  # ... walls and vegetation farther out are not


def test_voxel_memory_holds_the_voxels_of_the_last_memory_s_in_the_window():
    from gtgen.mapping.voxels import VoxelMemory

    rng = np.random.default_rng(5)
    vm = VoxelMemory(0.5, 0.25, 6.0)
    sweeps = []
    for s in range(30):  # the window moves 0.4 m a sweep, points expire after 0.25 s
        c = np.array([0.4 * s, 0.0])
        p = np.column_stack([c + rng.uniform(-8, 8, (300, 2)), rng.uniform(-1, 2, 300)])
        t = s * 100_000_000
        vm.add(p, c, t)
        sweeps.append((p, c, t))
    c, t = sweeps[-1][1], sweeps[-1][2]
    want = set()
    for p, cs, ts in sweeps:
        if t - ts <= 250_000_000:
            near = np.all(np.abs(p[:, :2] - cs) < 6.0, axis=1)
            for k in np.floor(p[near] / 0.5).astype(int):
                centre = (k + 0.5) * 0.5
                if np.all(np.abs(centre[:2] - c) < 6.0):
                    want.add(tuple(k))
    got = {tuple(k) for k in np.floor(vm.points(t, c) / 0.5).astype(int)}
    assert got == want and len(want) > 300


@pytest.mark.parametrize("res", [0.2, 0.8])
def test_a_smooth_slope_is_slope_not_step_or_roughness_at_any_cell_size(res):
    from gtgen.mapping.layers import geometry

    x = (np.arange(40) + 0.5) * res
    g = np.tan(np.radians(20.0)) * x[:, None] + 0.0 * x[None, :]
    geo = geometry(g, res, 3)
    assert np.allclose(geo["slope"][1:-1, 1:-1], 20.0, atol=0.01)
    assert geo["step"][1:-1, 1:-1].max() < 1e-5 and geo["roughness"][1:-1, 1:-1].max() < 1e-5
    g[20, 20] += 0.5  # a 0.5 m block: a step on its higher side only (the block), whatever the slope
    geo = geometry(g, res, 3)
    assert geo["step"][20, 20] > 0.45 and geo["step"][19, 20] < 0.1 and geo["step"][10, 10] < 1e-5


def test_geometry_equals_its_cell_by_cell_oracle():
    from gtgen.mapping.layers import geometry, geometry_naive

    rng = np.random.default_rng(2)
    g = rng.normal(0, 0.2, (14, 12)) + 0.3 * np.arange(14)[:, None] * 0.4
    g[rng.random(g.shape) < 0.2] = np.nan
    fast, slow = geometry(g, 0.4, 3), geometry_naive(g, 0.4, 3)
    for name in ("slope", "roughness", "step", "rise"):
        np.testing.assert_allclose(fast[name], slow[name], atol=2e-4, err_msg=name)


@pytest.mark.parametrize("res", [0.2, 0.8])
def test_a_steep_smooth_slope_is_not_an_obstacle_and_a_bush_on_it_is(res):
    """A 25 deg slope (below mapping.max_slope_deg) whose cells' points span what the slope
    climbs across a cell: not fatal at either cell size (at 0.8 m cells the span, 0.37 m,
    exceeded the 0.3 m clearance and the whole hillside read fatal); a 0.5 m bush on it is."""
    from gtgen.config import MappingConfig
    from gtgen.mapping.layers import layers

    cfg = MappingConfig()
    x = (np.arange(40) + 0.5) * res
    ground = np.tan(np.radians(25.0)) * x[:, None] + 0.0 * x[None, :]
    top = ground + np.tan(np.radians(25.0)) * res  # the cell's highest point: its far edge
    top[20, 20] += 0.5
    n = np.full(ground.shape, 50.0)
    lay = layers({"ground": ground, "top": top, "n": n, "range": np.zeros_like(n), "age_s": np.zeros_like(n)}, cfg, res, np.zeros(2))
    inner = np.ones(ground.shape, bool)
    inner[[0, -1], :] = inner[:, [0, -1]] = False
    inner[20, 20] = False
    assert lay.risk[inner].max() < 0.5, lay.risk[inner].max()
    assert lay.risk[20, 20] >= 0.5


def _old_rule_risk(ground: np.ndarray, top: np.ndarray, cfg, res: float) -> np.ndarray:
    """The risk of gtgen before issue 38 (the oracle of the ring): step, slope and roughness of
    the cells' own ground, the step measured both ways (the lower side of a rock's edge too)."""
    from gtgen.mapping.layers import geometry, neighbourhood_cells

    k = neighbourhood_cells(cfg, res)
    up, down = geometry(ground, res, k), geometry(-ground, res, k)  # a step down is a step up of -ground
    height = np.maximum(top - ground - up["rise"], 0.0)
    ratio = np.fmax.reduce([np.fmax(up["step"], down["step"]) / cfg.max_step_m, up["slope"] / cfg.max_slope_deg,
                            up["roughness"] / cfg.max_roughness_m, height / cfg.clearance_m])
    return np.clip(0.5 * ratio, 0.0, 1.0)


@pytest.mark.parametrize("res", [0.2, 0.8])
def test_a_box_on_a_slope_is_fatal_and_the_ground_around_it_is_not(res):
    """A box (1 m, or one 0.8 m cell) standing 0.5 m on a 15 deg slope with 2 cm noise: its cells fatal, the ring
    of cells around it not (the old two-sided step flagged that ring), nor the slope."""
    from scipy import ndimage

    from gtgen.config import MappingConfig
    from gtgen.mapping.layers import layers

    cfg = MappingConfig()
    rng = np.random.default_rng(38)
    n = int(round(8.0 / res))
    x = (np.arange(n) + 0.5) * res
    ground = np.tan(np.radians(15.0)) * x[:, None] + 0.0 * x[None, :] + rng.normal(0, 0.02, (n, n))
    near = np.abs(x - x[n // 2]) < 0.45  # 1 m at 0.2 m cells, one cell at 0.8 m
    box = near[:, None] & near[None, :]
    ground[box] += 0.5
    top = ground + np.tan(np.radians(15.0)) * res
    ground[0, 0] = np.nan  # a cell without ground stays without risk
    cells = {"ground": ground, "top": top, "n": np.full((n, n), 50.0), "range": np.zeros((n, n)), "age_s": np.zeros((n, n))}
    lay = layers(cells, cfg, res, np.zeros(2))
    ring = ndimage.binary_dilation(box, np.ones((3, 3), bool)) & ~box
    rest = ~box & ~ring & np.isfinite(ground)
    assert box.sum() >= 1 and ring.sum() >= 8
    assert lay.risk[box].min() >= 0.5
    assert lay.risk[ring].max() < 0.5, lay.risk[ring].max()
    assert lay.risk[rest].max() < 0.5 and np.isnan(lay.risk[0, 0])
    old = _old_rule_risk(ground, top, cfg, res)
    assert (old[ring] >= 0.5).mean() > 0.5  # the ring the old rule made (and a wide box's middle it missed)


def test_half_cover_top_equals_its_cell_by_cell_oracle():
    from gtgen.mapping.layers import half_cover_top, half_cover_top_naive

    rng = np.random.default_rng(5)
    sub = rng.normal(0, 1, (9, 7, 16)).astype(np.float32)
    sub[rng.random(sub.shape) < 0.4] = -np.inf
    sub[0, 0] = -np.inf  # a cell none of whose sub-cells is seen
    sub[1, 1, 1:] = -np.inf  # one seen: its top
    np.testing.assert_array_equal(half_cover_top(sub), half_cover_top_naive(sub))
    assert np.isnan(half_cover_top(sub)[0, 0]) and half_cover_top(sub)[1, 1] == sub[1, 1, 0]


@pytest.mark.parametrize("cover", [0.2, None])
def test_a_coarse_cell_is_an_obstacle_when_it_covers_half_of_it_not_its_corner(cover):
    """A 1 m tall bush over x, y in [0.2, 2.6) m, seen from above with beams through its
    leaves to the ground, on 0.8 m cells (cell k spans [0.8 k, 0.8 k + 0.8)): the cells it
    covers wholly or 9 of 16 sub-cells of are fatal; the cells whose edge column (4 of 16) or
    corner (1 of 16) it covers are not, by the cover of their 0.2 m sub-cells. With
    cover_cell_m null (the cell's highest point, the oracle of the change) they read fatal."""
    from gtgen.mapping.layers import layers

    m = MappingConfig(cover_cell_m=cover)
    rng = np.random.default_rng(38)
    g = rng.uniform(-8, 8, (60000, 2))
    bush = (g[:, 0] >= 0.2) & (g[:, 0] < 2.6) & (g[:, 1] >= 0.2) & (g[:, 1] < 2.6)
    z = rng.normal(0, 0.01, len(g)) + np.where(bush, 1.0, 0.0)
    under = np.column_stack([rng.uniform(0.2, 2.6, (2000, 2)), rng.normal(0, 0.01, 2000)])  # beams through the leaves
    pts = np.vstack([np.column_stack([g, z]), under])
    cells = RollingCells(20, 0.8, m)
    cells.add(pts, np.full(len(pts), 5.0, np.float32), np.zeros(2), 0)
    lay = layers(cells.crop(np.zeros(2), 20, 0), m, 0.8, np.zeros(2))

    def risk(kx: int, ky: int) -> float:  # cell (kx, ky) of odom; the crop's lowest cell is -10
        return lay.risk[kx + 10, ky + 10]

    assert risk(1, 1) >= 0.5 and risk(0, 0) >= 0.5  # wholly; [0.2, 0.8)^2 of [0, 0.8)^2
    assert risk(-3, -3) < 0.5 and risk(5, 1) < 0.5  # the ground away from it
    if cover is None:
        assert risk(3, 1) >= 0.5 and risk(3, 3) >= 0.5  # the highest point: any corner of a bush
    else:
        assert risk(3, 1) < 0.5 and risk(3, 3) < 0.5  # its edge column, its corner
