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
from gtgen.report.stats import PAPER_REGION_SHARE_PCT, PAPER_XRACER_AT_T
from gtgen.runtime.output import check_replace, lock, output_folder, signature, write_atomic, write_json
from gtgen.storage.dataset import DatasetStore
from gtgen.train.checkpoint import load_checkpoint
from gtgen.train.data import NO_SCANS
from gtgen.train.presets import PRESETS, preset_overrides
from gtgen.train.runs import METRICS, dataset_record, describe, recorded_dataset, same_dataset
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
TABLES = ("I", "II", "III", "IV")
REGIONS = ("obs_pc", "obs_f", "unobs", "total")
REGION_NAMES = {"obs_pc": "obs PC", "obs_f": "obs F", "unobs": "unobs", "total": "Total"}


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


@dataclass(frozen=True)
class Metric:
    """A column: ``kind`` mae (elevation MAE of region ``key``), risk (``key``: mse, precision,
    recall, f1) or cons (the consistency MAE), of range ``rng``."""

    header: str
    rng: str
    kind: str
    key: str = ""
    digits: int = 3

    def path(self, method: str) -> tuple[str, ...]:
        """Return the path of the value in an evaluation result (``method``: its row; "share":
        the region's share of the labelled cells)."""
        if self.kind == "cons":
            return ("consistency_mae_m",)
        if self.kind == "risk":
            return ("risk", self.rng, method, self.key)
        if method == "share":
            return ("elevation", self.rng, "model", self.key, "share_pct")
        return ("elevation", self.rng, method, self.key, "mae_m")


@dataclass(frozen=True)
class Line:
    """A table row: the runs it needs (the one giving a column is the one predicting its
    range), the evaluation row it reads (``method``: model, or a baseline row of the Ours run
    such as xracer), and the paper's numbers per column (None: not in the paper)."""

    label: str
    inputs: str
    runs: tuple[str, ...]
    paper: tuple[float | None, ...]
    method: str = "model"
    paper_coverage: tuple[float | None, ...] = ()


@dataclass(frozen=True)
class Table:
    number: str
    title: str
    metrics: tuple[Metric, ...]
    lines: tuple[Line, ...]


def _per_range(stem: str) -> tuple[str, ...]:
    return tuple(f"{stem}-{r}" for r in RANGES)


def _xracer_tab1(r: str, key: str) -> tuple[float | None, ...]:
    """Return the paper's X-Racer-at-t Tab. I columns (obs PC, obs F, unobs, total) of ``key``."""
    return (*PAPER_XRACER_AT_T[r][key].values(), None)


def _xracer_tab2(r: str) -> tuple[float | None, ...]:
    """Return the paper's X-Racer-at-t Tab. II columns (MSE, precision, recall, F1)."""
    return tuple(PAPER_XRACER_AT_T[r]["risk"][k] for k in ("mse", "precision", "recall", "f1"))


# the paper's numbers (Tab. I-IV); Tab. I's share row is each region's share of the labelled cells [%]
_TAB1 = {
    "micro": {"share": (*PAPER_REGION_SHARE_PCT["micro"].values(), None), "lss": (0.819, 1.01, 2.093, 1.167), "pp": (0.41, 0.545, 1.208, 0.635),
              "xracer": _xracer_tab1("micro", "mae_m"), "xracer_cov": _xracer_tab1("micro", "coverage_pct"), "rr": (0.399, 0.592, 1.629, 0.738),
              "womr": (0.241, 0.422, 1.261, 0.532), "ours": (0.215, 0.318, 0.869, 0.396)},
    "short": {"share": (*PAPER_REGION_SHARE_PCT["short"].values(), None), "lss": (1.489, 1.948, 3.606, 2.638), "pp": (0.732, 0.868, 1.992, 1.368),
              "xracer": _xracer_tab1("short", "mae_m"), "xracer_cov": _xracer_tab1("short", "coverage_pct"), "rr": (0.418, 0.852, 2.311, 1.453),
              "womr": (0.276, 0.627, 1.835, 1.126), "ours": (0.288, 0.65, 1.874, 1.155)},
}
_TAB2 = {  # MSE, precision, recall, F1 (the paper's X-Racer F1 is as printed there)
    "micro": {"lss": (0.0104, 0.363, 0.113, 0.173), "pp": (0.0086, 0.466, 0.189, 0.269), "xracer": _xracer_tab2("micro"),
              "xracer_cov": (None, PAPER_XRACER_AT_T["micro"]["risk"]["coverage_pct"], None, None), "rr": (0.0086, 0.501, 0.207, 0.293), "womr": (0.0080, 0.519, 0.240, 0.329),
              "ours": (0.0076, 0.523, 0.272, 0.357)},
    "short": {"lss": (0.0237, 0.241, 0.241, 0.241), "pp": (0.0173, 0.431, 0.291, 0.347), "xracer": _xracer_tab2("short"),
              "xracer_cov": (None, PAPER_XRACER_AT_T["short"]["risk"]["coverage_pct"], None, None), "rr": (0.0175, 0.433, 0.305, 0.358), "womr": (0.0165, 0.473, 0.343, 0.397),
              "ours": (0.0166, 0.465, 0.345, 0.396)},
}
_TAB3 = {1: (0.592, 0.304, 1.563, 0.331), 2: (0.521, 0.307, 1.372, 0.350), 5: (0.466, 0.316, 1.299, 0.358),
         10: (0.438, 0.331, 1.115, 0.375), "VM": (0.403, 0.358, 1.136, 0.394)}
