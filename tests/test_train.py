"""gtgen train / eval: real CLI step, overfitting, metrics by hand, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from conftest import run_cli
from gtgen.config import GtgenConfig, load_config
from gtgen.errors import StoreError, TrainError
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

    cfg = load_config(None, SMALL_TRAIN)
    seed_everything(0)
    ds = ShardDataset(dataset, cfg.train)
    batch = _collate([ds[0], ds[1]])
    model = build_model(cfg.train, ds.data_cfg)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(150):
        loss, _ = total_loss(model(batch), batch, cfg.train)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    print(f"overfit: loss {losses[0]:.4f} -> {losses[-1]:.4f}")
    assert losses[-1] < 0.1 * losses[0]


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

    from gtgen.dataset.writer import ShardWriter
    from gtgen.storage.schema import DatasetAttrs
    from gtgen.train.data import ShardDataset

    cfg = GtgenConfig()
    other = tmp_path / "other.zarr"
    shutil.copytree(dataset, other)
    g = zarr.open_group(str(other), mode="r+")
    g.attrs["version"] = 99
    with pytest.raises(StoreError, match="version 99"):
        ShardDataset(other, cfg.train)
    w = ShardWriter(tmp_path / "empty.zarr", 0, 8, 8, (4, 4))
    w.close(DatasetAttrs(gtgen_version="0", config=cfg.model_dump(mode="json"), drives=[], image_size=(4, 4), cameras=[]))
    with pytest.raises(TrainError, match="no samples"):
        ShardDataset(tmp_path / "empty.zarr", cfg.train)
    p = run_cli("train", tmp_path / "empty.zarr", "--steps", "1", cwd=tmp_path)
    assert p.returncode == 1 and "no samples" in p.stderr and "Traceback" not in p.stderr
    p = run_cli("train", dataset, "--preset", "huge", cwd=tmp_path)
    assert p.returncode == 1 and "preset 'huge' unknown" in p.stderr
