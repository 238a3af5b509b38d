"""The stage commands: synth, extract, fuse, dem-align, and build over many drives."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from gtgen.cli.app import MAX_WORKERS, WORKSPACE, ConfigOpt, OverwriteOpt, app, console, load, setting, table


@app.command()
def synth(
    out: Path = typer.Argument(..., metavar="OUT", help="output folder (created; must be empty or absent)"),
    seed: Optional[int] = typer.Option(None, callback=setting("synth.seed"), help="random seed, >= 0 [default from config: 0]"),
    duration: Optional[float] = typer.Option(None, metavar="SECONDS", callback=setting("synth.duration_s"),
                                             help="drive duration, at most 3600 [default from config: 60]"),
    format: Optional[str] = typer.Option(None, "--format", metavar="mcap|bag|both", callback=setting("synth.formats"),
                                         help="bag flavours to write [default from config: both]"),
    scan_rate: Optional[float] = typer.Option(None, "--scan-rate", metavar="HZ", callback=setting("synth.scan_rate_hz"),
                                              help="raw scans per lidar, 0 for none [default from config: 10]"),
    cameras: Optional[int] = typer.Option(None, "--cameras", min=0, max=4, metavar="N",
                                          help="cameras the drive carries: the first N of front, left, right, back [default: topics.cameras]"),
    overwrite: bool = typer.Option(False, help="replace a non-empty OUT"),
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Write a seeded synthetic drive: bags + DEM tiles + truth.

    **Examples**

    ```
    gtgen synth drive                   # 60 s drive, ROS 2 MCAP + ROS 1 bag
    gtgen synth drive --seed 3 --duration 120 --format mcap
    gtgen synth drive --scan-rate 2     # fewer raw scans: a faster drive
    gtgen synth drive --cameras 1       # a one-camera rig (front)
    ```
    """
    given = {"seed": seed, "duration_s": duration, "formats": format, "scan_rate_hz": scan_rate}
    over: dict[str, Any] = {"synth": {k: v for k, v in given.items() if v is not None}}
    if cameras is not None:
        from gtgen.config import CAMERAS, TopicsConfig

        rig = TopicsConfig().cameras
        over["topics"] = {"cameras": {c: rig[c].model_dump() for c in CAMERAS[:cameras]}}
    cfg = load(config, over)
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
    from gtgen.config import GtgenConfig

    if cfg.topics != GtgenConfig().topics:
        rows.append(("extract with", f"--config {res.out / 'gtgen-config.yaml'} (its topics are not the default mapping's)"))
    table("gtgen synth", rows)


