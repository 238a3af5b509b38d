"""Where and how training runs: devices, precision, torchrun (DDP), exact resume, curves,
validation and best.pt, and the trainer's edges (bad --steps, failed runs, full disks,
damaged checkpoints)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from conftest import run_cli
from gtgen.config import load_config
from gtgen.errors import ConfigError, GtgenError, TrainError
from test_train import SMALL_TRAIN


def _config_file(tmp_path: Path, **train) -> Path:
    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump({"train": {**SMALL_TRAIN["train"], **train}}))
    return c


def _state(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def test_resume_continues_the_same_run_bit_for_bit(dataset, tmp_path):
    from gtgen.train.trainer import train

    # mirroring on, random pillar points (2 per pillar, so the draw matters), and batches of
    # 16 of the 40 samples: 2 steps per epoch, so the resume starts a new epoch's order
    cfg = load_config(None, SMALL_TRAIN, {"train": {"batch_size": 16, "mirror_p": 0.5, "max_points_per_pillar": 2}})
    train(dataset, tmp_path / "straight", cfg, max_steps=4)
    train(dataset, tmp_path / "resumed", cfg, max_steps=2)
    train(dataset, tmp_path / "resumed", cfg, resume=True, max_steps=2)
    a, b = _state(tmp_path / "straight" / "ckpt.pt"), _state(tmp_path / "resumed" / "ckpt.pt")
    assert a["step"] == b["step"] == 4
    assert a["model"].keys() == b["model"].keys()
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    for sa, sb in zip(a["optim"]["state"].values(), b["optim"]["state"].values()):
        assert torch.equal(sa["exp_avg"], sb["exp_avg"]) and torch.equal(sa["exp_avg_sq"], sb["exp_avg_sq"])
    assert [h["total"] for h in a["history"]] == [h["total"] for h in b["history"]]


def test_the_step_sampler_splits_global_batches_and_resumes():
    from gtgen.train.sampler import StepBatchSampler

    one = StepBatchSampler(10, 4, seed=3)
    it = iter(one)
    steps = [next(it) for _ in range(6)]
    # two epochs of two full batches each (the 2 samples left over are dropped), each epoch
    # a permutation: no sample twice within an epoch
    for e in (0, 1):
        seen = steps[2 * e] + steps[2 * e + 1]
        assert len(set(seen)) == 8 and set(seen) <= set(range(10))
    assert steps[0] + steps[1] != steps[2] + steps[3]  # another permutation next epoch
    later = iter(StepBatchSampler(10, 4, seed=3, start_step=3))
    assert [next(later) for _ in range(3)] == steps[3:]
    for k in range(6):  # two processes see the global batch of one, in two halves
        assert StepBatchSampler(10, 4, 3, rank=0, world=2).step_indices(k) + StepBatchSampler(10, 4, 3, rank=1, world=2).step_indices(k) == steps[k]
    with pytest.raises(ConfigError, match="batch_size 3 is not a multiple of the 2 processes"):
        StepBatchSampler(10, 3, 0, world=2)


def test_torchrun_two_processes_train_like_one(dataset, tmp_path):
    torchrun = Path(sys.executable).parent / "torchrun"
    c = _config_file(tmp_path, batch_size=2)
    env = dict(os.environ, COLUMNS="200", OMP_NUM_THREADS="1")
    # docs/training.md's launch line (Several GPUs), as written
    cmd = [str(torchrun), "--standalone", "--nproc_per_node", "2", "-m", "gtgen", "train", str(dataset),
           "--steps", "2", "--run-dir", str(tmp_path / "runs" / "ddp"), "--config", str(c)]
    p = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600, env=env)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "lock" not in p.stderr and "Traceback" not in p.stderr
    run = tmp_path / "runs" / "ddp"
    assert sorted(x.name for x in run.glob("*.pt")) == ["ckpt.pt"]
    assert len(list((run / "tb").glob("events.out.tfevents.*"))) == 1
    assert p.stdout.count("gtgen train") == 1  # rank 0 alone reports
    m = json.loads((run / "metrics.json").read_text())
    assert m["processes"] == 2 and len(m["history"]) == 2
    # one process over the same global batch (batch 2 = 1 + 1): the same samples, mirror
    # and pillar draws. Elevation and consistency terms do not pass through a batch norm
    # at the first step (zero-initialised heads over the prior): equal to 1e-5. The risk
    # terms do, and gloo on CPU keeps each process's batch statistics (SyncBatchNorm is
    # CUDA's): the total within 2 %.
    from gtgen.train.trainer import train

    res = train(dataset, tmp_path / "runs" / "one", load_config(None, SMALL_TRAIN, {"train": {"batch_size": 2}}), max_steps=1)
    one = json.loads((tmp_path / "runs" / "one" / "metrics.json").read_text())["history"][0]
    two = m["history"][0]
    for k in ("micro/ele", "short/ele", "cons"):
        assert two[k] == pytest.approx(one[k], rel=1e-5), k
    assert two["total"] == pytest.approx(res.first_loss, rel=2e-2)


def test_bf16_autocast_step_on_cpu(dataset, tmp_path):
    from gtgen.train import distributed as D
    from gtgen.train.data import ShardDataset
    from gtgen.train.trainer import _collate, build_model, train

    cfg = load_config(None, SMALL_TRAIN, {"train": {"precision": "bf16-mixed"}})
    res = train(dataset, tmp_path / "run", cfg, max_steps=1)
    assert res.precision == "bf16-mixed" and np.isfinite(res.last_loss)
    ds = ShardDataset(dataset, cfg.train)
    model = build_model(cfg.train, ds.data_cfg)
    with D.autocast(torch.device("cpu"), "bf16-mixed"):
        pred = model(_collate([ds[0], ds[1]]))
    assert pred["short/risk_logit"].dtype == torch.bfloat16  # the convolutions ran in bf16
    assert D.resolve_precision("auto", torch.device("cpu")) == "32"


def test_devices_resolve_and_eval_runs_where_told(dataset, tmp_path, monkeypatch):
    from gtgen.train import distributed as D

    c = _config_file(tmp_path)
    p = run_cli("train", dataset, "--steps", "1", "--run-dir", tmp_path / "run", "--config", c, "--device", "cpu", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "cpu, precision 32" in p.stdout
    p = run_cli("eval", dataset, "--ckpt", tmp_path / "run" / "ckpt.pt", "--split", "all", "--device", "cpu", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert json.loads((tmp_path / "run" / "eval.json").read_text())["device"] == "cpu"
    if not torch.cuda.is_available():
        for cmd in (("eval", dataset, "--ckpt", tmp_path / "run" / "ckpt.pt", "--split", "all"),
                    ("viz", dataset, "--sample", "1", "--ckpt", tmp_path / "run" / "ckpt.pt", "-o", tmp_path / "v.png"),
                    ("train", dataset, "--steps", "1", "--run-dir", tmp_path / "cuda", "--config", c)):
            p = run_cli(*cmd, "--device", "cuda", cwd=tmp_path)
            assert p.returncode == 1 and "sees no CUDA device" in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
        assert not (tmp_path / "cuda").exists()
    p = run_cli("viz", dataset, "--sample", "1", "--ckpt", tmp_path / "run" / "ckpt.pt", "--device", "cpu", "-o", tmp_path / "v.png", cwd=tmp_path)
    assert p.returncode == 0 and (tmp_path / "v.png").is_file(), p.stderr
    with pytest.raises(ConfigError, match="'gpu' is not a torch device"):
        D.resolve_device("gpu")
    # auto takes CUDA when torch sees it, and under torchrun each process its LOCAL_RANK
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 4)
    assert D.resolve_device("auto") == torch.device("cuda", 0)
    assert D.resolve_device("cuda", D.Processes(rank=3, world=4, local_rank=1)) == torch.device("cuda", 1)
    assert D.resolve_device("cuda:2") == torch.device("cuda", 2)
    with pytest.raises(TrainError, match="only 4 CUDA devices"):
        D.resolve_device("cuda:7")


def test_curves_validation_best_and_resume_after_a_kill(with_val, tmp_path):
    from gtgen.train.curves import read_csv
    from gtgen.train.trainer import BEST_METRIC, train

    run = tmp_path / "run"
    cfg = load_config(None, SMALL_TRAIN, {"train": {"val_every": 2, "ckpt_every": 2}})
    res = train(with_val, run, cfg, max_steps=2)
    shutil.copy(run / "ckpt.pt", tmp_path / "at2.pt")
    train(with_val, run, cfg, resume=True, max_steps=1)  # steps 3, validated at the end
    killed = read_csv(run / "train.csv")
    assert [r["step"] for r in killed] == [1, 2, 3]
    # as if killed after step 3 before its checkpoint: back to the checkpoint of step 2
    shutil.copy(tmp_path / "at2.pt", run / "ckpt.pt")
    # TensorBoard names event files <second>.<host>.<pid>.<writer counter>: two writers of one
    # process in one second sort by the counter as text (.10 before .9) and replay out of order;
    # runs of a user are processes of their own, a second apart at least
    time.sleep(1.1)
    res = train(with_val, run, cfg, resume=True, max_steps=2)
    rows = read_csv(run / "train.csv")
    assert [r["step"] for r in rows] == [1, 2, 3, 4]  # the killed run's step 3 replaced, once
    assert rows[2]["total"] == killed[2]["total"]  # and redone identically
    assert all(r["data_s"] >= 0 and r["step_s"] > 0 for r in rows)
    val = read_csv(run / "val.csv")
    assert [r["step"] for r in val] == [2, 4]
    for r in val:
        assert r[BEST_METRIC] == pytest.approx((r["micro/mae_total_m"] + r["short/mae_total_m"]) / 2, rel=1e-5)  # CSV: 6 digits
        assert np.isfinite(r["loss"]) and (np.isnan(r["short/risk_f1"]) or 0 <= r["short/risk_f1"] <= 1)
    best = min(val, key=lambda r: r[BEST_METRIC])
    assert res.best == {"step": int(best["step"]), BEST_METRIC: pytest.approx(best[BEST_METRIC], rel=1e-5)}
    assert _state(run / "best.pt")["step"] == best["step"]
    events = list((run / "tb").glob("events.out.tfevents.*"))
    assert events
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run / "tb"))
    acc.Reload()
    assert [e.step for e in acc.Scalars("train/total")] == [1, 2, 3, 4]  # purged and rewritten
    assert [e.step for e in acc.Scalars(f"val/{BEST_METRIC}")] == [2, 4]


def test_bad_steps_and_failed_runs_leave_nothing(dataset, tmp_path, monkeypatch):
    from gtgen.train import trainer

    c = _config_file(tmp_path)
    for bad in ("0", "-3"):
        p = run_cli("train", dataset, "--steps", bad, "--config", c, cwd=tmp_path)
        assert p.returncode == 2 and "--steps" in p.stderr
    with pytest.raises(ConfigError, match="--steps 0: expected at least 1"):
        trainer.train(dataset, tmp_path / "runs" / "x", load_config(None, SMALL_TRAIN), max_steps=0)
    p = run_cli("train", tmp_path / "missing.zarr", "--steps", "1", "--config", c, cwd=tmp_path)
    assert p.returncode == 1 and "Traceback" not in p.stderr
    assert not (tmp_path / "runs").exists()
    # a failure after the run folder was made, before its first checkpoint: all of it removed
    def boom(*a, **k):
        raise TrainError("boom")

    monkeypatch.setattr(trainer, "total_loss", boom)
    with pytest.raises(TrainError, match="boom"):
        trainer.train(dataset, tmp_path / "runs" / "tiny", load_config(None, SMALL_TRAIN), max_steps=1)
    assert not (tmp_path / "runs").exists()
    # a finished run has nothing to resume
    monkeypatch.undo()
    cfg = load_config(None, SMALL_TRAIN, {"train": {"steps": 1}})
    trainer.train(dataset, tmp_path / "runs" / "done", cfg)
    with pytest.raises(TrainError, match="has trained all 1 steps"):
        trainer.train(dataset, tmp_path / "runs" / "done", cfg, resume=True)


def test_full_disk_while_saving_a_checkpoint_is_one_line(dataset, tmp_path):
    if shutil.which("unshare") is None or os.geteuid() != 0:
        pytest.skip("needs root and unshare to mount a small tmpfs")
    c = _config_file(tmp_path)
    mnt = tmp_path / "small"
    mnt.mkdir()
    # 256 KiB: the config, the curves and the events fit, the checkpoint (2.4 MB) does not
    script = (f"mount -t tmpfs -o size=256k none {mnt} && exec {sys.executable} -m gtgen train {dataset} --steps 1 "
              f"--run-dir {mnt}/runs/tiny --config {c}")
    p = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, timeout=600, env=dict(os.environ, COLUMNS="200"))
    if "mount" in p.stderr and p.returncode != 1:
        pytest.skip(f"cannot mount a tmpfs here: {p.stderr.strip()}")
    assert p.returncode == 1, p.stderr
    assert p.stderr.strip().splitlines() == [p.stderr.strip()] and "no space left on the device while writing" in p.stderr and "ckpt.pt" in p.stderr


def test_damaged_checkpoints_are_one_line_errors(dataset, tmp_path):
    c = _config_file(tmp_path)
    p = run_cli("train", dataset, "--steps", "1", "--run-dir", tmp_path / "run", "--config", c, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    good = (tmp_path / "run" / "ckpt.pt").read_bytes()
    (tmp_path / "truncated.pt").write_bytes(good[: len(good) // 2])
    flipped = bytearray(good)
    state = _state(tmp_path / "run" / "ckpt.pt")
    w = state["model"]["pillars.pfn.0.weight"].contiguous().view(torch.uint8).numpy().tobytes()
    at = bytes(good).find(w[:64])  # inside that tensor's stored bytes
    assert at > 0
    flipped[at + 8] ^= 0x40
    (tmp_path / "flipped.pt").write_bytes(bytes(flipped))
    state["model"]["enc1.a.0.weight"] = state["model"]["enc1.a.0.weight"][:1]  # a checkpoint of another model
    from gtgen.train.checkpoint import weights_digest

    state["model_sha256"] = weights_digest(state["model"])
    torch.save(state, tmp_path / "other.pt")
    for name, msg in (("truncated.pt", "cannot be read"), ("flipped.pt", "cannot be read|is damaged"), ("other.pt", "do not fit its model")):
        for cmd in (("eval", dataset, "--split", "all"), ("viz", dataset, "--sample", "0", "-o", tmp_path / "v.png")):
            p = run_cli(*cmd, "--ckpt", tmp_path / name, cwd=tmp_path)
            assert p.returncode == 1 and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1, (name, p.stderr)
            import re

            assert re.search(msg, p.stderr), (name, p.stderr)
    with pytest.raises(GtgenError):
        from gtgen.train.checkpoint import load_checkpoint

        load_checkpoint(tmp_path / "flipped.pt")


def test_gpu_check_script_runs_in_its_cpu_mode(dataset, tmp_path):
    if torch.cuda.is_available():
        pytest.skip("the GPU mode trains the paper preset for 300 steps")
    root = Path(__file__).resolve().parent.parent
    env = dict(os.environ, GPU_CHECK_OUT=str(tmp_path / "gc"), GPU_CHECK_STEPS="2", GPU_CHECK_REPEATS="2",
               PYTHON=sys.executable)
    p = subprocess.run(["bash", str(root / "scripts" / "gpu_check.sh"), str(dataset)], capture_output=True, text=True, timeout=600, env=env)
    assert p.returncode == 0, p.stderr[-3000:]
    out = {line[:28].strip(): line[29:] for line in p.stdout.splitlines()[1:]}  # "key (padded to 28) value"
    assert p.stdout.startswith("gpu_check: cpu mode (tiny preset, 2 steps on cpu)")
    assert "steps/s" in out["training"] and "samples/s" in out["training"] and out["peak GPU memory (training)"] == "n/a (CPU)"
    assert "ms per sample on cpu" in out["eval"] and "ms per sample (batch 1, 32)" in out["inference latency"]
    assert json.loads((tmp_path / "gc" / "runs" / "tiny" / "metrics.json").read_text())["processes"] == 1


def test_paper_faithful_config_holds_the_papers_choices():
    from gtgen.config import configs_dir
    from gtgen.train.presets import preset_overrides

    cfg = load_config(configs_dir() / "paper_faithful.yaml", preset_overrides("paper"))
    tc = cfg.train
    assert (tc.risk_loss, tc.elevation_beta_m, tc.mirror_p) == ("mse", tc.elevation_clip_m, 0.0)  # Smooth-L1's beta 1 on the +-1 scale
    assert (tc.batch_size, tc.steps, tc.lr, tc.image_backbone) == (6, 16000, 5e-4, "efficientnet_b0")
    assert (tc.alpha, tc.mu, tc.lam, tc.gamma) == (0.2, 2.0, 2.0, 5.0)


class _Touch:
    """A pickle that, loaded with Python's full unpickler, runs code (touches a file)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return (Path.touch, (self.path,))


