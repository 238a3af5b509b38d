"""The commands that look at a dataset: report and viz."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from gtgen.cli.app import WORKSPACE, OverwriteOpt, app, na, table


@app.command()
def report(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", metavar="DATASET", help="dataset from 'gtgen dem-align'"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="folder for report.json and PNGs [default: report/]"),
    overwrite: bool = OverwriteOpt,
) -> None:
    """Print a dataset card (kept/rejected, coverage, ICP fitness) and write QA figures.

    With synth truth beside the bags, also the label error per region and range and the
    DEM alignment error. The thresholds are those the dataset was built with (its
    recorded config), so the report takes no --config.

    **Examples**

    ```
    gtgen report
    gtgen report datasets/paso.zarr -o qa/
    ```
    """
    from gtgen.report import build_report

    out = out or Path("report")
    rep = build_report(dataset, out, overwrite=overwrite)
    c = rep.card
    rows: list[tuple[str, Any]] = [("dataset", c["dataset"]), ("samples kept", c["samples_kept"])]
    if c.get("samples_kept_by_odometry"):
        rows.append(("  of them by odometry over set-aside tiles", c["samples_kept_by_odometry"]))
    rows += [(f"  rejected: {k}", v) for k, v in c["samples_rejected"].items()]
    rows += [(f"  split {k}", v) for k, v in c["split"].items()]
    if len(c.get("split_by_drive", {})) > 1:
        rows += [(f"  drive {d}", ", ".join(f"{k} {v}" for k, v in n.items() if v)) for d, n in c["split_by_drive"].items()]
    if c.get("image_bytes_per_sample"):
        rows.append(("images per sample (JPEG, all cameras)", f"{c['image_bytes_per_sample'] / 1e3:.1f} kB"))
    if c.get("dem"):
        rows.append(("DEM", c["dem"]))
    if c.get("scan_input"):
        rows.append(("N-scan input (points: newest scan, all)", ", ".join(f"{k.replace('_', ' ')} {v:g}" for k, v in c["scan_input"].items())))
    for r, cov in c.get("coverage", {}).items():
        rows.append((f"coverage {r}", ", ".join(f"{k} {100 * v:.1f}%" for k, v in cov.items())))
    for r, share in c.get("region_share_pct", {}).items():
        paper = c["paper_region_share_pct"][r]
        rows.append((f"regions {r} (% of labelled; paper Tab. I)", ", ".join(f"{k} {na(v, '%')} ({paper[k]}%)" for k, v in share.items())))
    rows += _xracer_rows(c.get("xracer_at_t"))
    if c.get("icp_fitness"):
        rows.append(("ICP fitness", ", ".join(f"{k} {v:.3f}" for k, v in c["icp_fitness"].items())))
    a = c.get("alignment", {})
    if a:
        rows.append(("GNSS fit", f"rms {a['gnss_rms_m']:.2f} m, {a['gnss_outliers']} outliers; geoid offset {a['geoid_offset_m']:+.2f} m"))
    t = rep.truth
    if t.get("micro"):
        for r in ("micro", "short"):
            for reg in ("obs_pc", "obs_f", "unobs"):
                e = t[r][reg]
                rows.append((f"truth {r} {reg}", f"elev MAE {na(e['elevation_mae_m'], ' m')}, risk MSE {na(e['risk_mse'])}, "
                                                  f"X-Racer MAE {na(e['xracer_elevation_mae_m'], ' m')}"))
            fv = t[r]["fused_vs_single_map"]
            rows.append((f"truth {r} fused vs single map", f"{na(fv['fused_mae_m'], ' m')} vs {na(fv['single_map_mae_m'], ' m')} on {fv['cells']} cells"))
            fr = t[r].get("fatal_risk")
            if fr:
                rows.append((f"truth {r} fatal risk", f"precision {na(fr['precision'])}, recall {na(fr['recall'])} against the truth's obstacles on {fr['cells']} observed cells"))
        d = t["dem_alignment"]
        hv, ha, vv = d["horizontal_at_vehicle_m"], d["horizontal_50m_ahead_m"], d["vertical_m"]
        rows.append(("DEM alignment error", "none: no sample is placed (no DEM)") if not hv else ("DEM alignment error", f"horizontal median {na(hv.get('median'), ' m')} (max {na(hv.get('max'), ' m')}), "
                                            f"at 50 m ahead median {na(ha.get('median'), ' m')}, vertical median {na(vv.get('median'), ' m')} (max {na(vv.get('max'), ' m')})"))
    rj = t.get("rejections")
    if rj:
        c = rj["confusion"]
        rows.append(("truth: kept (good / bad)", f"{c['kept']['good']} / {c['kept']['bad']}"))
        rows.append(("truth: rejected (good / bad)", f"{c['rejected']['good']} / {c['rejected']['bad']}"))
        rows.append(("truth: bad rejected, good kept", f"{na(rj['bad_rejected_pct'], ' %')}, {na(rj['good_kept_pct'], ' %')}"))
        rows += [(f"truth: reasons of rejected {cls}", ", ".join(f"{k} {v}" for k, v in r.items()) or "none") for cls, r in rj["reasons"].items()]
        fe, ga = rj["fill_error_m"]["kept"], rj["gnss_fit_alone_error"]
        if fe:
            rows.append(("truth: DEM fill error of kept", f"median {na(fe['median'], ' m')}, max {na(fe['max'], ' m')}"))
        rows.append(("truth: GNSS fit alone", f"horizontal median {na(ga['horizontal_m'].get('median'), ' m')}, vertical {na(ga['vertical_m'].get('median'), ' m')}, "
                                              f"yaw {na(ga['yaw_deg'].get('median'), ' deg')}"))
    rows.append(("figures", ", ".join(str(p) for p in rep.figures)))
    table("gtgen report", rows)


def _xracer_rows(x: dict | None) -> list[tuple[str, str]]:
    """Return the card's X-Racer-at-t rows (the stack's map at t against the labels) beside
    the paper's Tab. I / II numbers (in brackets)."""
    if not x:
        return []

    def num(v: float | None, digits: int, unit: str = "") -> str:
        return "n/a" if v is None else f"{v:.{digits}f}{unit}"

    rows = []
    for r in ("micro", "short"):
        e, p = x[r]["elevation"], x["paper"][r]
        cells = []
        for k in ("obs_pc", "obs_f", "unobs"):
            pc = p["coverage_pct"][k]
            cells.append(f"{k} {num(e[k]['mae_m'], 3, ' m')} ({num(e[k]['coverage_pct'], 0, ' %')}) "
                         f"[{p['mae_m'][k]:.3f} m{'' if pc is None else f' ({pc:.0f} %)'}]")
        rows.append((f"X-Racer at t {r}: elevation MAE (coverage) [paper, Tab. I]", ", ".join(cells)))
        rk = x[r]["risk"]
        rows.append((f"X-Racer at t {r}: fatal risk [paper, Tab. II]", ", ".join(
            f"{k} {num(rk[k], 4 if k == 'mse' else 3)} [{p['risk'][k]}]" for k in ("mse", "precision", "recall", "f1"))))
    return rows


