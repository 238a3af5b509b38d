"""The learning commands: train, eval (the paper's tables) and experiments (all of the paper's rows)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from gtgen.cli.app import WORKSPACE, ConfigOpt, OverwriteOpt, app, console, fmt, read_yaml, table
from gtgen.errors import GtgenError


@app.command("train")
def train_cmd(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", metavar="DATASET", help="dataset from 'gtgen dem-align'"),
    preset: str = typer.Option("tiny", metavar="tiny|paper", help="tiny (CPU, minutes) or paper (the paper's network, GPU)"),
    run: Optional[Path] = typer.Option(None, "--run-dir", "--run", help="run folder [default: runs/PRESET, or runs/PRESET-seedK with --seeds]; under torchrun spell it --run-dir"),
    resume: bool = typer.Option(False, help="continue from the run folder's checkpoint (the same run: same samples, same draws)"),
    steps: Optional[int] = typer.Option(None, min=1, help="stop after this many more steps (the schedule keeps the preset's total)"),
    seeds: int = typer.Option(1, min=1, max=1000, help="train this many seeds (train.seed, +1, ...), one run folder each, one after the other"),
    device: Optional[str] = typer.Option(None, metavar="DEVICE", help="auto | cpu | cuda | cuda:N [default: train.device, auto: CUDA when present]"),
    overwrite: bool = OverwriteOpt,
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Train M&M-lite on the dataset's train split: checkpoints (ckpt.pt, best.pt by val MAE),
    curves (TensorBoard tb/, train.csv, val.csv), metrics JSON, resolved config.

    **Examples**

    ```
    gtgen train                         # tiny preset -> runs/tiny/
    gtgen train --seeds 3               # runs/tiny-seed0 .. runs/tiny-seed2
    gtgen train --preset paper --config configs/paper_faithful.yaml
    gtgen train --resume --run-dir runs/tiny
    torchrun --standalone --nproc_per_node 2 -m gtgen train --run-dir runs/d
    ```
    """
    from gtgen.config import load_config
    from gtgen.train.trainer import preset_overrides, train

    layer = preset_overrides(preset)
    cfg = load_config(None, layer) if config is None else load_config(None, layer, read_yaml(config))
    rows: list[tuple[str, Any]] = []
    main = True
    for i in range(seeds):
        seed = cfg.train.seed + i
        one = cfg.model_copy(update={"train": cfg.train.model_copy(update={"seed": seed})})
        base = run or Path("runs") / preset
        run_dir = base if seeds == 1 else base.with_name(f"{base.name}-seed{seed}")
        res = train(dataset, run_dir, one, resume=resume, max_steps=steps, device=device, overwrite=overwrite)
        main = res.rank == 0
        tag = "" if seeds == 1 else f" (seed {seed})"
        if i == 0:
            rows += [("device", f"{res.device}, precision {res.precision}" + (f", {res.world} processes (DDP)" if res.world > 1 else ""))]
            rows += [(f"parameters: {k}", f"{v / 1e6:.2f} M") for k, v in res.parameters.items()]
        best = f"step {res.best['step']}: {res.best['total_mae_m']:.3f} m (val MAE, micro and short)" if res.best else "no validation"
        rows += [
            (f"run{tag}", res.run_dir), (f"checkpoint{tag}", res.ckpt), (f"best.pt{tag}", best), (f"steps{tag}", res.steps),
            (f"loss first -> last{tag}", f"{res.first_loss:.4f} -> {res.last_loss:.4f}"),
            (f"time{tag}", f"{res.seconds:.1f} s; {res.samples_per_s:.2f} samples/s, {100 * res.data_wait_share:.0f} % of it waiting for data"),
        ]
        if res.peak_memory_mib is not None:
            rows.append((f"peak GPU memory{tag}", f"{res.peak_memory_mib:.0f} MiB"))
        if res.latest_note:
            rows.append((f"latest{tag}", f"not updated: {res.latest_note}"))
    if main:
        table("gtgen train", rows)


