"""Labels under adversity: each synth realism knob produces the failure it models, and
dem-align's decision rule rejects a constructed bad sample and keeps a good one, each
with its reason."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

from conftest import small_config
from gtgen import codes
from gtgen.config import SynthConfig
from gtgen.dem.index import TileIndex
from gtgen.dem.place import DrivePlacement, vegetation
from gtgen.dem.tiles import DemMosaic
from gtgen.geometry import quat_to_yaw, yaw_transform
from gtgen.storage.drive import DriveStore
from gtgen.storage.fused import FusedStore
from gtgen.synth.dem import altered_tiles, tile_lattice
from gtgen.synth.drive import gnss_errors, gnss_outage
from gtgen.synth.terrain import Terrain
from gtgen.synth.world import SynthWorld

T_NS = np.arange(0, 60_000_000_000, 200_000_000, dtype=np.int64)  # 60 s of 5 Hz fixes


def test_a_gnss_jump_moves_the_fixes_by_its_size_for_its_duration():
    base = SynthConfig(seed=3)
    jumped = SynthConfig(seed=3, gnss_jumps=2, gnss_jump_m=4.0, gnss_jump_s=5.0)
    d = gnss_errors(jumped, T_NS) - gnss_errors(base, T_NS)
    size = np.hypot(d[:, 0], d[:, 1])
    on = size > 1e-9
    assert on.any() and np.all((np.abs(size[on] - 4.0) < 1e-6) | (size[on] < 8.0 + 1e-6))  # 4 m, or two overlapping
    assert np.allclose(d[:, 2], 0.0)
    assert 2 * 25 - 2 <= on.sum() <= 2 * 25  # two jumps of 5 s at 5 Hz (they may overlap)


def test_a_gnss_outage_has_no_fixes_for_its_duration():
    off = gnss_outage(SynthConfig(seed=3, gnss_outages=1, gnss_outage_s=20.0), T_NS)
    assert off.sum() == 100  # 20 s at 5 Hz
    assert np.all(np.diff(np.nonzero(off)[0]) == 1)  # one stretch
    assert not gnss_outage(SynthConfig(seed=3), T_NS).any()


def test_terrain_change_is_in_the_world_not_in_the_dem_survey():
    cfg = SynthConfig(seed=2, duration_s=20, terrain_changes=1, terrain_change_m=1.5, terrain_change_radius_m=12.0)
    w = SynthWorld(cfg)
    (cu, cv), = w.changes.uv
    now = w.terrain.eval_grid(cu - 1.5, cv - 1.5, 1.0, 3, 3)["ground"]
    then = w.terrain.eval_grid(cu - 1.5, cv - 1.5, 1.0, 3, 3, surveyed=True)["ground"]
    assert float(now[1, 1] - then[1, 1]) == pytest.approx(1.5, abs=0.01)  # the patch's centre
    far = w.terrain.eval_grid(cu + 20, cv, 1.0, 3, 3)["ground"] - w.terrain.eval_grid(cu + 20, cv, 1.0, 3, 3, surveyed=True)["ground"]
    assert np.all(far == 0.0)


def test_the_shifted_and_the_wrong_tile_lie_under_the_drive():
    cfg = SynthConfig(seed=2, duration_s=60, dem_tile_m=200, dem_shifted_tile_m=3.0, dem_wrong_tile=True)
    w = SynthWorld(cfg)
    altered = altered_tiles(w)
    assert sorted(altered.values()) == sorted([(-3.0, 0.0), (0.0, 1000.0)])
    e, n = tile_lattice(w)
    utm = w.utm(w.path.uv)
    for e0, n0 in altered:
        assert e0 in e and n0 in n
        assert np.any((utm[:, 0] >= e0) & (utm[:, 0] < e0 + 200) & (utm[:, 1] >= n0) & (utm[:, 1] < n0 + 200))
    assert not altered_tiles(SynthWorld(SynthConfig(seed=2, duration_s=60, dem_tile_m=200)))


def test_canopy_and_bushes_stand_above_the_bare_ground():
    cfg = SynthConfig(seed=4, duration_s=20, canopy=True, bushes_per_ha=200, trees_per_ha=20)
    w = SynthWorld(cfg)
    assert len(w.obstacles.bush_uv) > 0
    (bu, bv), bh = w.obstacles.bush_uv[0], w.obstacles.bush_height[0]
    g = w.terrain.eval_grid(bu - 0.15, bv - 0.15, 0.1, 3, 3)
    assert float(g["surface"][1, 1] - g["ground"][1, 1]) == pytest.approx(bh, rel=0.05)
    assert isinstance(w.terrain, Terrain)


def test_vegetation_blobs_are_found_and_noise_spikes_are_not():
    rng = np.random.default_rng(0)
    d = rng.normal(0.3, 0.03, (100, 100))  # label minus DEM: an offset and noise
    d[40:48, 50:60] += 1.2  # a crown
    d[10, 10] += 2.0  # a lone spike
    veg = vegetation(d, np.ones(d.shape, bool), vegetation_m=0.4)
    assert veg[40:48, 50:60].all()
    assert not veg[10, 10]
    assert veg.sum() < 8 * 10 + 2 * (8 + 10) + 8  # the blob, grown by one cell


@pytest.fixture(scope="module")
def placed(drive_dir, drive_store, fused_store, cfg):
    """A fresh placement of the test drive, and what it needs to place sample k."""
    drive, fused = DriveStore(drive_store), FusedStore(fused_store)
    index = TileIndex.build(drive_dir / "dem")
    with contextlib.ExitStack() as stack:
        dem = stack.enter_context(DemMosaic(index, index.working_crs(-120.65, 35.6)))
        yield drive, fused, dem


def _placement(cfg, placed, drive_dir):
    drive, fused, dem = placed
    return DrivePlacement.of_drive(cfg, drive, fused, dem, drive_dir / "dem")


def _sample(placed, k):
    drive, fused, _ = placed
    s = drive.samples
    return (k, int(s.t_ns[k]), s.pos_odom_m[k], float(quat_to_yaw(s.quat_odom_xyzw[k][None])[0]),
            fused.grid("short", "region")[k], fused.grid("short", "elevation_m")[k].copy(), float(s.distance_m[k]))


def test_decision_keeps_a_good_sample_and_rejects_constructed_bad_ones(placed, drive_dir, cfg):
    k = 6
    good = _sample(placed, k)
    p = _placement(cfg, placed, drive_dir)
    for j in range(k):  # chain up to k as dem-align does
        p.place(*_sample(placed, j))
    T_prior = p.T_prior.copy()
    kept = p.place(*good)
    assert kept.reason == codes.OK, kept.signals
    assert kept.signals["disagreement"] < cfg.dem.max_disagreement

    # terrain that changed since the survey: half the observed ground 1.5 m lower
    k_, t, pos, yaw, region, elev, dist = good
    cut = elev.copy()
    obs = codes.observed(region) & np.isfinite(cut)
    half = obs & (np.arange(cut.shape[0])[:, None] < cut.shape[0] // 2)
    cut[half] -= 1.5
    p.T_prior = T_prior.copy()
    changed = p.place(k_, t, pos, yaw, region, cut, dist)
    # ICP fits the ground observed at t: half of it 1.5 m off leaves it too few inliers, or the
    # placement it finds disagrees with the rest
    assert changed.reason in (codes.LOW_FITNESS, codes.DEM_DISAGREES), changed.signals

    # a prior 6 m off (a chained placement: ICP must not silently move it that far)
    p.T_prior = T_prior.copy()
    p.T_prior[0, 3] += 6.0
    far = p.place(*good)
    assert far.reason in (codes.LARGE_CORRECTION, codes.LOW_FITNESS, codes.HIGH_RMSE, codes.DEM_DISAGREES), far.signals
    assert far.reason != codes.OK

    # GNSS that disagrees with the placement by far more than its noise
    p.T_prior = T_prior.copy()
    p.gnss_xy = p.gnss_xy.copy()
    p.gnss_xy[:, 2] += 30.0
    off = p.place(*good)
    assert off.reason == codes.GNSS_DISAGREES, off.signals


def test_a_sample_over_set_aside_tiles_is_carried_by_odometry_for_carry_over_m(placed, drive_dir, cfg):
    k = 6
    p = _placement(cfg, placed, drive_dir)
    for j in range(k):  # chain up to k as dem-align does
        p.place(*_sample(placed, j))
    T_prior, kept_at = p.T_prior.copy(), p.kept_at_m
    k_, t, pos, yaw, region, elev, dist = _sample(placed, k)
    T = T_prior @ yaw_transform(*pos, yaw)
    under = frozenset(int(i) for i in np.unique(p._tiles_at(T, codes.observed(region))) if i >= 0)
    q = p.without(under)  # every tile under the sample set aside
    q.T_prior, q.chained, q.kept_at_m = T_prior, True, kept_at
    carried = q.place(k_, t, pos, yaw, region, elev, dist)
    assert carried.reason == codes.OK and carried.icp is None, carried.signals
    np.testing.assert_allclose(carried.T_crs_target, T)  # the last kept placement, carried by odometry
    assert q.kept_at_m == kept_at and np.array_equal(q.T_prior, T_prior)  # the chain is not renewed by it
    stale = q.place(k_, t, pos, yaw, region, elev, kept_at + cfg.dem.carry_over_m + 1.0)
    assert stale.reason == codes.SUSPECT_TILE
    q.cfg = cfg.model_copy(update={"dem": cfg.dem.model_copy(update={"carry_over_m": 0.0})})
    assert q.place(k_, t, pos, yaw, region, elev, dist).reason == codes.SUSPECT_TILE


def test_canopy_cells_are_left_out_of_the_icp_source(placed, drive_dir, cfg):
    k = 6
    p = _placement(cfg, placed, drive_dir)
    for j in range(k):
        p.place(*_sample(placed, j))
    T_prior = p.T_prior.copy()
    k_, t, pos, yaw, region, elev, dist = _sample(placed, k)
    bare = p.place(k_, t, pos, yaw, region, elev, dist)
    crowns = elev.copy()
    obs = codes.observed(region) & np.isfinite(crowns)
    rng = np.random.default_rng(1)
    ii, jj = np.nonzero(obs)
    for c in rng.choice(len(ii), 60, replace=False):  # 25 crowns of 5 x 5 cells, 2-6 m tall
        crowns[ii[c] - 2 : ii[c] + 3, jj[c] - 2 : jj[c] + 3] += rng.uniform(0.6, 1.2)
    p.T_prior = T_prior
    canopy = p.place(k_, t, pos, yaw, region, crowns, dist)
    assert canopy.reason == codes.OK, canopy.signals
    assert np.abs(canopy.T_crs_target[:3, 3] - bare.T_crs_target[:3, 3]).max() < 0.05  # the crowns did not drag the fit
    assert canopy.signals["vegetation_share"] > 0.03


def test_report_confusion_on_a_kind_drive_keeps_everything_good(dataset, cfg):
    from gtgen.report.rejections import rejection_truth
    from gtgen.storage.dataset import DatasetStore
    from gtgen.synth.truth import Truth

    ds = DatasetStore(dataset)
    truth = Truth.find([b.path for b in ds.info.drives[0].bags])
    r = rejection_truth(ds, cfg, {0: truth})
    c = r["confusion"]
    assert c["kept"]["good"] == ds.n_samples and c["kept"]["bad"] == 0
    assert r["good_kept_pct"] == 100.0
    # a stricter definition of bad turns kept samples bad, and the table says so
    strict = small_config(report={"bad_horizontal_m": 0.001})
    assert rejection_truth(ds, strict, {0: truth})["confusion"]["kept"]["bad"] > 0
