"""The ``gtgen`` command line. The only module that prints or exits.

Every command reads and writes a workspace in the current directory by default:
``gtgen extract bag.mcap`` -> ``./gtgen_ws/drive.zarr``; ``gtgen fuse`` and
``gtgen dem-align`` read it and write ``./gtgen_ws/dataset.zarr``; ``gtgen train``
reads that. Explicit paths override. Heavy imports live inside the commands so that
``--help`` is instant.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any, Optional

import numpy as np
import typer

from gtgen import __version__
from gtgen.errors import GtgenError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    rich_markup_mode="markdown",
    help="gtgen: pseudo ground truth for BEV elevation and traversability learning (RoadRunner M&M).",
    pretty_exceptions_enable=False,
)

WORKSPACE = Path("gtgen_ws")
ConfigOpt = typer.Option(None, "--config", "-c", help="partial YAML over the defaults in configs/")


def _console():
    from rich.console import Console

    import shutil

    return Console(width=max(120, shutil.get_terminal_size((120, 40)).columns))


def _load(config: Optional[Path], *overrides: dict[str, Any]):
    from gtgen.config import load_config

    return load_config(config, *overrides)


def _table(title: str, rows: list[tuple[str, Any]]) -> None:
    from rich.table import Table

    t = Table(title=title, show_header=False)
    t.add_column("", style="bold")
    t.add_column("")
    for k, v in rows:
        t.add_row(str(k), str(v))
    _console().print(t)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"gtgen {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="print the version and exit"),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="log debug messages"),
) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")


@app.command()
def synth(
    out: Path = typer.Argument(..., help="output folder (created; must be empty or absent)"),
    seed: Optional[int] = typer.Option(None, help="random seed [default from config: 0]"),
    duration: Optional[float] = typer.Option(None, help="drive duration [s] [default from config: 60]"),
    format: Optional[str] = typer.Option(None, "--format", help="mcap | bag | both [default from config: both]"),
    overwrite: bool = typer.Option(False, help="replace a non-empty OUT"),
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Write a seeded synthetic drive: bags + DEM tiles + truth.

    **Examples**

        gtgen synth drive                      # 60 s drive, ROS 2 MCAP and ROS 1 bag
        gtgen synth drive --seed 3 --duration 120 --format mcap
    """
    over: dict[str, Any] = {}
    if seed is not None:
        over["seed"] = seed
    if duration is not None:
        if duration <= 0:
            raise GtgenError(f"--duration {duration} must be a positive number of seconds")
        over["duration_s"] = duration
    if format is not None:
        if format not in ("mcap", "bag", "both"):
            raise GtgenError(f"--format {format!r} unknown; expected one of ['mcap', 'bag', 'both']")
        over["formats"] = format
    cfg = _load(config, {"synth": over})
    from gtgen.synth import run_synth

    res = run_synth(cfg, out, overwrite=overwrite)
    rows: list[tuple[str, Any]] = [
        ("output", res.out),
        ("bags", ", ".join(p.name for p in res.bags)),
        ("DEM tiles", f"{len(res.dem_tiles)} in {res.out / 'dem'}"),
        ("duration", f"{res.duration_s:.1f} s"),
        ("distance", f"{res.distance_m:.0f} m"),
    ]
    rows += [(f"  {k}", v) for k, v in sorted(res.counts.items())]
    _table("gtgen synth", rows)


