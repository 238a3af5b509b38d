"""The model's switches (inputs on/off, single-range networks) and ``gtgen experiments``
(the paper's Tab. I-IV: runs shared, resumable, the paper's numbers beside ours)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch
import yaml

from conftest import run_cli
from gtgen.config import load_config
from gtgen.errors import ConfigError, TrainError
from test_train import SMALL_TRAIN

# the paper's baselines as switches (Sec. IV-B), and each switch alone
SWITCHES = {
    "no cameras": {"cameras": False},
    "no points": {"points": False},
    "no raw elevation": {"raw_elevation": False},
    "micro alone": {"ranges": "micro"},
    "short alone": {"ranges": "short"},
    "LSS (C), micro": {"cameras": True, "points": False, "raw_elevation": False, "ranges": "micro"},
    "PointPillars (L), short": {"cameras": False, "points": True, "raw_elevation": False, "ranges": "short"},
}
# what the loader reads for each switch that is off
INPUT_KEYS = {"cameras": ("images", "K", "T_target_cam"), "points": ("points", "n_points"), "raw_elevation": ("raw", "prior", "prior_micro")}


def _cfg(**train):
    return load_config(None, SMALL_TRAIN, {"train": train})


@pytest.mark.parametrize("switch", list(SWITCHES))
def test_each_switch_trains_one_step_and_evaluates(dataset, tmp_path, switch):
    from gtgen.train.data import ShardDataset
    from gtgen.train.loss import total_loss
    from gtgen.train.trainer import _collate, build_model, evaluate, train

    cfg = _cfg(**SWITCHES[switch])
    tc = cfg.train
    ranges = tc.predicted_ranges
    res = train(dataset, tmp_path / "run", cfg, max_steps=1)
    assert res.steps == 1 and np.isfinite(res.last_loss)
    ev = evaluate(dataset, tmp_path / "run" / "ckpt.pt", split=None)
    assert list(ev["elevation"]) == list(ranges) == ev["ranges"] and list(ev["risk"]) == list(ranges)  # rows of its ranges only
    for r in ranges:
        assert ev["elevation"][r]["model"]["total"]["coverage_pct"] == pytest.approx(100.0)
        assert ev["elevation"][r]["model"]["total"]["mae_m"] > 0
    assert (ev["consistency_mae_m"] is None) == (len(ranges) == 1)
    # the loader reads only what the model takes
    ds = ShardDataset(dataset, tc)
    sample = ds[0]
    for switch_key, keys in INPUT_KEYS.items():
        for k in keys:
            if k == "prior_micro":
                assert (k in sample) == (tc.raw_elevation and "micro" in ranges), k
            else:
                assert (k in sample) == getattr(tc, switch_key), k
    assert {k.split("/")[0] for k in sample if "/" in k} == set(ranges)
    # the loss: the ranges predicted, the consistency term only with both
    model = build_model(tc, ds.data_cfg).eval()
    assert (model.lift is None) != tc.cameras and (model.pillars is None) != tc.points
    batch = _collate([ds[0], ds[1]])
    with torch.no_grad():
        pred = model(batch)
    assert {k.split("/")[0] for k in pred} == set(ranges)
    parts = total_loss(pred, batch, tc)[1]
    assert ("cons" in parts) == (len(ranges) == 2) and {k.split("/")[0] for k in parts if "/" in k} == set(ranges)
    # zero-initialised heads: a fresh model's elevation is the prior it corrects, or flat
    # ground (0) where it predicts the elevation directly
    for r in ranges:
        prior = batch["prior" if r == "short" else "prior_micro"][:, 0] if tc.raw_elevation else torch.zeros_like(pred[f"{r}/elevation"])
        torch.testing.assert_close(pred[f"{r}/elevation"], prior)


def test_the_micro_network_sees_only_the_micro_range(dataset):
    from gtgen.train.data import ShardDataset
    from gtgen.train.trainer import _collate, build_model

    cfg = _cfg(ranges="micro")
    ds = ShardDataset(dataset, cfg.train)
    model = build_model(cfg.train, ds.data_cfg).eval()
    half_m = ds.data_cfg.grids.micro.length_m / 2
    both = build_model(_cfg().train, ds.data_cfg).eval()
    # the BEV grid is the micro extent at the short grid's cells: half the cells, same size
    assert model.pillars.bev_size == both.pillars.bev_size // 2 and model.pillars.bev_res == pytest.approx(both.pillars.bev_res)
    assert model.pillars.bev_size * model.pillars.bev_res == pytest.approx(2 * half_m)
    assert tuple(ds[0]["raw"].shape) == (2, model.pillars.bev_size, model.pillars.bev_size)

    def far_points_raised(batch):
        pts = batch["points"]
        outside = (pts[..., :2].abs().amax(-1) > half_m + 0.1) & (torch.arange(pts.shape[1])[None] < batch["n_points"][:, None])
        assert outside.sum() > 100  # the test drive has points beyond the micro range
        return {**batch, "points": torch.where(outside[..., None], pts + torch.tensor([0.0, 0.0, 5.0]), pts)}

    batch = _collate([ds[0], ds[1]])
    full = _collate([ShardDataset(dataset, _cfg().train)[i] for i in (0, 1)])
    with torch.no_grad():
        a, b = model(batch), model(far_points_raised(batch))
        c, d = both(full), both(far_points_raised(full))
    for k in a:  # points beyond +-half_m change nothing in the micro network
        torch.testing.assert_close(a[k], b[k])
    # but do in the multi-range one (its context; the risk: a fresh elevation head is zero)
    assert not torch.allclose(c["micro/risk"], d["micro/risk"])


def test_a_switch_through_the_cli(dataset, tmp_path):
    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump({"train": {**SMALL_TRAIN["train"], "cameras": False, "ranges": "short"}}))
    p = run_cli("train", dataset, "--steps", "1", "--run", tmp_path / "run", "--config", c, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "image backbone" not in p.stdout and "PointPillars" in p.stdout  # the parameters per block
    p = run_cli("eval", dataset, "--ckpt", tmp_path / "run" / "ckpt.pt", "--split", "all", "--viz", "2", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "short range: elevation MAE" in p.stdout and "micro range" not in p.stdout
    assert re.search(r"consistency MAE +│ n/a \(one range\)", p.stdout) and (tmp_path / "run" / "pred_2.png").is_file()
    assert list(json.loads((tmp_path / "run" / "eval.json").read_text())["elevation"]) == ["short"]
    c.write_text(yaml.safe_dump({"train": {"cameras": False, "points": False, "raw_elevation": False}}))
    p = run_cli("train", dataset, "--steps", "1", "--config", c, cwd=tmp_path)
    assert p.returncode == 1 and "all off: the model needs at least one input" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    c.write_text(yaml.safe_dump({"train": {"ranges": "long"}}))
    p = run_cli("train", dataset, "--steps", "1", "--config", c, cwd=tmp_path)
    assert p.returncode == 1 and "train.ranges" in p.stderr and "'both', 'micro' or 'short'" in p.stderr


def test_switched_model_exports_its_own_onnx_graph(dataset, tmp_path):
    import onnxruntime as ort

    from gtgen.train.checkpoint import load_checkpoint
    from gtgen.train.data import ShardDataset
    from gtgen.train.evaluation import trained_model as _trained_model
    from gtgen.train.onnx import Deployable, deploy_inputs
    from gtgen.train.trainer import _collate, train

    cfg = _cfg(cameras=False, ranges="micro")
    train(dataset, tmp_path / "run", cfg, max_steps=1)
    p = run_cli("export", "onnx", "--ckpt", tmp_path / "run" / "ckpt.pt", "-o", tmp_path / "m.onnx", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    assert names == ["pillar_points", "pillar_cells", "raw", "prior", "prior_micro"]
    assert [o.name for o in sess.get_outputs()] == ["micro_elevation", "micro_risk"]
    state, tc, data_cfg = load_checkpoint(tmp_path / "run" / "ckpt.pt")
    model = _trained_model(state, tc, data_cfg)
    batch = _collate([ShardDataset(dataset, tc)[3]])
    args = deploy_inputs(model, batch)
    with torch.no_grad():
        want = Deployable(model)(*args)
        torch.testing.assert_close(want[0], model(batch)["micro/elevation"])
    for w, g in zip(want, sess.run(None, {n: a.numpy() for n, a in zip(names, args)})):
        assert np.max(np.abs(w.numpy() - g)) < 1e-3


def test_scans_on_a_dataset_without_scans_is_one_line(dataset, tmp_path):
    from gtgen.train.data import ShardDataset

    with pytest.raises(TrainError, match="holds no raw lidar scans.*lidar role"):
        ShardDataset(dataset, _cfg(geometry="scans", n_scans=5).train)
    assert len(ShardDataset(dataset, _cfg(geometry="scans", points=False).train)) > 0  # no point input: nothing to read
    with pytest.raises(ConfigError, match="n_scans"):
        _cfg(n_scans=0)


def _experiments(with_val, out, *args):
    c = out.parent / "exp.yaml"
    c.write_text(yaml.safe_dump({"train": {**SMALL_TRAIN["train"], "ckpt_every": 1}}))
    return run_cli("experiments", with_val, "--config", c, "-o", out, *args, cwd=out.parent)


def test_experiments_share_runs_resume_and_retrain_nothing(with_val, tmp_path):
    from gtgen.train.experiments import _run_config, _runs
    from gtgen.train.presets import preset_overrides
    from gtgen.train.trainer import train

    out = tmp_path / "exp"
    # a run killed after its first checkpoint (of 2 steps): the experiments resume it
    base = load_config(None, preset_overrides("tiny"), {"train": {**SMALL_TRAIN["train"], "ckpt_every": 1}})
    killed = _run_config(base, _runs(False)["cl"], 2, base.train.seed, None)
    first = train(with_val, out / "runs" / "cl-seed0", killed, max_steps=1)
    p = _experiments(with_val, out, "--steps", "2", "--tables", "III,IV")
    assert p.returncode == 0, p.stderr
    assert "cl (seed 0, 2 steps; cameras + points + raw elevation, both ranges, alpha 0): resuming at step 1" in p.stdout
    # Tab. III's scan rows cannot run on a dataset without scans: one line says so and how
    skip = [ln for ln in p.stdout.splitlines() if ln.startswith("note: skipped")]
    assert len(skip) == 1 and "N=1, N=2, N=5, N=10" in skip[0] and "no raw lidar scans" in skip[0] and "lidar role" in skip[0]
    assert "no test split: every run is evaluated on the val split" in p.stdout
    assert "Tab. III" in p.stdout and "Tab. IV" in p.stdout and "0.853" in p.stdout  # a paper number beside ours
    assert re.search(r"runs trained now +│ 3 ", p.stdout)  # ul, cl, ours: VM and UL + CL share ours
    hist = json.loads((out / "runs" / "cl-seed0" / "metrics.json").read_text())["history"]
    assert [h["step"] for h in hist] == [1, 2] and hist[0]["total"] == pytest.approx(first.last_loss)
    res = json.loads((out / "experiments.json").read_text())
    assert res["split"] == "val" and res["steps"] == 2 and sorted(res["runs"]) == ["cl", "ours", "ul"]
    t3, t4 = res["tables"]
    assert [r["label"] for r in t3["rows"]] == ["VM"] and [r["label"] for r in t4["rows"]] == ["UL", "CL", "UL + CL"]
    ours = json.loads((out / "runs" / "ours-seed0" / "eval_val.json").read_text())
    vm, both = t3["rows"][0]["cells"], t4["rows"][2]["cells"]
    assert vm[0]["mean"] == ours["elevation"]["micro"]["model"]["total"]["mae_m"] and vm[0]["paper"] == 0.403
    assert both[2]["mean"] == ours["elevation"]["micro"]["model"]["unobs"]["mae_m"] and both[6]["mean"] == ours["consistency_mae_m"]
    assert vm[0]["spread"] is None  # one seed
    md = (out / "experiments.md").read_text()
    assert "| UL | gamma = 0 |" in md and "| VM | C + VM (= Ours) |" in md and "| 0.853 |" in md
    # a second run retrains and re-evaluates nothing
    stamps = {f: f.stat().st_mtime_ns for f in out.glob("runs/*/*") if f.suffix in (".pt", ".json")}
    p = _experiments(with_val, out, "--steps", "2", "--tables", "IV")
    assert p.returncode == 0, p.stderr
    assert re.search(r"runs trained now +│ 0 ", p.stdout) and re.search(r"runs already done +│ 3 ", p.stdout)
    assert p.stdout.count(": done") == 3
    assert stamps == {f: f.stat().st_mtime_ns for f in stamps}
    # runs of other settings are refused, not mixed in
    p = _experiments(with_val, out, "--steps", "3", "--tables", "IV")
    assert p.returncode == 1 and "was trained with train.steps = 2, not 3" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    p = _experiments(with_val, out, "--tables", "V")
    assert p.returncode == 1 and "--tables 'V'" in p.stderr


def test_experiments_seeds_give_mean_and_spread(with_val, tmp_path):
    from gtgen.train.experiments import run_experiments
    from gtgen.train.tables import parse_tables
    from gtgen.train.trainer import mean_and_spread

    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump(SMALL_TRAIN))
    lines = []
    # 2 steps: a schedule of one step has a learning rate of almost 0, and the fresh
    # elevation heads start at 0 whatever the seed
    # one seed, then two into the same folder: the second run reads seed 0 from disk and
    # averages it with the fresh seed 1
    run_experiments(with_val, tmp_path / "exp", seeds=1, steps=2, tables=parse_tables("iii"), config=c, progress=lines.append)
    res = run_experiments(with_val, tmp_path / "exp", seeds=2, steps=2, tables=parse_tables("iii"), config=c, progress=lines.append)
    head = "ours (seed {k}, 2 steps; cameras + points + raw elevation, both ranges)"
    assert lines == [f"[1/1] {head.format(k=0)}: training", f"[1/1] {head.format(k=0)}: evaluating on val",
                     f"[1/2] {head.format(k=0)}: done", f"[2/2] {head.format(k=1)}: training", f"[2/2] {head.format(k=1)}: evaluating on val"]
    evs = [json.loads((tmp_path / "exp" / "runs" / f"ours-seed{k}" / "eval_val.json").read_text()) for k in (0, 1)]
    a, b = (e["elevation"]["short"]["model"]["total"]["mae_m"] for e in evs)
    assert a != b  # the seeds train different networks
    cell = res.tables[0]["rows"][0]["cells"][2]
    assert cell["mean"] == pytest.approx((a + b) / 2) and cell["spread"] == pytest.approx(abs(a - b) / np.sqrt(2))
    assert mean_and_spread(evs)["elevation"]["short"]["model"]["total"]["mae_m"] == pytest.approx(cell["mean"])
    vm = next(ln for ln in res.markdown_path.read_text().splitlines() if ln.startswith("| VM |"))
    cells = res.tables[0]["rows"][0]["cells"]
    differ = sum(1 for c in cells if None not in (c["mean"], c["spread"]) and c["spread"] > 1e-6 * abs(c["mean"]))
    assert vm.count("±") == differ >= 2  # the MAEs differ; an F1 both seeds share has no spread shown
    assert res.notes[-1].startswith("skipped N=1, N=2, N=5, N=10: the dataset holds no raw lidar scans")


def test_every_run_of_a_seed_comes_before_the_next_seed(monkeypatch, tmp_path):
    """A session cut short holds whole tables of the seeds it finished."""
    from gtgen.train import experiments as ex
    from gtgen.train import tables

    order = []

    def fake_run_one(dataset, identity, folder, cfg, split, baselines, say, overwrite):
        order.append(folder.name)
        return {"train_s": 0.0}, True

    monkeypatch.setattr(ex, "_run_one", fake_run_one)
    plan = ex._plan(False, tables.parse_tables("i,iv"))
    base = ex.load_config(None, ex.preset_overrides("tiny"), {})
    res = ex.ExperimentsResult(tmp_path, tmp_path / "e.json", tmp_path / "e.md", "val", [], [])
    ex._train_and_evaluate(tmp_path, "id", tmp_path, plan, base, 2, 3, "val", None, None, res)
    seeds = [int(name.rsplit("seed", 1)[1]) for name in order]
    assert seeds == sorted(seeds) and len(order) == 3 * len(plan.needed)
    assert order[: len(plan.needed)] == [f"{name}-seed0" for name in plan.needed]


def test_experiments_refuse_a_file_and_a_users_tables_before_training(with_val, tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    p = _experiments(with_val, afile, "--steps", "2", "--tables", "III")
    assert p.returncode == 1 and f"experiments folder '{afile}' is a file" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    out = tmp_path / "exp"
    out.mkdir()
    (out / "experiments.md").write_text("my notes")
    p = _experiments(with_val, out, "--steps", "2", "--tables", "III")
    assert p.returncode == 1 and "experiments.md' is an existing file that gtgen did not write" in p.stderr
    assert (out / "experiments.md").read_text() == "my notes" and not (out / "runs").exists() and afile.read_text() == "mine"


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_experiments_that_fail_before_any_run_leave_no_folder(with_val, tmp_path):
    out = tmp_path / "exp"
    p = _experiments(with_val, out, "--steps", "2", "--tables", "III", "--device", "cuda")
    assert p.returncode == 1 and "sees no CUDA device" in p.stderr
    assert not out.exists()


def test_results_are_tied_to_their_dataset(dataset, with_val, tmp_path):
    """A run resumed, or an experiments folder reused, on another dataset is one line
    naming both (before, experiments named B with A's numbers); the records themselves."""
    from gtgen.storage.dataset import DatasetStore
    from gtgen.train.experiments import run_experiments
    from gtgen.train.tables import parse_tables
    from gtgen.train.trainer import evaluate, train

    a, b = DatasetStore(dataset).identity, DatasetStore(with_val).identity
    assert a != b  # with_val differs from dataset in meta/split only
    cfg = _cfg(steps=2, ckpt_every=1, val_every=0)
    run = tmp_path / "exp" / "runs" / "ours-seed0"
    train(dataset, run, cfg, max_steps=1)
    assert json.loads((run / "metrics.json").read_text())["dataset"] == {"path": str(dataset), "identity": a}
    assert evaluate(dataset, run / "ckpt.pt", split=None)["dataset"]["identity"] == a
    with pytest.raises(TrainError) as err:
        train(with_val, run, cfg, resume=True)
    msg = str(err.value)
    assert f"'{dataset}' (identity {a})" in msg and f"'{with_val}' (identity {b})" in msg and "another --run-dir" in msg
    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump(SMALL_TRAIN))
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with pytest.raises(TrainError) as err:
        run_experiments(with_val, tmp_path / "exp", steps=2, tables=parse_tables("iv"), config=c)
    msg = str(err.value)
    assert f"identity {a}" in msg and f"identity {b}" in msg and "another -o folder" in msg and "\n" not in msg
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before  # nothing trained, no tables written