_TAB4 = {"UL": (0.229, 0.333, 0.853, 0.298, 0.655, 1.849, 0.18), "CL": (0.216, 0.347, 1.246, 0.278, 1.025, 3.575, 0.08),
         "UL + CL": (0.215, 0.319, 0.870, 0.289, 0.650, 1.874, 0.09)}


def _tables(lidar: str, cameras: bool = True) -> list[Table]:
    """Return the paper's tables; ``lidar`` names the "L" input of this dataset, and without
    ``cameras`` the rows' inputs go without "C" (the runs' camera input is off)."""
    if not cameras:
        return [_without_cameras(t) for t in _tables(lidar)]
    out = []
    for r in RANGES:
        p = _TAB1[r]
        out.append(Table("I", f"Tab. I, {r} range: elevation MAE [m] (in brackets: coverage of the labelled cells)",
                         tuple(Metric(REGION_NAMES[k], r, "mae", k) for k in REGIONS), (
            Line("share of the labelled cells [%]", "", ("ours",), p["share"], "share"),
            Line("LSS", "C", _per_range("lss"), p["lss"]),
            Line("PointPillars", lidar, _per_range("pp"), p["pp"]),
            Line("X-Racer at t", "C + VM", ("ours",), p["xracer"], "xracer", p["xracer_cov"]),
            Line("raw min z, nearest-filled", "VM", ("ours",), (None,) * 4, "raw_nearest"),
            Line("RoadRunner", "C + L + E", _per_range("rr"), p["rr"]),
            Line("Ours w/o MR", "C + VM", _per_range("ours"), p["womr"]),
            Line("Ours", "C + VM", ("ours",), p["ours"]))))
    for r in RANGES:
        p = _TAB2[r]
        out.append(Table("II", f"Tab. II, {r} range: risk (fatal: risk >= train.fatal_risk)",
                         tuple(Metric(h, r, "risk", k, 4 if k == "mse" else 3) for h, k in
                               (("MSE", "mse"), ("Precision", "precision"), ("Recall", "recall"), ("F1", "f1"))), (
            Line("LSS", "C", _per_range("lss"), p["lss"]),
            Line("PointPillars", lidar, _per_range("pp"), p["pp"]),
            Line("X-Racer at t", "C + VM", ("ours",), p["xracer"], "xracer", p["xracer_cov"]),
            Line("RoadRunner", "C + L + E", _per_range("rr"), p["rr"]),
            Line("Ours w/o MR", "C + VM", _per_range("ours"), p["womr"]),
            Line("Ours", "C + VM", ("ours",), p["ours"]))))
    out.append(Table("III", "Tab. III: point cloud accumulation (elevation MAE [m] over all labelled cells, risk F1)",
                     (Metric("micro MAE", "micro", "mae", "total"), Metric("micro F1", "micro", "risk", "f1"),
                      Metric("short MAE", "short", "mae", "total"), Metric("short F1", "short", "risk", "f1")),
                     tuple(Line(f"N={n}", "C + N scans", (f"scans-{n}",), _TAB3[n]) for n in (1, 2, 5, 10))
                     + (Line("VM", "C + VM (= Ours)", ("ours",), _TAB3["VM"]),)))
    out.append(Table("IV", "Tab. IV: the loss (UL: unobserved loss, CL: consistency loss); elevation MAE [m]",
                     tuple(Metric(f"{r} {REGION_NAMES[k]}", r, "mae", k) for r in RANGES for k in REGIONS[:3])
                     + (Metric("Cons. MAE", "micro", "cons"),),
                     (Line("UL", "gamma = 0", ("ul",), _TAB4["UL"]), Line("CL", "alpha = 0", ("cl",), _TAB4["CL"]),
                      Line("UL + CL", "= Ours", ("ours",), _TAB4["UL + CL"]))))
    return out