def _checkpoints(patterns: list[Path]) -> list[Path]:
    """Return the checkpoints ``--ckpt`` names, each a path or a quoted glob pattern."""
    import glob

    out: list[Path] = []
    for p in patterns:
        hits = sorted(glob.glob(str(p))) if glob.has_magic(str(p)) else [str(p)]
        if not hits:
            raise GtgenError(f"--ckpt {str(p)!r} matches no checkpoint")
        out += [Path(h) for h in hits]
    return out


def _cell(res: dict, path: tuple[str, ...], coverage: bool = False) -> str:
    """Return a table cell: the metric at ``path`` (an MAE with its coverage if
    ``coverage``), with '± spread' when several seeds were evaluated."""
    node, sp = res, res.get("spread")
    for k in path:
        node, sp = node[k], (sp[k] if sp is not None else None)
    val, s = (node["mae_m"], sp["mae_m"] if sp is not None else None) if coverage else (node, sp)
    if coverage and node.get("coverage_pct") is None:
        return "-"  # an empty region (no unobserved cells in a dataset without a DEM, say)
    text = fmt(val) + (f" ± {fmt(s)}" if s is not None else "")
    return text + (f" ({fmt(node['coverage_pct'], True)})" if coverage else "")


@app.command("eval")
def eval_cmd(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", metavar="DATASET", help="dataset to evaluate on"),
    ckpt: list[Path] = typer.Option([Path("runs/latest/ckpt.pt")], "--ckpt", help="checkpoint from 'gtgen train'; repeat it, or quote a glob, for several seeds (mean ± spread)"),
    preset: Optional[str] = typer.Option(None, metavar="tiny|paper", help="refuse a checkpoint of another preset"),
    split: str = typer.Option("val", metavar="val|test|train|all", help="the split to evaluate (test: the drives held out whole with 'split: test' in the build manifest)"),
    viz: Optional[int] = typer.Option(None, "--viz", metavar="SAMPLE", help="also draw this sample with the predictions (of the first checkpoint)"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="metrics JSON [default: eval.json beside the (first) checkpoint]"),
    device: Optional[str] = typer.Option(None, help="auto | cpu | cuda | cuda:N [default: auto, CUDA when present]"),
    overwrite: bool = OverwriteOpt,
) -> None:
    """Paper-style tables: elevation MAE per region, risk MSE/P/R/F1, consistency; baselines.

    The model and thresholds are those the checkpoint recorded: no --config.

    **Examples**

    ```
    gtgen eval --ckpt runs/latest/ckpt.pt
    gtgen eval --ckpt 'runs/tiny-seed*/ckpt.pt'   # mean ± spread of seeds
    gtgen eval paso/dataset.zarr --ckpt runs/a/best.pt --split test
    gtgen eval data/test.zarr --ckpt runs/paper/best.pt --split all --viz 3
    ```
    """

    from rich.markup import escape
    from rich.table import Table

    from gtgen import codes
    from gtgen.train.trainer import EVAL_ROWS, evaluate, evaluate_seeds

    names = [*codes.SPLITS.values(), "all"]
    if split not in names:
        raise GtgenError(f"--split {split!r} unknown; expected one of {names}")
    ckpts = _checkpoints(ckpt)
    out = out or ckpts[0].parent / "eval.json"
    png = ckpts[0].parent / f"pred_{viz}.png"
    from gtgen.runtime.output import check_replace, write_json

    for path in (out, *([png] if viz is not None else [])):
        check_replace(path, overwrite)  # before the evaluation
    sp = None if split == "all" else split
    res = evaluate(dataset, ckpts[0], preset, sp, device) if len(ckpts) == 1 else evaluate_seeds(dataset, ckpts, sp, device)
    if preset is not None and len(ckpts) > 1 and res["preset"] != preset:
        raise GtgenError(f"checkpoints are of preset {res['preset']!r}, not {preset!r}")
    con = console()
    seeds = f", mean ± spread of {len(ckpts)} seeds" if len(ckpts) > 1 else ""
    for r in res["elevation"]:  # the ranges the model predicts
        t = Table(title=escape(f"{r} range: elevation MAE [m] (coverage of labelled cells) on {res['split']} ({res['samples']} samples{seeds})"))
        for col in ("method", "obs PC", "obs F", "unobs", "total"):
            t.add_column(col)
        for m in res["elevation"][r]:
            t.add_row(EVAL_ROWS[m], *(_cell(res, ("elevation", r, m, k), coverage=True) for k in ("obs_pc", "obs_f", "unobs", "total")))
        con.print(t)
        t = Table(title=f"{r} range: risk (fatal >= threshold){seeds}")
        for col in ("method", "MSE", "precision", "recall", "F1", "coverage"):
            t.add_column(col)
        for m, tab in res["risk"][r].items():
            t.add_row(EVAL_ROWS[m], *(_cell(res, ("risk", r, m, k)) for k in ("mse", "precision", "recall", "f1")), fmt(tab["coverage_pct"], True))
        con.print(t)
    write_json(out, res, overwrite, indent=1)
    cons = f"{_cell(res, ('consistency_mae_m',))} m" if res["consistency_mae_m"] is not None else "n/a (one range)"
    rows: list[tuple[str, Any]] = [("consistency MAE", cons),
                                   ("device", f"{res['device']}, {1000 * res['seconds_per_sample']:.1f} ms per sample"), ("metrics", out)]
    if viz is not None:
        from gtgen.train.trainer import predict_sample
        from gtgen.viz import render_sample

        rows.append(("prediction figure", render_sample(dataset, viz, png, predict_sample(dataset, ckpts[0], viz, device), overwrite)))
    table("gtgen eval", rows)