@app.command()
def extract(
    bags: list[Path] = typer.Argument(..., metavar="BAG...", help="bag files (.bag, .mcap, .db3) or rosbag2 folders of ONE drive"),
    out: Path = typer.Option(WORKSPACE / "drive.zarr", "-o", "--out", help="drive store to write"),
    workers: int = typer.Option(2, min=1, max=MAX_WORKERS, help="processes reading the bags (record-time slices)"),
    overwrite: bool = OverwriteOpt,
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Read a drive's bags into a per-drive store: poses, GNSS, maps, images, voxel maps.

    Messages that do not decode are counted per topic (decode failures), messages recorded
    twice are dropped (dropped: duplicate); only a topic left with no usable message stops
    the run.

    **Examples**

    ```
    gtgen extract bag.mcap              # -> ./gtgen_ws/drive.zarr
    gtgen extract run_0.bag run_1.bag -o runs/a.zarr
    gtgen extract rosbag2_folder --config my_robot.yaml
    ```
    """
    cfg = load(config)
    from gtgen.extract import run_extract

    res = run_extract(bags, out, cfg, workers=workers, overwrite=overwrite)
    from rich.table import Table

    t = Table(title="gtgen extract: topics")
    t.add_column("topic", overflow="fold")  # a topic name cut short with an ellipsis is no name
    for col in ("role", "count", "rate Hz", "max gap s", "decode failures", "dropped", "record-header max s"):
        t.add_column(col)
    for s in res.topics:
        t.add_row(s["topic"], s["role"], str(s["count"]), str(s["rate_hz"]), str(s["max_gap_s"]),
                  str(s["decode_failures"]) + (f" ({s['first_error'][:40]})" if s["first_error"] else ""),
                  ", ".join(f"{k} {v}" for k, v in s["dropped"].items()) or "0", str(s["record_minus_header_max_s"]))
    console().print(t)
    rows: list[tuple[str, Any]] = [
        ("store", res.store),
        ("poses", res.poses),
        ("candidates", res.n_candidates),
        ("samples kept", res.n_samples),
        ("samples snap to", res.reference),
    ]
    rows += [(f"  rejected: {k}", v) for k, v in res.rejected.items()]
    rows += [(f"maps kept ({k})", v) for k, v in res.maps_kept.items()]
    rows += [(f"skew {k}", f"{v:.3f} s") for k, v in res.skew_s.items()]
    if res.reread:
        rows.append(("read twice", f"{res.reread} kept messages no slice had staged (stamps far from record times)"))
    rows += [("warning", w) for w in res.warnings]
    table("gtgen extract", rows)


@app.command()
def fuse(
    drive: Path = typer.Argument(WORKSPACE / "drive.zarr", metavar="DRIVE", help="drive store from 'gtgen extract'"),
    window: Optional[float] = typer.Option(None, "--window", metavar="SECONDS", callback=setting("fuse.window_s"),
                                           help="future window, > 0 and at most a day [default from config: 60]"),
    past: Optional[float] = typer.Option(None, "--past", metavar="SECONDS", callback=setting("fuse.past_s"),
                                         help="past window, >= 0 and at most a day [default from config: 0]"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="fused store [default: fused.zarr beside DRIVE]"),
    workers: int = typer.Option(2, min=1, max=MAX_WORKERS, help="processes (jobs split by range and by fuse.chunk_samples samples)"),
    overwrite: bool = OverwriteOpt,
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Hindsight-fuse each sample's maps: elevation, confidence, risk, regions, X-Racer at t.

    **Examples**

    ```
    gtgen fuse --window 60              # gtgen_ws/drive.zarr -> fused.zarr
    gtgen fuse runs/a.zarr --window 30 --past 5
    ```
    """
    given = {"window_s": window, "past_s": past}
    over: dict[str, Any] = {k: v for k, v in given.items() if v is not None}
    cfg = load(config, {"fuse": over})
    from gtgen.fuse.run import run_fuse

    res = run_fuse(drive, out or drive.parent / "fused.zarr", cfg, workers=workers, overwrite=overwrite)
    rows: list[tuple[str, Any]] = [("store", res.store), ("samples", res.n_samples), ("fused", res.n_fused)]
    rows += [(f"  rejected: {k}", v) for k, v in res.rejected.items()]
    for r, cov in res.coverage.items():
        rows.append((f"coverage {r}", ", ".join(f"{k} {100 * v:.1f}%" for k, v in cov.items())))
    table("gtgen fuse", rows)


@app.command("dem-align")
def dem_align(
    drive: Path = typer.Argument(WORKSPACE / "drive.zarr", metavar="DRIVE", help="drive store from 'gtgen extract'"),
    fused: Optional[Path] = typer.Option(None, "--fused", help="fused store [default: fused.zarr beside DRIVE]"),
    dem: Optional[Path] = typer.Option(None, "--dem", help="DEM folder [default: dem.dir, else dem/ beside the bag]"),
    no_dem: bool = typer.Option(False, "--no-dem", help="no DEM (dem.enabled: false): the fused labels alone, unobserved cells unlabelled"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="dataset to write [default: dataset.zarr beside DRIVE]"),
    workers: int = typer.Option(2, min=1, max=MAX_WORKERS, help="processes building the samples (the ICP chain runs beside them); "
                                "the dataset is the same for any number"),
    overwrite: bool = OverwriteOpt,
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Place the DEM by GNSS, refine per sample by ICP, reject misfits, inpaint, write shards.

    A log without GNSS or without DEM tiles: --no-dem writes the dataset from the fused
    labels alone (unobserved cells stay unlabelled, samples are not georeferenced).

    **Examples**

    ```
    gtgen dem-align                     # gtgen_ws/ -> gtgen_ws/dataset.zarr
    gtgen dem-align --dem /data/usgs_1m/ -o datasets/paso.zarr
    gtgen dem-align --no-dem            # lidar and poses: no GNSS, no DEM
    ```
    """
    cfg = _no_dem(load(config), dem, no_dem)
    from gtgen.dataset.dem_align import run_dem_align

    res = run_dem_align(drive, fused or drive.parent / "fused.zarr", dem, out or drive.parent / "dataset.zarr", cfg,
                        workers=workers, overwrite=overwrite)
    import numpy as np

    f = np.asarray(res.fitness) if res.fitness else None
    rows: list[tuple[str, Any]] = [
        ("dataset", res.store),
        ("samples in", res.n_in),
        ("samples kept", res.n_kept),
    ]
    rows += [(f"  rejected: {k}", v) for k, v in res.rejected.items()]
    rows += [(f"  split {k}", v) for k, v in res.split_counts.items()]
    if res.n_kept and not res.split_counts.get("val"):
        rows.append(("  split val", f"0: no {cfg.shards.split_block_m:g} m block (shards.split_block_m) of this drive fell in val; "
                                    "train will not validate: a smaller block, or more drives, gives it one"))
    if res.fit is None:
        rows.append(("DEM", "none (--no-dem): unobserved cells unlabelled, samples not georeferenced (geography split in odom)"))
    else:
        rows += [
            ("working CRS", res.crs),
            ("GNSS fit", f"rms {res.fit.rms_m:.2f} m over {res.fit.n_used} fixes, {res.fit.n_outliers} outliers, yaw {np.degrees(res.fit.yaw):.2f} deg"),
            ("vertical offset odom->DEM", f"{res.dz_dem_m:+.2f} m"),
            ("ellipsoid - DEM height (geoid)", f"{res.geoid_offset_m:+.2f} m"),
        ]
    if f is not None:
        rows.append(("ICP fitness", f"median {np.median(f):.3f}, min {f.min():.3f}"))
    table("gtgen dem-align", rows)


def _no_dem(cfg: Any, dem: Optional[Path], no_dem: bool) -> Any:
    """Return ``cfg`` with ``dem.enabled`` off for ``--no-dem``; ``--dem`` beside it is a usage error."""
    if no_dem and dem is not None:
        raise typer.BadParameter(f"--no-dem and --dem {dem} given together; expected one of them", param_hint="--dem")
    return cfg.model_copy(update={"dem": cfg.dem.model_copy(update={"enabled": False})}) if no_dem else cfg


@app.command()
def build(
    sources: list[Path] = typer.Argument(..., metavar="SOURCE...", help="manifest YAML, drive folders, a folder of drive folders, or bags"),
    dem: Optional[Path] = typer.Option(None, "--dem", help="DEM folder [default: dem.dir, else dem/ beside each drive's bags]"),
    no_dem: bool = typer.Option(False, "--no-dem", help="no DEM (dem.enabled: false): the fused labels alone, unobserved cells unlabelled"),
    out: Path = typer.Option(Path("gtgen_build"), "-o", "--out", help="output folder (dataset.zarr + drives/)"),
    workers: int = typer.Option(2, min=1, max=MAX_WORKERS, help="local worker processes"),
    scheduler: Optional[str] = typer.Option(None, help="dask.distributed scheduler address (e.g. tcp://host:8786)"),
    overwrite: bool = OverwriteOpt,
    config: Optional[Path] = ConfigOpt,
) -> None:
    """Build one dataset from many drives (extract -> fuse -> dem-align each), resumable.

    A manifest maps drive names to their bags: `drives: {name: [bag, ...]}`.

    **Examples**

    ```
    gtgen build drives/ --dem usgs_1m/ -o paso_dataset --workers 2
    gtgen build manifest.yaml --scheduler tcp://10.0.0.5:8786
    ```
    """
    from pipelines.build_dataset import build_dataset, summary_rows

    cfg = _no_dem(load(config), dem, no_dem)
    res = build_dataset(sources, dem, out, cfg, workers=workers, scheduler=scheduler, overwrite=overwrite)
    table("gtgen build", summary_rows(res))
    if any(not r.ok for r in res.drives):
        raise typer.Exit(code=2)