def test_a_checkpoint_is_loaded_as_data_never_run(tmp_path):
    """eval, viz and export take checkpoints from anywhere: one that would run code when
    unpickled is refused without running it, and a folder is named as one."""
    from gtgen.train.checkpoint import load_checkpoint

    marker = tmp_path / "ran"
    torch.save({"version": 5, "model": {}, "x": _Touch(marker)}, tmp_path / "evil.pt")
    with pytest.raises(TrainError, match="cannot be read") as err:
        load_checkpoint(tmp_path / "evil.pt")
    assert not marker.exists() and "\n" not in str(err.value)
    with pytest.raises(TrainError, match="is a folder, not a checkpoint file"):
        load_checkpoint(tmp_path)


@pytest.mark.parametrize("free_gib, says", [(12.0, "train.batch_size: 2 needs about"), (3.0, "even train.batch_size: 1 needs about")])
def test_a_run_that_does_not_fit_the_memory_stops_before_any_work(dataset, tmp_path, monkeypatch, free_gib, says):
    """The paper preset at its batch 6 on the CPU was killed by the kernel mid-step; now it
    is one line saying what fits, before the model or the data are touched (the free
    memory injected, nothing allocated)."""
    from gtgen.train import memory
    from gtgen.train.trainer import preset_overrides, train

    monkeypatch.setattr(memory, "available_bytes", lambda device: int(free_gib * 2**30))
    cfg = load_config(None, preset_overrides("paper"))
    with pytest.raises(TrainError) as err:
        train(dataset, tmp_path / "run", cfg, device="cpu")
    msg = str(err.value)
    assert msg.startswith("the paper preset at train.batch_size 6 needs about") and says in msg and "\n" not in msg, msg
    assert f"{free_gib:.1f} GiB is free" in msg and "train.check_memory: false" in msg
    assert not (tmp_path / "run").exists()
    from gtgen.train.memory import need_gib

    assert need_gib(cfg.train, 1) == pytest.approx(5.0, abs=0.3)  # the README's measured peak RSS at batch 1
    assert need_gib(cfg.train, 6) > 20.0  # killed at 21.5 GB (20.0 GiB) before the step ended


def test_torchrun_into_a_busy_run_folder_says_it_once(dataset, tmp_path):
    """Every rank stops; rank 0 alone prints the one-line cause (torchrun's own report of
    the failed processes follows it: the README says so)."""
    from gtgen.runtime.output import lock

    torchrun = Path(sys.executable).parent / "torchrun"
    run = tmp_path / "runs" / "busy"
    run.mkdir(parents=True)
    env = dict(os.environ, COLUMNS="200", OMP_NUM_THREADS="1")
    cmd = [str(torchrun), "--standalone", "--nproc_per_node", "2", "-m", "gtgen", "train", str(dataset), "--steps", "1",
           "--run-dir", str(run), "--config", str(_config_file(tmp_path, batch_size=2))]
    with lock(run):
        p = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600, env=env)
    assert p.returncode == 1
    errors = [ln for ln in p.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "is being written by another gtgen command" in errors[0], p.stderr[-3000:]