@app.command()
def viz(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", metavar="DATASET", help="dataset from 'gtgen dem-align'"),
    sample: int = typer.Option(0, "--sample", "-n", min=0, help="sample index (0 is the first)"),
    out: Path = typer.Option(Path("sample.png"), "-o", "--out", help="PNG to write"),
    ckpt: Optional[Path] = typer.Option(None, "--ckpt", metavar="CKPT", help="also draw this checkpoint's predictions"),
    device: Optional[str] = typer.Option(None, help="device of the prediction: auto | cpu | cuda | cuda:N [default: auto]"),
    overwrite: bool = OverwriteOpt,
) -> None:
    """Draw one sample: its cameras' images, and per range labels, regions, X-Racer at t, DEM.

    Reads only the dataset (grids and resolutions as recorded in it): no --config.

    **Examples**

    ```
    gtgen viz --sample 12 -o s12.png
    gtgen viz datasets/paso.zarr -n 0 -o first.png
    gtgen viz -n 12 --ckpt runs/latest/best.pt -o pred12.png
    ```
    """
    from gtgen.runtime.output import check_replace
    from gtgen.viz import render_sample

    check_replace(out, overwrite)  # before the prediction
    pred = None
    if ckpt is not None:
        from gtgen.train.trainer import predict_sample

        pred = predict_sample(dataset, ckpt, sample, device)
    p = render_sample(dataset, sample, out, pred, overwrite=overwrite)
    table("gtgen viz", [("figure", p)])


@app.command()
def verify(
    store: Path = typer.Argument(WORKSPACE / "dataset.zarr", metavar="STORE", help="a store gtgen wrote: drive, fused or dataset"),
) -> None:
    """Check a store whole: every chunk and shard file it was written with is there with its
    size and CRC32C, metadata unchanged, every chunk decodes (checksums). Exit code 1 if
    damaged, or if it holds files it was not written with (then it says which: removing
    them is enough).

    **Examples**

    ```
    gtgen verify                          # gtgen_ws/dataset.zarr
    gtgen verify gtgen_ws/drive.zarr
    ```
    """
    from gtgen.errors import GtgenError
    from gtgen.storage.stores import verify_store

    fmt, v = verify_store(store)
    rows: list[tuple[str, Any]] = [("store", store), ("kind", fmt.kind), ("files checked", v.checked)]
    rows += [("problem", p) for p in v.problems[:20]]
    if len(v.problems) > 20:
        rows.append(("", f"... and {len(v.problems) - 20} more"))
    strays = v.strays + v.extra  # gtgen did not write them: chunk-named ones first (zarr reads those)
    rows += [("not written by gtgen", f) for f in strays[:20]]
    if len(strays) > 20:
        rows.append(("", f"... and {len(strays) - 20} more"))
    files = f"{len(strays)} file{'s' if len(strays) > 1 else ''}"
    verdict = (f"DAMAGED ({len(v.problems)} problems)" if v.problems else
               f"holds {files} gtgen did not write, {len(v.strays)} named as chunks" if v.strays else
               "whole" + (f", with {files} gtgen did not write" if v.extra else ""))
    rows.append(("verdict", verdict))
    table("gtgen verify", rows)
    if v.problems:
        more = f" (and {len(v.problems) - 1} more)" if len(v.problems) > 1 else ""
        raise GtgenError(f"store '{store}' is damaged: {v.problems[0]}{more}; rebuild it with '{fmt.made_by}'")
    if strays:
        more = f" (and {len(strays) - 1} more)" if len(strays) > 1 else ""
        them = "them" if len(strays) > 1 else "it"
        read = ("named as a chunk, which zarr would read as data; the data gtgen wrote is there: removing "
                f"{them} is enough (then verify again)") if v.strays else f"its data is whole: removing {them} is enough (nothing to rebuild)"
        raise GtgenError(f"store '{store}' holds {files} gtgen did not write: '{strays[0]}'{more}, {read}")
