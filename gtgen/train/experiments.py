"""``gtgen experiments``: the paper's Tab. I-IV (Sec. IV) on one dataset, every row trained and evaluated.

A table row is made of runs: one network for both ranges, or one per range for the paper's
single-range baselines. A run is trained with ``trainer.train``, one folder per seed
(``<out>/runs/<run>-seed<k>/``), and evaluated with ``trainer.evaluate`` on the test split
(the val split when the dataset has none). Rows that are the same training share its runs:
Ours is Tab. III's VM and Tab. IV's UL + CL. A run whose evaluation is on disk is neither
retrained nor re-evaluated; a run with a checkpoint short of its steps resumes from it;
a run folder trained with other settings is refused. The tables go to ``experiments.json``
(numbers) and ``experiments.md`` (the paper's layout, the paper's numbers beside ours).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from gtgen import codes
from gtgen.config import RANGES, GtgenConfig, load_config, read_yaml
from gtgen.errors import ConfigError, TrainError
from gtgen.runtime.output import check_replace, lock, output_folder, write_atomic, write_json
from gtgen.storage.dataset import DatasetStore
from gtgen.train.checkpoint import load_checkpoint
from gtgen.train.data import NO_SCANS
from gtgen.train.presets import PRESETS, preset_overrides
from gtgen.train.runs import METRICS, dataset_record, describe, recorded_dataset, same_dataset
from gtgen.train.tables import TABLES, Table, markdown, paper_tables, table_value
from gtgen.train.trainer import evaluate, mean_and_spread, train

# steps of every run per preset unless --steps. The tiny preset's 15 runs of one seed cost
# about 13 runs of the full network (bench/experiments.py: a micro-only network as much as
# the full one, its image branch and micro head being the same; a short-only one 0.8, the
# camera-only and point-only ones 0.5 to 0.8), so at 0.3 to 0.5 s a step 400 steps take 26
# to 43 minutes on 2 cores, with room in the hour for the evaluations and the scans'
# loading; other presets train their own steps
DEFAULT_STEPS = {"tiny": 400}
# raw scans of the lidar input ("L") of the PointPillars and RoadRunner rows: Tab. III's largest N
L_SCANS = 10


@dataclass(frozen=True)
class Run:
    """One network to train: its switches over the preset (``train`` keys), and whether it
    reads raw scans."""

    train: dict[str, Any]
    scans: bool = False

    @property
    def ranges(self) -> tuple[str, ...]:
        r = self.train.get("ranges", "both")
        return RANGES if r == "both" else (r,)


def _runs(scans: bool, cameras: bool = True) -> dict[str, Run]:
    """Return every run of the tables by name; the lidar input "L" is the raw scans when the
    dataset has them (``scans``), else the voxel map; without ``cameras`` (a dataset without
    images) every run that has other inputs trains without the camera one."""
    out = _all_runs(scans)
    if cameras:
        return out
    return {name: r if _cameras_only(r) else Run({**r.train, "cameras": False}, r.scans) for name, r in out.items()}


def _all_runs(scans: bool) -> dict[str, Run]:
    lidar = {"geometry": "scans", "n_scans": L_SCANS} if scans else {}
    out = {"ours": Run({})}
    for r in RANGES:
        out[f"ours-{r}"] = Run({"ranges": r})
        out[f"lss-{r}"] = Run({"cameras": True, "points": False, "raw_elevation": False, "ranges": r})
        out[f"pp-{r}"] = Run({"cameras": False, "points": True, "raw_elevation": False, "ranges": r, **lidar}, scans)
        out[f"rr-{r}"] = Run({"geometry": "scans", "n_scans": L_SCANS, "ranges": r}, True)
    for n in (1, 2, 5, 10):
        out[f"scans-{n}"] = Run({"geometry": "scans", "n_scans": n}, True)
    out["ul"] = Run({"gamma": 0.0})
    out["cl"] = Run({"alpha": 0.0})
    return out


@dataclass
class ExperimentsResult:
    """What ``run_experiments`` did and found (``tables``: as in ``experiments.json``)."""

    out: Path
    json_path: Path
    markdown_path: Path
    split: str
    notes: list[str]
    tables: list[dict]
    trained: list[str] = field(default_factory=list)
    reused: list[str] = field(default_factory=list)
    train_s: float = 0.0


@dataclass(frozen=True)
class _Plan:
    """What a dataset allows of the asked tables: the tables, every run by name, the lines
    skipped for want of raw scans, and the runs to train, in table order."""

    tables: list[Table]
    runs: dict[str, Run]
    skipped: list[str]
    needed: list[str]
    no_cameras: list[str] = field(default_factory=list)  # lines skipped for want of camera images


def run_experiments(dataset: Path, out: Path, preset: str = "tiny", seeds: int = 1, steps: int | None = None,
                    tables: tuple[str, ...] = TABLES, config: Path | None = None, device: str | None = None,
                    progress: Callable[[str], None] | None = None, overwrite: bool = False) -> ExperimentsResult:
    """Train and evaluate every run of ``tables`` for ``seeds`` seeds (train.seed, +1, ...)
    into ``out``, and write ``experiments.json`` and ``experiments.md`` there. ``steps``
    overrides the steps of every run (default ``DEFAULT_STEPS`` or the preset's);
    ``config`` is a partial YAML under every run's own switches (its train.steps, if any,
    counts as ``steps``). ``progress`` is told in one line what each run is doing. A file of
    the user's where an output goes is replaced only with ``overwrite``."""
    if seeds < 1:
        raise ConfigError(f"--seeds {seeds}: expected at least 1 seed")
    if steps is not None and steps < 1:
        raise ConfigError(f"--steps {steps}: expected at least 1 step")
    user = read_yaml(config) if config is not None else {}
    base = load_config(None, preset_overrides(preset), user)
    n_steps = steps or (user.get("train") or {}).get("steps") or DEFAULT_STEPS.get(preset, PRESETS[preset].train["steps"])
    if out.exists() and not out.is_dir():
        raise TrainError(f"experiments folder '{out}' is a file; choose another -o")
    for path in (out / "experiments.json", out / "experiments.md"):  # before an hour of training, not after
        check_replace(path, overwrite)
    store = DatasetStore(dataset)
    split, notes = _eval_split(store)
    plan = _plan(store.has_scans, tables, bool(store.cameras))
    if plan.skipped:
        notes.append(f"skipped {', '.join(plan.skipped)}: the dataset {NO_SCANS}")
    if plan.no_cameras:
        notes.append(f"skipped {', '.join(plan.no_cameras)}: the dataset holds no camera images (the other rows train without "
                     "their camera input)")
    res = ExperimentsResult(out, out / "experiments.json", out / "experiments.md", split, notes, [])
    with output_folder(out), lock(out):
        _check_dataset(out, store)
        evals = _train_and_evaluate(dataset, store.identity, out, plan, base, n_steps, seeds, split, device, progress, res, overwrite)
        res.tables = [_fill(t, {name: mean_and_spread(evs) for name, evs in evals.items()}, plan, seeds) for t in plan.tables]
        summary = {"dataset": str(dataset), "dataset_identity": store.identity, "split": split, "preset": preset, "steps": n_steps, "seeds": seeds, "notes": notes,
                   "runs": {name: {"train": plan.runs[name].train, "folders": [str(_folder(out, name, base.train.seed + k))
                                                                               for k in range(seeds)]} for name in evals},
                   "train_s": res.train_s, "tables": res.tables}
        write_json(res.json_path, summary, overwrite, indent=1)
        write_atomic(res.markdown_path, markdown(res.tables, summary), overwrite)
    return res