@app.command()
def extract(
    bags: list[Path] = typer.Argument(..., help="bag files (.bag, .mcap, .db3) or rosbag2 folders of ONE drive"),
    out: Path = typer.Option(WORKSPACE / "drive.zarr", "-o", "--out", help="drive store to write"),
    workers: int = typer.Option(2, min=1, help="processes reading the bags (record-time slices)"),
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Read a drive's bags into a per-drive store: poses, GNSS, maps, images, voxel maps.

    **Examples**

        gtgen extract bag.mcap                         # -> ./gtgen_ws/drive.zarr
        gtgen extract run_0.bag run_1.bag -o runs/a.zarr
        gtgen extract rosbag2_folder --config my_robot.yaml
    """
    cfg = _load(config)
    from gtgen.extract import run_extract

    out.parent.mkdir(parents=True, exist_ok=True)
    res = run_extract(bags, out, cfg, workers=workers)
    from rich.table import Table

    t = Table(title="gtgen extract: topics")
    for col in ("topic", "role", "count", "rate Hz", "max gap s", "decode failures", "record-header max s"):
        t.add_column(col)
    for s in res.topics:
        t.add_row(s["topic"], s["role"], str(s["count"]), str(s["rate_hz"]), str(s["max_gap_s"]),
                  str(s["decode_failures"]) + (f" ({s['first_error'][:40]})" if s["first_error"] else ""),
                  str(s["record_minus_header_max_s"]))
    _console().print(t)
    rows: list[tuple[str, Any]] = [
        ("store", res.store),
        ("candidates", res.n_candidates),
        ("samples kept", res.n_samples),
    ]
    rows += [(f"  rejected: {k}", v) for k, v in res.rejected.items()]
    rows += [(f"maps kept ({k})", v) for k, v in res.maps_kept.items()]
    rows += [(f"skew {k}", f"{v:.3f} s") for k, v in res.skew_s.items()]
    if res.reread:
        rows.append(("read twice", f"{res.reread} kept messages no slice had staged (stamps far from record times)"))
    rows += [("warning", w) for w in res.warnings]
    _table("gtgen extract", rows)


@app.command()
def fuse(
    drive: Path = typer.Argument(WORKSPACE / "drive.zarr", help="drive store from 'gtgen extract'"),
    window: Optional[float] = typer.Option(None, "--window", help="future window [s] [default from config: 60]"),
    past: Optional[float] = typer.Option(None, "--past", help="past window [s] [default from config: 0]"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="fused store [default: fused.zarr beside DRIVE]"),
    workers: int = typer.Option(2, help="processes (one per range)"),
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Hindsight-fuse each sample's maps: elevation, confidence, risk, regions, X-Racer at t.

    **Examples**

        gtgen fuse --window 60                 # ./gtgen_ws/drive.zarr -> ./gtgen_ws/fused.zarr
        gtgen fuse runs/a.zarr --window 30 --past 5
    """
    over: dict[str, Any] = {}
    if window is not None:
        if window <= 0:
            raise GtgenError(f"--window {window} must be a positive number of seconds")
        over["window_s"] = window
    if past is not None:
        if past < 0:
            raise GtgenError(f"--past {past} must be zero or a positive number of seconds")
        over["past_s"] = past
    cfg = _load(config, {"fuse": over})
    from gtgen.fuse.run import run_fuse

    res = run_fuse(drive, out or drive.parent / "fused.zarr", cfg, workers=workers)
    rows: list[tuple[str, Any]] = [("store", res.store), ("samples", res.n_samples), ("fused", res.n_fused)]
    rows += [(f"  rejected: {k}", v) for k, v in res.rejected.items()]
    for r, cov in res.coverage.items():
        rows.append((f"coverage {r}", ", ".join(f"{k} {100 * v:.1f}%" for k, v in cov.items())))
    _table("gtgen fuse", rows)


@app.command("dem-align")
def dem_align(
    drive: Path = typer.Argument(WORKSPACE / "drive.zarr", help="drive store from 'gtgen extract'"),
    fused: Optional[Path] = typer.Option(None, "--fused", help="fused store [default: fused.zarr beside DRIVE]"),
    dem: Optional[Path] = typer.Option(None, "--dem", help="DEM folder [default: dem.dir, else dem/ beside the bag]"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="dataset to write [default: dataset.zarr beside DRIVE]"),
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Place the DEM by GNSS, refine per sample by ICP, reject misfits, inpaint, write shards.

    **Examples**

        gtgen dem-align                        # ./gtgen_ws/{drive,fused}.zarr -> ./gtgen_ws/dataset.zarr
        gtgen dem-align --dem /data/usgs_1m/ -o datasets/paso.zarr
    """
    cfg = _load(config)
    from gtgen.dataset.run import run_dem_align

    res = run_dem_align(drive, fused or drive.parent / "fused.zarr", dem, out or drive.parent / "dataset.zarr", cfg)
    f = np.asarray(res.fitness) if res.fitness else None
    rows: list[tuple[str, Any]] = [
        ("dataset", res.store),
        ("samples in", res.n_in),
        ("samples kept", res.n_kept),
    ]
    rows += [(f"  rejected: {k}", v) for k, v in res.rejected.items()]
    rows += [(f"  split {k}", v) for k, v in res.split_counts.items()]
    rows += [
        ("GNSS fit", f"rms {res.fit.rms_m:.2f} m over {res.fit.n_used} fixes, {res.fit.n_outliers} outliers, yaw {np.degrees(res.fit.yaw):.2f} deg"),
        ("vertical offset odom->DEM", f"{res.dz_dem_m:+.2f} m"),
        ("ellipsoid - DEM height (geoid)", f"{res.geoid_offset_m:+.2f} m"),
    ]
    if f is not None:
        rows.append(("ICP fitness", f"median {np.median(f):.3f}, min {f.min():.3f}"))
    _table("gtgen dem-align", rows)


@app.command()
def report(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", help="dataset from 'gtgen dem-align'"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="folder for report.json and PNGs [default: report/ beside the dataset's workspace]"),
) -> None:
    """Print a dataset card (kept/rejected, coverage, ICP fitness) and write QA figures.

    With synth truth beside the bags, also the label error per region and range and the
    DEM alignment error.

    **Examples**

        gtgen report
        gtgen report datasets/paso.zarr -o qa/
    """
    from gtgen.report import build_report

    out = out or Path("report")
    rep = build_report(dataset, out)
    c = rep.card
    rows: list[tuple[str, Any]] = [("dataset", c["dataset"]), ("samples kept", c["samples_kept"])]
    rows += [(f"  rejected: {k}", v) for k, v in c["samples_rejected"].items()]
    rows += [(f"  split {k}", v) for k, v in c["split"].items()]
    for r, cov in c.get("coverage", {}).items():
        rows.append((f"coverage {r}", ", ".join(f"{k} {100 * v:.1f}%" for k, v in cov.items())))
    if c.get("icp_fitness"):
        rows.append(("ICP fitness", ", ".join(f"{k} {v:.3f}" for k, v in c["icp_fitness"].items())))
    a = c.get("alignment", {})
    if a:
        rows.append(("GNSS fit", f"rms {a['gnss_rms_m']:.2f} m, {a['gnss_outliers']} outliers; geoid offset {a['geoid_offset_m']:+.2f} m"))
    t = rep.truth
    if t:
        for r in ("micro", "short"):
            for reg in ("obs_pc", "obs_f", "unobs"):
                e = t[r][reg]
                rows.append((f"truth {r} {reg}", f"elev MAE {e['elevation_mae_m']} m, risk MSE {e['risk_mse']}, X-Racer MAE {e['xracer_elevation_mae_m']} m"))
            fv = t[r]["fused_vs_single_map"]
            rows.append((f"truth {r} fused vs single map", f"{fv['fused_mae_m']} m vs {fv['single_map_mae_m']} m on {fv['cells']} cells"))
        d = t["dem_alignment"]
        rows.append(("DEM alignment error", f"horizontal median {d['horizontal_at_vehicle_m'].get('median')} m (max {d['horizontal_at_vehicle_m'].get('max')}), "
                                            f"at 50 m ahead median {d['horizontal_50m_ahead_m'].get('median')} m, vertical median {d['vertical_m'].get('median')} m (max {d['vertical_m'].get('max')})"))
    rows.append(("figures", ", ".join(str(p) for p in rep.figures)))
    _table("gtgen report", rows)


@app.command()
def viz(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", help="dataset from 'gtgen dem-align'"),
    sample: int = typer.Option(0, "--sample", "-n", help="sample index"),
    out: Path = typer.Option(Path("sample.png"), "-o", "--out", help="PNG to write"),
) -> None:
    """Draw one sample: the four images, and per range labels, regions, X-Racer at t, DEM.

    **Examples**

        gtgen viz --sample 12 -o s12.png
    """
    from gtgen.viz import render_sample

    p = render_sample(dataset, sample, out)
    _table("gtgen viz", [("figure", p)])


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
    cfg = load_config(None, layer) if config is None else load_config(None, layer, _read(config))
    run_dir = run or Path("runs") / preset
    res = train(dataset, run_dir, cfg, resume=resume, max_steps=steps)
    _table("gtgen train", [
        ("run", res.run_dir), ("checkpoint", res.ckpt), ("steps", res.steps),
        ("loss first -> last", f"{res.first_loss:.4f} -> {res.last_loss:.4f}"),
        ("time", f"{res.seconds:.1f} s ({res.steps and res.seconds / max(res.steps, 1):.2f} s/step this run)"),
    ])


def _read(path: Path) -> dict:
    from gtgen.config import read_yaml

    return read_yaml(path)


def _fmt(v: Any, pct: bool = False) -> str:
    if v is None:
        return "n/a"
    return f"{v:.1f}%" if pct else f"{v:.3f}"


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
    con = _console()
    for r in ("micro", "short"):
        t = Table(title=f"{r} range: elevation MAE [m] (coverage of labelled cells) on {res['split']} ({res['samples']} samples)")
        for col in ("method", "obs PC", "obs F", "unobs", "total"):
            t.add_column(col)
        names = {"model": "M&M-lite", "model_on_raw_cells": "M&M-lite on the raw cells", "xracer": "X-Racer at t", "raw": "raw elevation (min z)"}
        for m, tab in res["elevation"][r].items():
            cells = [f"{_fmt(tab[k]['mae_m'])} ({_fmt(tab[k]['coverage_pct'], True)})" if m not in ("model",) else _fmt(tab[k]["mae_m"]) for k in ("obs_pc", "obs_f", "unobs", "total")]
            t.add_row(names[m], *cells)
        con.print(t)
        t = Table(title=f"{r} range: risk (fatal >= threshold)")
        for col in ("method", "MSE", "precision", "recall", "F1", "coverage"):
            t.add_column(col)
        for m, tab in res["risk"][r].items():
            t.add_row(names[m], _fmt(tab["mse"]), _fmt(tab["precision"]), _fmt(tab["recall"]), _fmt(tab["f1"]), _fmt(tab["coverage_pct"], True))
        con.print(t)
    out = out or ckpt.parent / "eval.json"
    out.write_text(json.dumps(res, indent=1))
    rows: list[tuple[str, Any]] = [("consistency MAE", f"{_fmt(res['consistency_mae_m'])} m"), ("metrics", out)]
    if viz is not None:
        from gtgen.train.trainer import predict_sample
        from gtgen.viz import render_sample

        png = render_sample(dataset, viz, ckpt.parent / f"pred_{viz}.png", predict_sample(dataset, ckpt, viz))
        rows.append(("prediction figure", png))
    _table("gtgen eval", rows)


@app.command()
def build(
    sources: list[Path] = typer.Argument(..., help="manifest YAML, drive folders, a folder of drive folders, or bags"),
    dem: Optional[Path] = typer.Option(None, "--dem", help="DEM folder [default: dem.dir, else dem/ beside each drive's bags]"),
    out: Path = typer.Option(Path("gtgen_build"), "-o", "--out", help="output folder (dataset.zarr + drives/)"),
    workers: int = typer.Option(2, help="local worker processes"),
    scheduler: Optional[str] = typer.Option(None, help="dask.distributed scheduler address (e.g. tcp://host:8786)"),
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Build one dataset from many drives (extract -> fuse -> dem-align each), resumable.

    **Examples**

        gtgen build drives/ --dem usgs_1m/ -o paso_dataset --workers 2
        gtgen build manifest.yaml --scheduler tcp://10.0.0.5:8786
    """
    from pipelines.build_dataset import build_dataset, summary_rows

    cfg = _load(config)
    res = build_dataset(sources, dem, out, cfg, workers=workers, scheduler=scheduler)
    _table("gtgen build", summary_rows(res))
    if any(not r.ok for r in res.drives):
        raise typer.Exit(code=2)


def main() -> None:
    """Run the CLI: usage errors print the usage and exit 2 (click's standalone mode);
    gtgen errors and OS errors (a full disk, a permission) print one line and exit 1."""
    try:
        app()
    except GtgenError as err:
        typer.echo(f"error: {err}", err=True)
        sys.exit(1)
    except OSError as err:
        typer.echo(f"error: {err.strerror or err}" + (f": '{err.filename}'" if err.filename else ""), err=True)
        sys.exit(1)