def _without_cameras(t: Table) -> Table:
    """Return table ``t`` with its trained rows' inputs named without the cameras ("C + ")."""
    lines = tuple(ln if ln.method != "model" else Line(ln.label, ln.inputs.removeprefix("C + "), ln.runs, ln.paper, ln.method,
                                                       ln.paper_coverage) for ln in t.lines)
    return Table(t.number, t.title, t.metrics, lines)


def parse_tables(text: str) -> tuple[str, ...]:
    """Return the table numbers of ``--tables`` ('I,III,IV'), in the paper's order."""
    asked = [t.strip().upper() for t in text.split(",") if t.strip()]
    bad = [t for t in asked if t not in TABLES]
    if bad or not asked:
        raise ConfigError(f"--tables {text!r}: expected a comma-separated list of {', '.join(TABLES)}")
    return tuple(t for t in TABLES if t in asked)


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
    tables = [t for t in _tables("L (raw scans)" if scans else "L (VM: no raw scans)", cameras) if t.number in numbers]
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
            cells.append({"run": run, **_value(reduced[run], m, ln.method, seeds),
                          "paper": ln.paper[j], "paper_coverage_pct": ln.paper_coverage[j] if ln.paper_coverage else None})
        rows.append({"label": ln.label, "inputs": ln.inputs, "method": ln.method, "cells": cells})
    return {"number": table.number, "title": table.title, "columns": [m.header for m in table.metrics],
            "digits": [m.digits for m in table.metrics], "rows": rows}


def _value(res: dict, m: Metric, method: str, seeds: int) -> dict:
    """Return the mean, spread (None for one seed) and coverage [%] of metric ``m`` of row
    ``method`` in a reduced evaluation."""
    node, sp = res, res["spread"]
    path = m.path(method)
    for k in path:
        node, sp = node[k], (sp[k] if sp is not None else None)
    cov = None
    if m.kind != "cons" and method != "share":
        tab = res["elevation" if m.kind == "mae" else "risk"][m.rng][method]
        cov = (tab[m.key] if m.kind == "mae" else tab)["coverage_pct"]
    return {"mean": node, "spread": sp if seeds > 1 else None, "coverage_pct": cov}


def _number(v: float | None, digits: int, pct: bool = False) -> str:
    if v is None:
        return "—"
    return f"{v:.1f} %" if pct else f"{v:.{digits}f}"


def cell_texts(table: dict) -> tuple[list[str], list[list[str]]]:
    """Return the header and the rows of a filled table as text: Method, Input, then per
    column ours (mean ± spread, coverage when partial) and the paper's."""
    head = ["Method", "Input"] + [h for c in table["columns"] for h in (c, "paper")]
    rows = []
    for row in table["rows"]:
        pct = row["method"] == "share"
        texts = [row["label"], row["inputs"]]
        for c, digits in zip(row["cells"], table["digits"]):
            ours = _number(c["mean"], digits, pct)
            # none for one seed; 0 (to float rounding) for what every seed shares: baselines, shares
            if c["spread"] is not None and c["mean"] is not None and c["spread"] > 1e-6 * abs(c["mean"]):
                ours += f" ± {_number(c['spread'], digits, pct)}"
            if c["coverage_pct"] is not None and c["mean"] is not None and c["coverage_pct"] < 99.95:
                ours += f" ({c['coverage_pct']:.0f} %)"
            paper = _number(c["paper"], digits, pct)
            if c["paper_coverage_pct"] is not None:
                paper += f" ({c['paper_coverage_pct']:.0f} %)"
            texts += [ours, paper]
        rows.append(texts)
    return head, rows


def markdown(tables: list[dict], summary: dict) -> str:
    """Return the tables as Markdown, with what they were computed on."""
    lines = [f"<!-- {signature()} -->", "# The paper's experiments on this dataset", "",
             f"Dataset `{summary['dataset']}`, evaluated on its {summary['split']} split; preset {summary['preset']}, "
             f"{summary['steps']} steps per run, {summary['seeds']} seed(s) (ours: mean ± spread over the seeds, "
             "no spread where every seed gives the same: the baselines, the shares; paper: the paper's numbers).", ""]
    lines += [f"- {n}" for n in summary["notes"]] + ([""] if summary["notes"] else [])
    for t in tables:
        head, rows = cell_texts(t)
        lines += [f"## {t['title']}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(r) + " |" for r in rows] + [""]
    return "\n".join(lines)