def _check_dataset(out: Path, store: DatasetStore) -> None:
    """Raise TrainError when the experiments folder ``out`` holds results of another dataset
    than ``store`` (its tables, or any run): they are never reused, nor mixed with this
    dataset's."""
    try:
        doc = json.loads((out / "experiments.json").read_text())
        found = [(out / "experiments.json", {"path": doc.get("dataset"), "identity": doc.get("dataset_identity")}
                  if doc.get("dataset_identity") else None)]
    except (OSError, ValueError, AttributeError):
        found = []
    runs = out / "runs"
    if runs.is_dir():
        found += [(f, recorded_dataset(f)) for f in sorted(runs.iterdir())
                  if f.is_dir() and not f.is_symlink() and ((f / "ckpt.pt").is_file() or (f / METRICS).is_file())]
    for where, rec in found:
        if not same_dataset(rec, store):
            raise TrainError(f"experiments folder '{out}' holds results of {describe(rec)} ('{where}'), not of "
                             f"{describe(dataset_record(store))}; write these experiments to another -o folder, or remove "
                             f"'{out}' to run them anew on this dataset")


def _plan(scans: bool, numbers: tuple[str, ...], cameras: bool = True) -> _Plan:
    """Return the plan of tables ``numbers`` on a dataset with raw scans or without, with
    camera images or without (the rows whose only input is the cameras are skipped)."""
    runs = _runs(scans, cameras)
    tables = [t for t in paper_tables("L (raw scans)" if scans else "L (VM: no raw scans)", cameras) if t.number in numbers]
    lines = [ln for t in tables for ln in t.lines]
    skipped = [] if scans else list(dict.fromkeys(ln.label for ln in lines if any(runs[r].scans for r in ln.runs)))
    blind = [] if cameras else list(dict.fromkeys(ln.label for ln in lines if ln.label not in skipped and any(_cameras_only(runs[r]) for r in ln.runs)))
    needed = list(dict.fromkeys(r for ln in lines if ln.label not in skipped + blind for r in ln.runs))
    return _Plan(tables, runs, skipped, needed, blind)