@app.command("experiments")
def experiments_cmd(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", metavar="DATASET", help="dataset from 'gtgen dem-align'"),
    preset: str = typer.Option("tiny", metavar="tiny|paper", help="the model preset of every run"),
    seeds: int = typer.Option(1, min=1, max=1000, help="seeds per run (train.seed, +1, ...); tables show mean ± spread"),
    steps: Optional[int] = typer.Option(None, min=1, help="steps of every run [default: 400 for tiny, else the preset's]"),
    tables: str = typer.Option("I,II,III,IV", metavar="I,II,III,IV", help="the paper's tables to reproduce (II shares I's runs)"),
    out: Path = typer.Option(Path("experiments"), "-o", "--out", help="folder of the runs, experiments.json and experiments.md"),
    device: Optional[str] = typer.Option(None, metavar="DEVICE", help="auto | cpu | cuda | cuda:N [default: train.device]"),
    overwrite: bool = OverwriteOpt,
    config: Optional[Path] = ConfigOpt,
) -> None:
    """The paper's Tab. I-IV on the dataset: every row trained (one folder per run and seed),
    evaluated on the test split (val when there is none), printed beside the paper's numbers.

    Resumable: a finished run is not retrained, a killed one resumes from its checkpoint.
    With the tiny preset, one seed of every row takes about an hour on 2 cores.

    **Examples**

    ```
    gtgen experiments --seeds 3 -o experiments/
    gtgen experiments data/paso.zarr --tables I,IV --steps 1000
    gtgen experiments --preset paper --device cuda
    ```
    """
    from rich.markup import escape
    from rich.measure import Measurement
    from rich.table import Table

    from gtgen.train.experiments import run_experiments
    from gtgen.train.tables import cell_texts, parse_tables

    con = console()

    def line(text: str) -> None:  # one line each, whatever its length: the log of a long job
        con.print(text, markup=False, highlight=False, soft_wrap=True)

    res = run_experiments(dataset, out, preset, seeds, steps, parse_tables(tables), config, device, progress=line, overwrite=overwrite)
    for note in res.notes:
        line(f"note: {note}")
    for tab in res.tables:
        head, rows = cell_texts(tab)
        t = Table(title=escape(tab["title"]))
        for h in head:
            t.add_column(escape(h), style="dim" if h == "paper" else None, no_wrap=True)
        for r in rows:
            t.add_row(*map(escape, r))
        # as wide as the table, whatever the terminal: a cut number is no number
        con.width = max(con.width, Measurement.get(con, con.options.update_width(10_000), t).maximum)
        con.print(t)
    table("gtgen experiments", [
        ("evaluated on", f"the {res.split} split"), ("runs trained now", len(res.trained)), ("runs already done", len(res.reused)),
        ("training time of all runs", f"{res.train_s / 60:.1f} min (the steps' own time)"),
        ("tables", res.json_path), ("markdown", res.markdown_path)])