def test_a_datasets_identity_is_its_arrays(dataset, tmp_path):
    """The same arrays under other root attributes (a rebuild's timings) keep the identity;
    one chunk changed gives another."""
    import shutil

    import zarr

    from conftest import reseal
    from gtgen.storage.dataset import DatasetStore

    copy = tmp_path / "d.zarr"
    shutil.copytree(dataset, copy)
    zarr.open_group(str(copy), mode="r+").attrs["provenance"] = {"units": [{"seconds": {"extract": 1.0}}]}
    reseal(copy)
    assert DatasetStore(copy).identity == DatasetStore(dataset).identity
    g = zarr.open_group(str(copy), mode="r+")
    g["meta/icp_fitness"][0] = 0.5
    reseal(copy)
    assert DatasetStore(copy).identity != DatasetStore(dataset).identity


def test_experiments_overwrite_replaces_the_users_tables(with_val, tmp_path):
    """The refusal says 'pass --overwrite': experiments has that option (it had none)."""
    out = tmp_path / "exp"
    out.mkdir()
    (out / "experiments.md").write_text("my notes")
    p = _experiments(with_val, out, "--steps", "2", "--tables", "III")
    assert p.returncode == 1 and "--overwrite" in p.stderr
    p = _experiments(with_val, out, "--steps", "2", "--tables", "III", "--overwrite")
    assert p.returncode == 0, p.stderr
    assert (out / "experiments.md").read_text().startswith("<!-- written by gtgen")
