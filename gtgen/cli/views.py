"""The commands that look at a dataset: report and viz."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from gtgen.cli.app import WORKSPACE, app, table


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
    if c.get("samples_kept_by_odometry"):
        rows.append(("  of them by odometry over set-aside tiles", c["samples_kept_by_odometry"]))
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
    if t.get("micro"):
        for r in ("micro", "short"):
            for reg in ("obs_pc", "obs_f", "unobs"):
                e = t[r][reg]
                rows.append((f"truth {r} {reg}", f"elev MAE {e['elevation_mae_m']} m, risk MSE {e['risk_mse']}, X-Racer MAE {e['xracer_elevation_mae_m']} m"))
            fv = t[r]["fused_vs_single_map"]
            rows.append((f"truth {r} fused vs single map", f"{fv['fused_mae_m']} m vs {fv['single_map_mae_m']} m on {fv['cells']} cells"))
        d = t["dem_alignment"]
        rows.append(("DEM alignment error", f"horizontal median {d['horizontal_at_vehicle_m'].get('median')} m (max {d['horizontal_at_vehicle_m'].get('max')}), "
                                            f"at 50 m ahead median {d['horizontal_50m_ahead_m'].get('median')} m, vertical median {d['vertical_m'].get('median')} m (max {d['vertical_m'].get('max')})"))
    rj = t.get("rejections")
    if rj:
        c = rj["confusion"]
        rows.append(("truth: kept (good / bad)", f"{c['kept']['good']} / {c['kept']['bad']}"))
        rows.append(("truth: rejected (good / bad)", f"{c['rejected']['good']} / {c['rejected']['bad']}"))
        rows.append(("truth: bad rejected, good kept", f"{rj['bad_rejected_pct']} %, {rj['good_kept_pct']} %"))
        rows += [(f"truth: reasons of rejected {cls}", ", ".join(f"{k} {v}" for k, v in r.items()) or "none") for cls, r in rj["reasons"].items()]
        fe, ga = rj["fill_error_m"]["kept"], rj["gnss_fit_alone_error"]
        if fe:
            rows.append(("truth: DEM fill error of kept", f"median {fe['median']} m, max {fe['max']} m"))
        rows.append(("truth: GNSS fit alone", f"horizontal median {ga['horizontal_m'].get('median')} m, vertical {ga['vertical_m'].get('median')} m, "
                                              f"yaw {ga['yaw_deg'].get('median')} deg"))
    rows.append(("figures", ", ".join(str(p) for p in rep.figures)))
    table("gtgen report", rows)


@app.command()
def viz(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", help="dataset from 'gtgen dem-align'"),
    sample: int = typer.Option(0, "--sample", "-n", help="sample index"),
    out: Path = typer.Option(Path("sample.png"), "-o", "--out", help="PNG to write"),
    ckpt: Optional[Path] = typer.Option(None, "--ckpt", help="also draw this checkpoint's predictions"),
    device: Optional[str] = typer.Option(None, help="device of the prediction: auto | cpu | cuda | cuda:N [default: auto]"),
) -> None:
    """Draw one sample: the four images, and per range labels, regions, X-Racer at t, DEM.

    **Examples**

        gtgen viz --sample 12 -o s12.png

        gtgen viz --sample 12 --ckpt runs/latest/best.pt --device cuda -o s12_pred.png
    """
    from gtgen.viz import render_sample

    pred = None
    if ckpt is not None:
        from gtgen.train.trainer import predict_sample

        pred = predict_sample(dataset, ckpt, sample, device)
    p = render_sample(dataset, sample, out, pred)
    table("gtgen viz", [("figure", p)])
