"""gtgen train / eval: real CLI step, overfitting, metrics by hand, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from conftest import reseal, run_cli
from gtgen.config import GtgenConfig, load_config
from gtgen.errors import ConfigError, StoreError, TrainError
from gtgen.train.metrics import Consistency, ElevationMAE, RiskMetrics

SMALL_TRAIN = {"train": {"micro_size": 32, "short_size": 32, "image_width": 48, "image_height": 30, "depth_step_m": 8.0,
                         "image_channels": 8, "pillar_channels": 8, "decoder_channels": 8, "batch_size": 2, "steps": 200}}


def test_one_step_and_eval_through_the_cli(dataset, tmp_path):
    import yaml

    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump(SMALL_TRAIN))
    p = run_cli("train", dataset, "--preset", "tiny", "--steps", "1", "--run", tmp_path / "run", "--config", c, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "run" / "ckpt.pt").is_file() and (tmp_path / "run" / "gtgen-config.yaml").is_file()
    hist = json.loads((tmp_path / "run" / "metrics.json").read_text())["history"]
    assert len(hist) == 1 and np.isfinite(hist[0]["total"])
    p = run_cli("eval", dataset, "--ckpt", tmp_path / "run" / "ckpt.pt", "--split", "all", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "obs PC" in p.stdout and "X-Racer" in p.stdout and "raw elevation" in p.stdout and "consistency MAE" in p.stdout
    res = json.loads((tmp_path / "run" / "eval.json").read_text())
    assert res["elevation"]["micro"]["xracer"]["obs_pc"]["coverage_pct"] == pytest.approx(100.0)
    # resume continues the step count
    p = run_cli("train", dataset, "--preset", "tiny", "--steps", "1", "--run", tmp_path / "run", "--config", c, "--resume", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert len(json.loads((tmp_path / "run" / "metrics.json").read_text())["history"]) == 2
    # a checkpoint of another preset is refused
    p = run_cli("eval", dataset, "--ckpt", tmp_path / "run" / "ckpt.pt", "--preset", "paper", cwd=tmp_path)
    assert p.returncode == 1 and "preset 'tiny'" in p.stderr
    # a checkpoint whose config this version does not know (another gtgen) is refused in one line
    import torch

    state = torch.load(tmp_path / "run" / "ckpt.pt", map_location="cpu", weights_only=False)
    state["train"]["prior_correction_m"] = 0.5
    torch.save(state, tmp_path / "foreign.pt")
    p = run_cli("eval", dataset, "--ckpt", tmp_path / "foreign.pt", cwd=tmp_path)
    assert p.returncode == 1 and "Traceback" not in p.stderr and "does not accept (prior_correction_m" in p.stderr


def test_overfitting_a_fixed_batch(dataset):
    from gtgen.train.data import ShardDataset
    from gtgen.train.loss import total_loss
    from gtgen.train.trainer import _collate, build_model, seed_everything

    # the paper's MSE risk loss: a fitted batch drives it to zero (the cross-entropy of soft
    # risk labels keeps their entropy)
    cfg = load_config(None, SMALL_TRAIN, {"train": {"risk_loss": "mse"}})
    seed_everything(0)
    ds = ShardDataset(dataset, cfg.train)
    batch = _collate([ds[0], ds[1]])
    model = build_model(cfg.train, ds.data_cfg)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(220):  # one thread per test process: the loss at 0.144, 0.091, 0.080, 0.061 of the first after 100, 150, 200, 250 steps
        loss, _ = total_loss(model(batch), batch, cfg.train)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    print(f"overfit: loss {losses[0]:.4f} -> {losses[-1]:.4f}")
    assert losses[-1] < 0.1 * losses[0]


def test_the_training_read_is_the_full_read_without_the_baselines(dataset):
    from gtgen.train.data import ShardDataset
    from gtgen.train.evaluation import run_eval
    from gtgen.train.loss import total_loss
    from gtgen.train.trainer import _collate, build_model, seed_everything

    cfg = load_config(None, SMALL_TRAIN)
    full, lean = ShardDataset(dataset, cfg.train), ShardDataset(dataset, cfg.train, baselines=False)
    baseline_keys = {f"{r}/{k}" for r in ("micro", "short") for k in ("xr_elevation", "xr_risk", "raw_elevation")}
    for i in (0, len(full) - 1):
        a, b = full[i], lean[i]
        assert set(a) - set(b) == baseline_keys and set(b) <= set(a)
        for k, v in b.items():
            assert v.dtype == a[k].dtype and torch.equal(torch.nan_to_num(v), torch.nan_to_num(a[k])), k
        assert a["micro/region"].dtype == torch.uint8 and int(a["micro/region"].max()) <= 3
    seed_everything(0)
    model = build_model(cfg.train, full.data_cfg)
    batch_a, batch_b = _collate([full[0], full[1]]), _collate([lean[0], lean[1]])
    assert total_loss(model(batch_a), batch_a, cfg.train)[0] == total_loss(model(batch_b), batch_b, cfg.train)[0]
    # the baseline rows need the baselines' grids: a clear error, not a KeyError mid-run
    with pytest.raises(ValueError, match="baselines=True"):
        run_eval(model.eval(), lean, cfg.train, torch.device("cpu"), "32", baselines=True)


def test_elevation_mae_by_hand_with_empty_regions():
    m = ElevationMAE()
    pred = np.array([[1.0, 2.0], [np.nan, 4.0]])
    lab = np.array([[0.0, 0.0], [1.0, np.nan]])
    reg = np.array([[1, 1], [3, 3]])
    m.add(pred, lab, reg)
    t = m.table()
    assert t["obs_pc"]["mae_m"] == pytest.approx(1.5) and t["obs_pc"]["coverage_pct"] == pytest.approx(100)
    assert t["unobs"]["mae_m"] is None and t["unobs"]["coverage_pct"] == pytest.approx(0)  # labelled, not predicted
    assert t["obs_f"]["mae_m"] is None and t["obs_f"]["coverage_pct"] is None  # no cell at all: n/a
    assert t["total"]["mae_m"] == pytest.approx(1.5)
    # each region's share of the labelled cells (Tab. I's header): 2 obs PC, 1 unobs
    assert [t[k]["share_pct"] for k in ("obs_pc", "obs_f", "unobs", "total")] == pytest.approx([200 / 3, 0, 100 / 3, 100])


def test_risk_metrics_by_hand():
    r = RiskMetrics(threshold=0.5)
    pred = np.array([0.9, 0.8, 0.1, 0.2, 0.7])
    lab = np.array([1.0, 0.0, 1.0, 0.0, np.nan])
    r.add(pred, lab)
    t = r.table()
    assert t["mse"] == pytest.approx((0.01 + 0.64 + 0.81 + 0.04) / 4)
    assert t["precision"] == pytest.approx(0.5) and t["recall"] == pytest.approx(0.5) and t["f1"] == pytest.approx(0.5)
    empty = RiskMetrics(threshold=0.5).table()
    assert empty == {"mse": None, "precision": None, "recall": None, "f1": None, "coverage_pct": None}


def test_consistency_by_hand():
    c = Consistency()
    short = np.zeros((1, 8, 8))
    micro = np.ones((1, 8, 8))  # pooled to the 4 x 4 centre crop: all ones
    c.add(micro, short)
    assert c.value() == pytest.approx(1.0)
    assert Consistency().value() is None


def test_bad_datasets(dataset, tmp_path):
    import shutil

    import zarr

    from gtgen.storage.dataset_writer import ShardWriter
    from gtgen.storage.schema import DatasetAttrs
    from gtgen.train.data import ShardDataset

    cfg = GtgenConfig()
    other = tmp_path / "other.zarr"
    shutil.copytree(dataset, other)
    g = zarr.open_group(str(other), mode="r+")
    g.attrs["version"] = 99
    reseal(other)
    with pytest.raises(StoreError, match="version 99"):
        ShardDataset(other, cfg.train)
    w = ShardWriter(tmp_path / "empty.zarr", 0, 8, 8, 4, 48)
    w.close(DatasetAttrs(gtgen_version="0", config=cfg.model_dump(mode="json"), drives=[], image_size=(4, 4), cameras=[]))
    with pytest.raises(TrainError, match="no samples"):
        ShardDataset(tmp_path / "empty.zarr", cfg.train)
    p = run_cli("train", tmp_path / "empty.zarr", "--steps", "1", cwd=tmp_path)
    assert p.returncode == 1 and "no samples" in p.stderr and "Traceback" not in p.stderr
    p = run_cli("train", dataset, "--preset", "huge", cwd=tmp_path)
    assert p.returncode == 1 and "preset 'huge' unknown" in p.stderr
    # a dataset made by a gtgen whose trainer had other keys stays readable; an unknown key
    # about the data itself is one line naming it
    g = zarr.open_group(str(other), mode="r+")
    g.attrs["version"] = zarr.open_group(str(dataset), mode="r").attrs["version"]
    conf = dict(g.attrs["config"])
    conf["train"] = {**conf["train"], "ema_decay": 0.99}
    g.attrs["config"] = conf
    reseal(other)
    assert len(ShardDataset(other, cfg.train)) > 0
    conf["grids"] = {**conf["grids"], "tiles": 3}
    g.attrs["config"] = conf
    reseal(other)
    with pytest.raises(ConfigError, match="records a config this gtgen does not accept .*grids.tiles"):
        ShardDataset(other, cfg.train)
    p = run_cli("report", other, "-o", tmp_path / "rep", cwd=tmp_path)
    assert p.returncode == 1 and "grids.tiles" in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_filled_prior_and_nearest_baseline_by_hand():
    from gtgen.grids import filled, nearest_filled, point_distance

    g = np.full((9, 9), np.nan)
    g[4, 0:3] = [1.0, 2.0, 3.0]
    near = nearest_filled(g)
    assert near[4, 8] == 3.0 and near[0, 0] == 1.0 and near[4, 1] == 2.0  # nearest valid cell's value
    f = filled(g)
    assert np.isfinite(f).all() and f[4, 1] == 2.0  # valid cells keep their value
    assert 1.0 <= f.min() and f.max() <= 3.0  # a weighted mean of the valid cells
    assert f[4, 8] > f[4, 0]  # far to the right, nearer the 3 than the 1
    assert np.all(filled(np.full((4, 4), np.nan)) == 0) and np.isnan(nearest_filled(np.full((2, 2), np.nan))).all()
    d = point_distance(g)
    assert d[4, 1] == 0 and d[4, 8] == pytest.approx(6 / 9)


def test_pyramid_fill_follows_the_full_resolution_fill():
    from scipy.ndimage import gaussian_filter

    from gtgen.grids import filled

    rng = np.random.default_rng(3)
    for n in (40, 125, 250):
        # smooth hills seen in a disc and a few far patches, like the voxel map's min z
        xx, yy = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        g = 3 * np.sin(xx / (0.3 * n)) + 2 * np.cos(yy / (0.2 * n)) + 0.1 * rng.normal(size=(n, n))
        seen = np.hypot(xx - n / 2, yy - n / 2) < n / 5
        seen |= rng.random((n, n)) < 0.002
        g[~seen] = np.nan
        oracle = filled(g, max_sigma_cells=np.inf)  # every scale at full resolution
        # the oracle is the plain coarse-to-fine normalized convolution, written out
        ok = np.isfinite(g)
        naive = np.full(g.shape, np.nan)
        sigma = 1.0
        while np.isnan(naive).any() and sigma <= 2 * n:
            den = gaussian_filter(ok.astype(float), sigma, mode="constant", truncate=3.0)
            num = gaussian_filter(np.where(ok, g, 0.0), sigma, mode="constant", truncate=3.0)
            reach = np.isnan(naive) & (den > 1e-3)
            naive[reach] = num[reach] / den[reach]
            sigma *= 2
        naive[ok] = g[ok]
        np.testing.assert_allclose(oracle, naive, atol=1e-5)
        fast = filled(g)
        d = np.abs(fast - oracle)
        assert np.array_equal(fast[ok], g[ok].astype(np.float32))
        # apart from the seams where a cell's scale changes, the two agree (a half-cell
        # misplacement of the levels doubles both numbers)
        assert d.mean() < 0.03 and np.mean(d > 0.05) < 0.1, (n, d.mean(), np.mean(d > 0.05))


def test_weighted_risk_loss_weighs_fatal_cells():
    from gtgen.train.loss import risk_loss

    label = torch.tensor([1.0, 0.0, 0.0, 0.0, float("nan")])
    logit = torch.full((5,), -4.0)
    pred = {"r/risk": torch.sigmoid(logit), "r/risk_logit": logit}  # "no risk anywhere"
    p = float(torch.sigmoid(torch.tensor(-4.0)))

    def loss(**train):
        return float(risk_loss(pred, "r", label, load_config(None, {"train": train}).train))

    assert loss(risk_loss="mse") == pytest.approx(((1 - p) ** 2 + 3 * p**2) / 4)
    assert loss(risk_loss="weighted_mse", risk_fatal_weight=10) == pytest.approx((10 * (1 - p) ** 2 + 3 * p**2) / 13)
    bce_fatal, bce_safe = -np.log(p), -np.log(1 - p)
    assert loss(risk_loss="weighted_bce", risk_fatal_weight=10) == pytest.approx((10 * bce_fatal + 3 * bce_safe) / 13, rel=1e-5)


@pytest.mark.parametrize("ablation", [{"alpha": 0.0}, {"gamma": 0.0}])
def test_loss_ablations_train_one_step(dataset, tmp_path, ablation):
    from gtgen.train.data import ShardDataset
    from gtgen.train.loss import total_loss
    from gtgen.train.trainer import _collate, build_model, train

    cfg = load_config(None, SMALL_TRAIN, {"train": ablation})
    res = train(dataset, tmp_path / "run", cfg, max_steps=1)
    assert res.steps == 1 and np.isfinite(res.last_loss)
    ds = ShardDataset(dataset, cfg.train)
    batch = _collate([ds[0], ds[1]])
    model = build_model(cfg.train, ds.data_cfg).eval()
    with torch.no_grad():
        pred = model(batch)
        base, parts = total_loss(pred, batch, cfg.train)
        if "alpha" in ablation:  # the unobserved cells' labels no longer count
            other = dict(batch)
            for r in ("micro", "short"):
                other[f"{r}/elevation"] = torch.where(batch[f"{r}/region"] == 3, batch[f"{r}/elevation"] + 0.5, batch[f"{r}/elevation"])
            assert float(total_loss(pred, other, cfg.train)[0]) == pytest.approx(float(base))
        else:  # the consistency term is logged but not added
            tc = cfg.train
            assert float(base) == pytest.approx(sum(tc.mu * parts[f"{r}/trav"] + tc.lam * parts[f"{r}/ele"] for r in ("micro", "short")), rel=1e-5)


def test_seeds_train_and_eval_mean_and_spread(dataset, tmp_path):
    import yaml

    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump(SMALL_TRAIN))
    p = run_cli("train", dataset, "--steps", "1", "--seeds", "2", "--run", tmp_path / "runs" / "tiny", "--config", c, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "runs" / "tiny-seed0" / "ckpt.pt").is_file() and (tmp_path / "runs" / "tiny-seed1" / "ckpt.pt").is_file()
    p = run_cli("eval", dataset, "--ckpt", str(tmp_path / "runs" / "tiny-seed*" / "ckpt.pt"), "--split", "all", "-o", tmp_path / "e.json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "mean ± spread of 2 seeds" in p.stdout and "X-Racer's cells" in p.stdout and "nearest-filled" in p.stdout
    res = json.loads((tmp_path / "e.json").read_text())
    assert len(res["runs"]) == 2
    a, b = (r["elevation"]["short"]["model"]["total"]["mae_m"] for r in res["runs"])
    assert res["elevation"]["short"]["model"]["total"]["mae_m"] == pytest.approx((a + b) / 2)
    assert res["spread"]["elevation"]["short"]["model"]["total"]["mae_m"] == pytest.approx(abs(a - b) / np.sqrt(2))
    near = res["elevation"]["short"]["raw_nearest"]["total"]
    assert near["coverage_pct"] == pytest.approx(100.0)  # the trivial baseline covers every labelled cell
    xr = res["elevation"]["short"]["model_on_xracer_cells"]["total"]["coverage_pct"]
    assert xr == pytest.approx(res["elevation"]["short"]["xracer"]["total"]["coverage_pct"])
    p = run_cli("eval", dataset, "--ckpt", str(tmp_path / "nothing*" / "ckpt.pt"), cwd=tmp_path)
    assert p.returncode == 1 and "matches no checkpoint" in p.stderr


def test_bad_training_input_one_line(dataset, tmp_path):
    import shutil

    import yaml
    import zarr

    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump(SMALL_TRAIN))
    p = run_cli("train", dataset, "--steps", "1", "--run", tmp_path / "run", "--config", c, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    # a dataset whose val split is empty
    only_train = tmp_path / "only_train.zarr"
    shutil.copytree(dataset, only_train)
    g = zarr.open_group(str(only_train), mode="r+")
    g["meta/split"][:] = 0
    reseal(only_train)
    p = run_cli("eval", only_train, "--ckpt", tmp_path / "run" / "ckpt.pt", cwd=tmp_path)
    assert p.returncode == 1 and "no 'val' samples" in p.stderr and "--split all" in p.stderr and "Traceback" not in p.stderr
    # an old checkpoint format
    state = torch.load(tmp_path / "run" / "ckpt.pt", map_location="cpu", weights_only=False)
    state["version"] = 2  # this gtgen writes 5
    torch.save(state, tmp_path / "old.pt")
    p = run_cli("eval", dataset, "--ckpt", tmp_path / "old.pt", "--split", "all", cwd=tmp_path)
    assert p.returncode == 1 and "version 5 (found 2)" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    # grids the model cannot tile
    from gtgen.train.trainer import build_model

    with pytest.raises(ConfigError, match="micro grid must span 100 m"):
        build_model(GtgenConfig().train, load_config(None, {"grids": {"micro": {"size": 400}}}))
    with pytest.raises(ConfigError, match="short_size 8"):
        build_model(load_config(None, {"train": {"short_size": 8}}).train, GtgenConfig())


def test_paper_preset_runs_one_step_on_cpu(dataset, tmp_path):
    """The paper's network (EfficientNet-B0 and FPN, its depth bins, 256-channel pillars,
    its decoder) through one training step, on half its grids and images: the step at full
    size took 80 s of CPU, and what the full size adds is memory, which
    test_a_run_that_does_not_fit_the_memory_stops_before_any_work checks. Halving keeps
    the sizes that the strides do not divide (124 / 8, 198 / 32), as 250 and 396 are not."""
    from gtgen.train.trainer import preset_overrides, train

    paper = preset_overrides("paper")["train"]
    half = {k: paper[k] // 2 for k in ("image_width", "image_height")} | {"micro_size": 248, "short_size": 124}
    cfg = load_config(None, preset_overrides("paper"), {"train": {"batch_size": 1, "workers": 0, **half}})
    res = train(dataset, tmp_path / "paper", cfg, max_steps=1)
    assert res.steps == 1 and np.isfinite(res.last_loss)


def test_mirror_keeps_cameras_points_and_grids_consistent(dataset):
    from gtgen.train.augment import GRID_KEYS, mirror
    from gtgen.train.data import ShardDataset
    from gtgen.train.trainer import _collate

    cfg = load_config(None, SMALL_TRAIN)
    ds = ShardDataset(dataset, cfg.train)
    batch = _collate([ds[0], ds[1]])
    which = torch.tensor([True, False])
    m = mirror(batch, which)

    def same(a, b):  # NaN (no label) equal to NaN
        return torch.equal(torch.nan_to_num(a, nan=-9.0), torch.nan_to_num(b, nan=-9.0)) if a.is_floating_point() else torch.equal(a, b)

    for k, v in batch.items():  # the second sample is untouched, the first mirrored back is itself
        assert same(m[k][1], v[1]), k
        assert same(mirror(m, which)[k], v), k
    for k in GRID_KEYS:  # (x, y) grids: y reversed
        assert same(m[k][0], batch[k][0].flip(-1)), k
    assert torch.equal(m["points"][0][:, 1], -batch["points"][0][:, 1])
    # a point seen by a camera is seen by the camera mirrored at the mirrored point, at the
    # mirrored pixel, whose colour is the one the camera saw there
    W, H = batch["images"].shape[-1], batch["images"].shape[-2]

    def project(b, cam, p):
        T = b["T_target_cam"][0, cam].double()
        pc = torch.linalg.inv(T) @ torch.cat([p, torch.ones(1, dtype=p.dtype)])
        uvw = b["K"][0, cam].double() @ pc[:3]
        return uvw[:2] / uvw[2], pc[2]

    rng = np.random.default_rng(0)
    seen = 0
    for cam in range(batch["images"].shape[1]):
        twin = cam
        for p in torch.from_numpy(rng.uniform([-40, -40, -3], [40, 40, 3], (200, 3))):
            (u, v), z = project(batch, cam, p)
            if z <= 0 or not (0 <= u <= W - 1 and 0 <= v <= H - 1):
                continue
            (u2, v2), z2 = project(m, twin, p * torch.tensor([1.0, -1.0, 1.0], dtype=p.dtype))
            assert float(z2) == pytest.approx(float(z), abs=1e-4)
            assert float(u2) == pytest.approx(W - 1 - float(u), abs=1e-3) and float(v2) == pytest.approx(float(v), abs=1e-3)
            ui, vi = int(round(float(u))), int(round(float(v)))
            assert torch.equal(m["images"][0, twin, :, vi, W - 1 - ui], batch["images"][0, cam, :, vi, ui])
            seen += 1
    assert seen > 100


def test_micro_prior_finer_than_the_points_grid_follows_the_fine_oracle(dataset):
    from gtgen.grids import nearest_index
    from gtgen.train.data import ShardDataset

    cfg = load_config(None, SMALL_TRAIN)
    ds = ShardDataset(dataset, cfg.train)
    n_s = ds.store.size("short")
    crop = n_s - 2 * (n_s // 4)
    fine = load_config(None, SMALL_TRAIN, {"train": {"micro_size": 4 * crop}})
    ds = ShardDataset(dataset, fine.train)
    clip = fine.train.elevation_clip_m
    for i in (0, len(ds) // 2):
        got = ds[i]["prior_micro"].numpy()
        assert got.shape == (2, 4 * crop, 4 * crop) and np.isfinite(got).all()
        # oracle: the prior computed on the raw grid's centre upsampled to the model's cells
        raw = ds.store.inputs("raw_elevation_m")[int(ds.indices[i])][n_s // 4 : n_s - n_s // 4, n_s // 4 : n_s - n_s // 4]
        up = raw[np.ix_(nearest_index(crop, 4 * crop), nearest_index(crop, 4 * crop))]
        oracle = ds._prior(up, ds._prior_win["micro"])
        assert np.mean(np.abs(got[0] - oracle[0])) * clip < 0.03  # metres (6 mm on the test drive)
        assert np.max(np.abs(got[1] - oracle[1])) < 1.0 / crop  # distance to points / grid size: within a raw cell

