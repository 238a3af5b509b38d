"""The learning commands: train and eval (the paper's tables)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from gtgen.cli.app import WORKSPACE, ConfigOpt, app, console, fmt, read_yaml, table
from gtgen.errors import GtgenError


@app.command("train")
def train_cmd(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", help="dataset from 'gtgen dem-align'"),
    preset: str = typer.Option("tiny", help="tiny (CPU, minutes) | paper (paper sizes, GPU)"),
    run: Optional[Path] = typer.Option(None, "--run", help="run folder [default: runs/<preset>]"),
    resume: bool = typer.Option(False, help="continue from the run folder's checkpoint"),
    steps: Optional[int] = typer.Option(None, help="stop after this many more steps (the schedule keeps the preset's total)"),
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Train M&M-lite on the dataset's train split; checkpoints, metrics JSON, resolved config.

    **Examples**

        gtgen train                                # tiny preset on ./gtgen_ws/dataset.zarr -> runs/tiny/
        gtgen train --preset paper --config gpu.yaml
        gtgen train --resume --run runs/tiny
    """
    from gtgen.config import load_config
    from gtgen.train.trainer import preset_overrides, train

    layer = preset_overrides(preset)
    cfg = load_config(None, layer) if config is None else load_config(None, layer, read_yaml(config))
    run_dir = run or Path("runs") / preset
    res = train(dataset, run_dir, cfg, resume=resume, max_steps=steps)
    table("gtgen train", [
        ("run", res.run_dir), ("checkpoint", res.ckpt), ("steps", res.steps),
        ("loss first -> last", f"{res.first_loss:.4f} -> {res.last_loss:.4f}"),
        ("time", f"{res.seconds:.1f} s ({res.steps and res.seconds / max(res.steps, 1):.2f} s/step this run)"),
    ])


@app.command("eval")
def eval_cmd(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", help="dataset to evaluate on"),
    ckpt: Path = typer.Option(Path("runs/latest/ckpt.pt"), "--ckpt", help="checkpoint from 'gtgen train'"),
    preset: Optional[str] = typer.Option(None, help="refuse a checkpoint of another preset"),
    split: str = typer.Option("val", help="val | train | all (val falls back to all when empty)"),
    viz: Optional[int] = typer.Option(None, "--viz", help="also draw this sample with the predictions"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="metrics JSON [default: eval.json beside the checkpoint]"),
) -> None:
    """Paper-style tables: elevation MAE per region, risk MSE/P/R/F1, consistency; baselines.

    **Examples**

        gtgen eval --ckpt runs/latest/ckpt.pt
        gtgen eval datasets/test.zarr --ckpt runs/paper/ckpt.pt --split all --viz 3
    """
    import json

    from rich.table import Table

    from gtgen.train.trainer import evaluate

    if split not in ("val", "train", "all"):
        raise GtgenError(f"--split {split!r} unknown; expected one of ['val', 'train', 'all']")
    res = evaluate(dataset, ckpt, preset, None if split == "all" else split)
    con = console()
    for r in ("micro", "short"):
        t = Table(title=f"{r} range: elevation MAE [m] (coverage of labelled cells) on {res['split']} ({res['samples']} samples)")
        for col in ("method", "obs PC", "obs F", "unobs", "total"):
            t.add_column(col)
        names = {"model": "M&M-lite", "model_on_raw_cells": "M&M-lite on the raw cells", "xracer": "X-Racer at t", "raw": "raw elevation (min z)"}
        for m, tab in res["elevation"][r].items():
            cells = [f"{fmt(tab[k]['mae_m'])} ({fmt(tab[k]['coverage_pct'], True)})" if m not in ("model",) else fmt(tab[k]["mae_m"]) for k in ("obs_pc", "obs_f", "unobs", "total")]
            t.add_row(names[m], *cells)
        con.print(t)
        t = Table(title=f"{r} range: risk (fatal >= threshold)")
        for col in ("method", "MSE", "precision", "recall", "F1", "coverage"):
            t.add_column(col)
        for m, tab in res["risk"][r].items():
            t.add_row(names[m], fmt(tab["mse"]), fmt(tab["precision"]), fmt(tab["recall"]), fmt(tab["f1"]), fmt(tab["coverage_pct"], True))
        con.print(t)
    out = out or ckpt.parent / "eval.json"
    out.write_text(json.dumps(res, indent=1))
    rows: list[tuple[str, Any]] = [("consistency MAE", f"{fmt(res['consistency_mae_m'])} m"), ("metrics", out)]
    if viz is not None:
        from gtgen.train.trainer import predict_sample
        from gtgen.viz import render_sample

        png = render_sample(dataset, viz, ckpt.parent / f"pred_{viz}.png", predict_sample(dataset, ckpt, viz))
        rows.append(("prediction figure", png))
    table("gtgen eval", rows)