def _cameras_only(run: Run) -> bool:
    """Whether the run's only input is the cameras."""
    t = run.train
    return t.get("cameras", True) and not t.get("points", True) and not t.get("raw_elevation", True)


def _folder(out: Path, run: str, seed: int) -> Path:
    return out / "runs" / f"{run}-seed{seed}"


def _train_and_evaluate(dataset: Path, identity: str, out: Path, plan: _Plan, base: GtgenConfig, steps: int, seeds: int, split: str,
                        device: str | None, progress: Callable[[str], None] | None, res: ExperimentsResult,
                        overwrite: bool = False) -> dict[str, list[dict]]:
    """Return the evaluations of every needed run per seed, training what is not done;
    record in ``res`` what was trained and what was found done. Every run of one seed comes
    before the next seed, so a session cut short holds whole tables of the seeds it finished."""
    evals: dict[str, list[dict]] = {}
    todo = [(name, base.train.seed + k) for k in range(seeds) for name in plan.needed]
    for i, (name, seed) in enumerate(todo, 1):
        run = plan.runs[name]
        folder = _folder(out, name, seed)
        say = _teller(progress, f"[{i}/{len(todo)}] {name} (seed {seed}, {steps} steps; {_describe(run)})")
        ev, trained = _run_one(dataset, identity, folder, _run_config(base, run, steps, seed, device), split, name == "ours", say, overwrite)
        (res.trained if trained else res.reused).append(folder.name)
        res.train_s += ev["train_s"]
        evals.setdefault(name, []).append(ev)
    return evals


def _eval_split(store: DatasetStore) -> tuple[str, list[str]]:
    """Return the split the runs are evaluated on, and a note when it is not the test split."""
    splits = store.splits
    if "test" in codes.SPLITS.values() and len(splits["test"]):
        return "test", []
    if not len(splits.get("val", ())):
        raise TrainError(f"dataset '{store.path}' has neither test nor val samples to evaluate on; build it with more drives "
                         "or smaller shards.split_block_m")
    return "val", ["the dataset has no test split: every run is evaluated on the val split (the runs do not validate on it)"]


def _teller(progress: Callable[[str], None] | None, head: str) -> Callable[[str], None]:
    """Return a function telling ``progress`` (if any) "``head``: <state>"."""
    return (lambda state: progress(f"{head}: {state}")) if progress is not None else (lambda state: None)


def _describe(run: Run) -> str:
    """Return the run's inputs, ranges and loss changes in words."""
    t = run.train
    points = f"{t['n_scans']} scans" if t.get("geometry") == "scans" else "points"
    parts = [name for name, key in (("cameras", "cameras"), (points, "points"), ("raw elevation", "raw_elevation")) if t.get(key, True)]
    rng = t.get("ranges", "both")
    extra = [f"{k} {v:g}" for k, v in t.items() if k in ("alpha", "gamma")]
    return f"{' + '.join(parts)}, {'both ranges' if rng == 'both' else rng + ' range alone'}" + "".join(f", {e}" for e in extra)


