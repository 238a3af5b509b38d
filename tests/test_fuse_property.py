"""The fast hindsight fusion equals the naive per-sample oracle (Hypothesis)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gtgen.fuse.fusion import FuseParams, MapSource, SampleGrid, fuse_range, naive_fuse_range
from gtgen.fuse.lattice import to_lattice


@st.composite
def scenarios(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    res = draw(st.sampled_from([0.2, 0.5, 1.0]))
    n_map = draw(st.integers(4, 14))
    n_maps = draw(st.integers(1, 25))
    rotated = draw(st.booleans())
    t_maps = np.sort(rng.integers(0, 30_000, n_maps)) * 1_000_000
    maps = []
    for t in t_maps:
        center = np.round(rng.uniform(-6, 6, 3) / res) * res
        yaw = rng.uniform(-np.pi, np.pi) if rotated else 0.0
        elev = rng.normal(0, 1, (n_map, n_map)).astype(np.float32)
        risk = rng.uniform(0, 1, (n_map, n_map)).astype(np.float32)
        conf = rng.uniform(0, 1, (n_map, n_map)).astype(np.float32)
        for a in (elev, risk, conf):
            a[rng.random(a.shape) < 0.2] = np.nan
        maps.append(to_lattice(int(t), (elev, risk, conf), center, yaw, res, res))
    src = MapSource.from_list(maps)
    window_ms = draw(st.integers(1, 20_000))
    past_ms = draw(st.sampled_from([0, 0, 2_000]))
    params = FuseParams(window_ns=window_ms * 1_000_000, past_ns=past_ms * 1_000_000, min_conf=0.1, risk_min_conf=0.5, tile=draw(st.sampled_from([4, 8, 64])),
                        elevation_rule=draw(st.sampled_from(["mean", "ground"])), top_height_m=0.5, top_footprint_m=3.0)
    n_s = draw(st.integers(1, 12))
    ts = np.sort(rng.integers(0, 30_000, n_s)) * 1_000_000
    samples = []
    for t in ts:
        cur = int(np.searchsorted(src.t_ns, t, side="right")) - 1  # latest map stamped <= t
        samples.append(SampleGrid(int(t), np.array([*rng.uniform(-5, 5, 2), rng.normal()]), float(rng.uniform(-np.pi, np.pi)), cur, draw(st.integers(3, 12)), res))
    return src, samples, params


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenarios())
def test_fast_fusion_equals_oracle(case):
    src, samples, params = case
    fast = dict(fuse_range(src, samples, params))
    slow = dict(naive_fuse_range(src, samples, params))
    assert sorted(fast) == sorted(slow) == list(range(len(samples)))
    for k in slow:
        f, o = fast[k], slow[k]
        for name in ("elevation", "confidence", "risk", "last_dt_s", "xr_elevation", "xr_risk", "xr_confidence"):
            np.testing.assert_allclose(getattr(f, name), getattr(o, name), rtol=1e-5, atol=1e-5, equal_nan=True, err_msg=name)
        np.testing.assert_array_equal(f.count, o.count)
        np.testing.assert_array_equal(f.region, o.region)
    # without the QA grids (shards.qa_ranges): none of them, every other grid bit for bit
    lean = dict(fuse_range(src, samples, replace(params, qa=False)))
    for k, f in lean.items():
        assert f.confidence is None and f.last_dt_s is None and f.xr_confidence is None
        for name in ("elevation", "risk", "count", "region", "xr_elevation", "xr_risk"):
            np.testing.assert_array_equal(getattr(f, name), getattr(fast[k], name), err_msg=name)


def test_fusion_yields_in_time_order():
    rng = np.random.default_rng(0)
    maps = [to_lattice(t, tuple(rng.uniform(0.2, 1, (6, 6)).astype(np.float32) for _ in range(3)), np.zeros(3), 0.0, 1.0, 1.0) for t in range(0, 10_000_000_000, 500_000_000)]
    src = MapSource.from_list(maps)
    samples = [SampleGrid(t, np.zeros(3), 0.0, int(np.searchsorted(src.t_ns, t, side="right")) - 1, 4, 1.0) for t in (9_000_000_000, 1_000_000_000, 5_000_000_000)]
    order = [k for k, _ in fuse_range(src, samples, FuseParams(window_ns=2_000_000_000))]
    assert order == [1, 2, 0]


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.sampled_from([0.2, 0.37, 0.8]), st.sampled_from([0.1, 0.2, 0.8]),
       st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), st.floats(-7.0, 7.0))
def test_the_lattice_index_of_a_target_grid_equals_the_meshgrid_one(size, res, lattice_res, x, y, yaw):
    """The target grid's lattice indices from a column and a row of products equal those of
    the meshgrid (its oracle) cell for cell: the same floats, so the same floor."""
    from gtgen.fuse.lattice import target_lattice_index, target_lattice_index_naive

    pos = np.array([x, y, 0.0])
    for a, b in zip(target_lattice_index(size, res, lattice_res, pos, yaw), target_lattice_index_naive(size, res, lattice_res, pos, yaw)):
        assert a.dtype == b.dtype and np.array_equal(a, b)
