"""What one seed of ``gtgen experiments`` costs with the tiny preset on this machine: the
seconds per training step of every run kind (the full network, the single-range ones, those
without cameras or points), each against the full network's, the evaluation's seconds per
sample, and from them the projected minutes of one seed at the experiments' default steps
(``gtgen.train.experiments.DEFAULT_STEPS``), against the hour the command promises on 2 cores.

Each run trains ``BENCH_EXPERIMENT_STEPS`` steps (default 12; the first step, with its
start-up, is left out of the rates) on the demo-sized dataset bench/train.py builds (or
``BENCH_DATASET``).
"""

from __future__ import annotations

import json
import os
import shutil
import time

from _common import OUT, bench_dataset, header

if __name__ == "__main__":
    header("bench/experiments.py")
    from gtgen.config import load_config
    from gtgen.storage.dataset import DatasetStore
    from gtgen.train.experiments import DEFAULT_STEPS, _plan, _run_config
    from gtgen.train.presets import preset_overrides
    from gtgen.train.trainer import evaluate, train

    dataset = bench_dataset()
    store = DatasetStore(dataset)
    plan = _plan(store.has_scans, ("I", "II", "III", "IV"))
    steps = int(os.environ.get("BENCH_EXPERIMENT_STEPS", "12"))
    base = load_config(None, preset_overrides("tiny"))
    root = OUT / "experiments"
    per_step = {}
    kinds = {}  # runs that are the same network at another loss weight cost the same: timed once
    for name in plan.needed:
        run = plan.runs[name]
        key = json.dumps({k: v for k, v in run.train.items() if k not in ("alpha", "gamma")}, sort_keys=True)
        if key in kinds:
            per_step[name] = per_step[kinds[key]]
            continue
        kinds[key] = name
        folder = root / name
        shutil.rmtree(folder, ignore_errors=True)
        train(dataset, folder, _run_config(base, run, steps, 0, "cpu"))
        history = json.loads((folder / "metrics.json").read_text())["history"][1:]
        per_step[name] = sum(h["data_s"] + h["step_s"] for h in history) / len(history)
    split = "test" if "test" in store.splits and len(store.splits["test"]) else "val"
    t = time.perf_counter()
    ev = evaluate(dataset, root / "ours" / "ckpt.pt", split=split, device="cpu")
    eval_ours = time.perf_counter() - t
    t = time.perf_counter()
    evaluate(dataset, root / "ours-micro" / "ckpt.pt", split=split, device="cpu", baselines=False)
    eval_other = time.perf_counter() - t
    full = per_step["ours"]
    for name, s in per_step.items():
        print(f"{name:11s} {s:.3f} s per step ({s / full:.2f}x the full network)")
    n = DEFAULT_STEPS["tiny"]
    train_min = sum(per_step.values()) * n / 60
    eval_min = (eval_ours + (len(per_step) - 1) * eval_other) / 60
    print(f"evaluation on {split} ({ev['samples']} samples): {eval_ours:.1f} s with the baseline rows (the Ours run), "
          f"{eval_other:.1f} s without (each other run)")
    print(f"one seed of {len(per_step)} runs at {n} steps: {train_min:.1f} min training + {eval_min:.1f} min evaluation = "
          f"{train_min + eval_min:.1f} min (promise: about 60 min on 2 cores; {sum(per_step.values()) / full:.1f} full-network runs)")
    shutil.rmtree(root, ignore_errors=True)