def _run_config(base: GtgenConfig, run: Run, steps: int, seed: int, device: str | None) -> GtgenConfig:
    """Return the config of one run: the base, the experiments' schedule (no validation: the
    run is evaluated after; a checkpoint at least every tenth of the run, so a killed run
    loses at most that), the run's switches and the seed."""
    ckpt_every = min(base.train.ckpt_every, max(1, steps // 10))
    layer = {"steps": steps, "val_every": 0, "ckpt_every": ckpt_every, "seed": seed, **run.train, **({"device": device} if device else {})}
    return load_config(None, base.model_dump(mode="json"), {"train": layer})


def _run_one(dataset: Path, identity: str, folder: Path, cfg: GtgenConfig, split: str, baselines: bool,
             say: Callable[[str], None], overwrite: bool = False) -> tuple[dict, bool]:
    """Return the evaluation of the run in ``folder`` (training or resuming it first when
    short of its steps; its evaluation on disk reused only when of the dataset of
    ``identity``) and whether it trained now; ``say`` is told what it does."""
    tc = cfg.train
    done = folder / f"eval_{split}.json"
    _same_settings(folder, cfg)
    step = load_checkpoint(folder / "ckpt.pt")[0]["step"] if (folder / "ckpt.pt").is_file() else 0
    trained = step < tc.steps
    if trained:
        say(f"resuming at step {step}" if step else "training")
        train(dataset, folder, cfg, resume=step > 0, overwrite=overwrite)
    elif done.is_file():
        ev = json.loads(done.read_text())
        ev.pop("written_by", None)  # the file's signature, not a result: the fresh evaluations of other seeds have none
        if ev.get("step") == tc.steps and (ev.get("dataset") or {}).get("identity") == identity:
            say("done")
            return ev, False
    say(f"evaluating on {split}")
    ev = evaluate(dataset, folder / "ckpt.pt", split=split, device=tc.device, baselines=baselines)
    history = json.loads((folder / METRICS).read_text())["history"]
    ev["train_s"] = sum(h["data_s"] + h["step_s"] for h in history)
    write_json(done, ev, overwrite, indent=1)
    return ev, trained


def _same_settings(folder: Path, cfg: GtgenConfig) -> None:
    """Raise ConfigError when ``folder`` holds a run trained with other settings than ``cfg``
    (the device aside)."""
    saved = folder / "gtgen-config.yaml"
    if not saved.is_file():
        return
    old = yaml.safe_load(saved.read_text()) or {}
    new = cfg.model_dump(mode="json")
    for section, values in new.items():
        for key, value in (values.items() if isinstance(values, dict) else ()):
            if section == "train" and key == "device":
                continue
            was = (old.get(section) or {}).get(key)
            if was != value:
                raise ConfigError(f"run folder '{folder}' was trained with {section}.{key} = {was!r}, not {value!r}; "
                                  "remove it, or write these experiments to another -o folder")


def _fill(table: Table, reduced: dict[str, dict], plan: _Plan, seeds: int) -> dict:
    """Return ``table`` with our numbers: per line and column the mean, spread (over seeds)
    and coverage of the labelled cells [%], and the paper's."""
    rows = []
    for ln in table.lines:
        if ln.label in plan.skipped or ln.label in plan.no_cameras:
            continue
        cells = []
        for j, m in enumerate(table.metrics):
            run = next(r for r in ln.runs if m.rng in plan.runs[r].ranges)
            cells.append({"run": run, **table_value(reduced[run], m, ln.method, seeds),
                          "paper": ln.paper[j], "paper_coverage_pct": ln.paper_coverage[j] if ln.paper_coverage else None})
        rows.append({"label": ln.label, "inputs": ln.inputs, "method": ln.method, "cells": cells})
    return {"number": table.number, "title": table.title, "columns": [m.header for m in table.metrics],
            "digits": [m.digits for m in table.metrics], "rows": rows}
