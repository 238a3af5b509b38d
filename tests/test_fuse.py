"""gtgen fuse: pinned geometry, averaging beats a single map, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import run_cli
from gtgen.errors import StoreError
from gtgen.fuse.fusion import FuseParams, MapSource, SampleGrid, fuse_range
from gtgen.fuse.lattice import to_lattice
from gtgen.fuse.run import run_fuse
from gtgen.storage.fused import FusedStore


@pytest.mark.parametrize("res, size", [(0.2, 500), (0.8, 250)])
@pytest.mark.parametrize("yaw", [0.0, 0.5, np.pi / 2, -2.5, np.pi])
def test_obstacle_at_known_point_lands_in_documented_cell(res, size, yaw):
    """An obstacle at odom point P appears at the cell SPEC section 3 documents."""
    P = np.array([12.3, -7.9])
    pos = np.array([2.0, 3.0, 0.5])
    n = 200
    center = np.round(P / res) * res  # a map centred near P, on the lattice
    elev = np.zeros((n, n), np.float32)
    risk = np.zeros((n, n), np.float32)
    conf = np.ones((n, n), np.float32)
    c = center - 0.5 * n * res
    i, j = int(np.floor((P[0] - c[0]) / res)), int(np.floor((P[1] - c[1]) / res))
    risk[i - 1 : i + 2, j - 1 : j + 2] = 1.0  # a 3 x 3 cell obstacle around P
    m = to_lattice(0, (elev, risk, conf), np.array([*center, 0.0]), 0.0, res, res)
    s = SampleGrid(0, pos, yaw, 0, size, res)
    (_, f), = list(fuse_range(MapSource.from_list([m]), [s], FuseParams(window_ns=10**9)))
    q = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]]) @ (P - pos[:2])
    L = size * res
    ti, tj = int(np.floor((q[0] + L / 2) / res)), int(np.floor((q[1] + L / 2) / res))
    assert f.risk[ti, tj] == 1.0
    far = np.argwhere(f.risk == 1.0)
    assert np.abs(far - [ti, tj]).max() <= 3  # nothing lands elsewhere
    assert f.region[ti, tj] == 1 and f.elevation[ti, tj] == pytest.approx(-0.5)


@pytest.mark.parametrize("rule, crown", [("mean", 2.406), ("ground", 0.0)])
def test_elevation_rule_under_a_crown(rule, crown):
    """A crown (4 m, 2 m wide) seen from afar in 3 maps and the ground under it in 2: the
    paper's mean mixes them (2.4 m), rule ground keeps the ground; a rock (0.6 m) seen in
    every map is kept by both rules."""
    res, n = 0.2, 60
    maps = []
    for t in range(5):
        elev = np.zeros((n, n), np.float32)
        if t < 3:
            elev[20:30, 20:30] = 4.0 + 0.01 * t
        elev[45:48, 45:48] = 0.6
        conf = np.ones((n, n), np.float32)
        maps.append(to_lattice(t * 10**8, (elev, np.zeros_like(elev), conf), np.zeros(3), 0.0, res, res))
    s = SampleGrid(0, np.zeros(3), 0.0, 0, n, res)
    p = FuseParams(window_ns=10**9, elevation_rule=rule, top_height_m=0.5, top_footprint_m=4.0)
    (_, f), = list(fuse_range(MapSource.from_list(maps), [s], p))
    assert f.elevation[25, 25] == pytest.approx(crown, abs=1e-4)
    assert f.count[25, 25] == (5 if rule == "mean" else 2)
    assert f.elevation[46, 46] == pytest.approx(0.6, abs=1e-5) and f.count[46, 46] == 5
    assert f.elevation[5, 5] == pytest.approx(0.0, abs=1e-6)


def test_unknown_elevation_rule_is_refused():
    with pytest.raises(ValueError, match="elevation rule 'max'"):
        FuseParams(window_ns=1, elevation_rule="max")


def test_empty_window_gives_unobserved_cells():
    m = to_lattice(0, tuple(np.ones((4, 4), np.float32) for _ in range(3)), np.zeros(3), 0.0, 1.0, 1.0)
    s = SampleGrid(10**12, np.zeros(3), 0.0, -1, 8, 1.0)
    (_, f), = list(fuse_range(MapSource.from_list([m]), [s], FuseParams(window_ns=10**9)))
    assert np.isnan(f.elevation).all() and (f.region == 3).all() and (f.count == 0).all()


def test_fused_store(fused_store, drive_store, cfg):
    g = FusedStore(fused_store).group
    S = g["samples/reason"].shape[0]
    reg = g["fused/micro/region"][S // 2]
    el = g["fused/micro/elevation_m"][S // 2]
    assert set(np.unique(reg)) <= {1, 2, 3}
    assert np.isfinite(el[(reg == 1) | (reg == 2)]).all() and np.isnan(el[reg == 3]).all()
    assert (g["fused/micro/count"][S // 2][reg == 1] > 0).all()
    lt = g["fused/short/last_dt_s"][S // 2]
    assert np.nanmin(lt) >= -cfg.extract.map_skew_s - 1e-6 and np.nanmax(lt) <= cfg.fuse.window_s


def test_without_qa_ranges_fuse_stores_no_qa_grid_and_the_same_dataset(drive_store, fused_store, dataset, cfg, tmp_path):
    """shards.qa_ranges [] (the default): the fused store holds no QA grid, its other grids
    are the full store's bit for bit, and dem-align makes from it the session dataset
    (made with every QA grid) without its QA grids; a config asking for QA grids the fused
    store lacks is refused in one line."""
    import zarr

    from gtgen.dataset.dem_align import run_dem_align
    from gtgen.errors import ConfigError
    from gtgen.storage.schema import FUSED_QA, qa_paths

    lean_cfg = cfg.model_copy(update={"shards": cfg.shards.model_copy(update={"qa_ranges": []})})
    run_fuse(drive_store, tmp_path / "lean.zarr", lean_cfg, workers=1)
    full, lean = zarr.open_group(str(fused_store), mode="r"), zarr.open_group(str(tmp_path / "lean.zarr"), mode="r")
    assert lean.attrs["qa_ranges"] == [] and full.attrs["qa_ranges"] == ["micro", "short"]
    names = {k for k, _ in lean.members(max_depth=None) if isinstance(_, zarr.Array)}
    assert names and not names & set(qa_paths(grids=FUSED_QA)) and names | set(qa_paths(grids=FUSED_QA)) >= {k for k, a in full.members(max_depth=None) if isinstance(a, zarr.Array)}
    for name in names:
        np.testing.assert_array_equal(full[name][:], lean[name][:], err_msg=name)
    with pytest.raises(ConfigError, match=r"asks for the QA grids of \['micro', 'short'\].*run 'gtgen fuse' again") as err:
        run_dem_align(drive_store, tmp_path / "lean.zarr", None, tmp_path / "qa.zarr", cfg, workers=1)
    assert "\n" not in str(err.value) and not (tmp_path / "qa.zarr").exists()
    run_dem_align(drive_store, tmp_path / "lean.zarr", None, tmp_path / "a.zarr", lean_cfg, workers=1)
    a, b = zarr.open_group(str(tmp_path / "a.zarr"), mode="r"), zarr.open_group(str(dataset), mode="r")
    arrays = {k for k, x in a.members(max_depth=None) if isinstance(x, zarr.Array)}
    assert len(arrays) > 20 and not arrays & set(qa_paths())
    for k in arrays:
        assert np.array_equal(a[k][...], b[k][...], equal_nan=a[k].dtype.kind == "f"), k


def test_averaging_beats_the_single_map(dataset):
    """Fused elevation error against truth is lower than the single X-Racer map's, on the
    cells both call observed (odometry z drift on)."""
    from gtgen.report import build_report

    rep = build_report(dataset, dataset.parent / "report")
    for r in ("micro", "short"):
        fv = rep.truth[r]["fused_vs_single_map"]
        print(f"{r}: fused MAE {fv['fused_mae_m']} m vs single map {fv['single_map_mae_m']} m on {fv['cells']} cells")
        assert fv["cells"] > 1000 and fv["fused_mae_m"] < fv["single_map_mae_m"]


def test_bad_window_and_missing_store(tmp_path):
    for w in ("0", "-5"):  # a usage error: the usage line, then the error naming the option
        p = run_cli("fuse", tmp_path / "d.zarr", "--window", w)
        usage, error = p.stderr.strip().splitlines()
        assert p.returncode == 2 and usage.startswith("Usage: gtgen fuse") and error.startswith("error: Invalid value for '--window'")
    p = run_cli("fuse", tmp_path / "d.zarr")
    assert p.returncode == 1 and "run 'gtgen extract BAG' first" in p.stderr


def test_refuses_an_older_or_partial_drive_store(tmp_path, cfg):
    import zarr

    d = tmp_path / "d.zarr"
    zarr.open_group(str(d), mode="w").attrs.update({"store": "gtgen-drive", "version": 0, "complete": True})
    with pytest.raises(StoreError, match="version 0"):
        run_fuse(d, tmp_path / "f.zarr", cfg, workers=1)
    assert not (tmp_path / "f.zarr").exists()


def test_time_chunked_fusion_equals_one_pass_exactly(drive_store, fused_store, cfg, tmp_path):
    """A long drive fused in chunks (here 5 samples, on 2 processes) gives bit-identical labels."""
    import zarr

    chunked = cfg.model_copy(update={"fuse": cfg.fuse.model_copy(update={"chunk_samples": 5})})
    run_fuse(drive_store, tmp_path / "chunked.zarr", chunked, workers=2)
    a = zarr.open_group(str(fused_store), mode="r")
    b = zarr.open_group(str(tmp_path / "chunked.zarr"), mode="r")
    for r in ("micro", "short"):
        for name in ("elevation_m", "confidence", "risk", "count", "last_dt_s", "region"):
            np.testing.assert_array_equal(a[f"fused/{r}/{name}"][:], b[f"fused/{r}/{name}"][:], err_msg=f"{r}/{name}")
        np.testing.assert_array_equal(a[f"xracer/{r}/elevation_m"][:], b[f"xracer/{r}/elevation_m"][:])
    np.testing.assert_array_equal(a["samples/reason"][:], b["samples/reason"][:])
