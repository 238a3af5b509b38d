"""``gtgen report``: a dataset card and QA figures; label error against synth truth."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gtgen import codes
from gtgen.config import RANGES, GtgenConfig
from gtgen.geometry import grid_xy, yaw_transform
from gtgen.storage.stores import open_dataset

REGIONS = {code: codes.REGIONS[code] for code in codes.LABELLED}


@dataclass
class Report:
    """Numbers of the dataset card (also written as JSON beside the figures)."""

    card: dict = field(default_factory=dict)
    truth: dict = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)


def _coverage(g, r: str, idx: np.ndarray) -> dict[str, float]:
    counts = np.zeros(len(codes.REGIONS), np.int64)
    for k in idx:
        counts += np.bincount(g[f"labels/{r}/region"][int(k)].ravel(), minlength=len(codes.REGIONS))
    tot = max(int(counts.sum()), 1)
    return {codes.REGIONS[i]: counts[i] / tot for i in codes.REGIONS}


def build_report(dataset: Path, out_dir: Path, max_truth_samples: int = 40) -> Report:
    """Return the report of ``dataset`` and write its JSON and PNG figures into ``out_dir``."""
    import json

    g, info = open_dataset(dataset)
    attrs = info.attrs
    S = info.n_samples
    rep = Report()
    rej_reason = g["rejected/reason"][:]
    fit = g["meta/icp_fitness"][:] if S else np.zeros(0)
    rfit = g["rejected/icp_fitness"][:]
    idx = np.unique(np.linspace(0, S - 1, min(S, max_truth_samples)).astype(int)) if S else np.zeros(0, int)
    split = g["meta/split"][:] if S else np.zeros(0)
    rep.card = {
        "dataset": str(dataset),
        "samples_kept": S,
        "samples_rejected": {codes.reason_name(c): int((rej_reason == c).sum()) for c in np.unique(rej_reason)},
        "split": {name: int((split == code).sum()) for code, name in codes.SPLITS.items()},
        "coverage": {r: {k: round(float(v), 4) for k, v in _coverage(g, r, idx).items()} for r in RANGES} if S else {},
        "icp_fitness": _quantiles(np.concatenate([fit, rfit[np.isfinite(rfit)]])),
        "icp_rmse_m": _quantiles(g["meta/icp_rmse_m"][:]) if S else {},
        "alignment": attrs.drives[0].alignment if len(attrs.drives) == 1 else {},
    }
    bag_paths = [b.path for d in attrs.drives for b in d.bags]
    from gtgen.synth.truth import Truth

    truth = Truth.find(bag_paths)
    cfg = GtgenConfig.model_validate(attrs.config)
    if truth is not None and S:
        rep.truth = _truth_errors(g, cfg, truth, idx)
    out_dir.mkdir(parents=True, exist_ok=True)
    rep.figures = _figures(g, rep, out_dir, fit, rfit, rej_reason)
    (out_dir / "report.json").write_text(json.dumps({"card": rep.card, "truth": rep.truth}, indent=2, default=float))
    return rep


def _quantiles(x: np.ndarray) -> dict[str, float]:
    x = x[np.isfinite(x)]
    if not len(x):
        return {}
    return {"min": round(float(x.min()), 4), "p05": round(float(np.quantile(x, 0.05)), 4),
            "median": round(float(np.median(x)), 4), "max": round(float(x.max()), 4)}


def _truth_errors(g, cfg: GtgenConfig, truth, idx: np.ndarray) -> dict:
    t = g["meta/t_ns"][:]
    pos = g["meta/pos_odom_m"][:]
    yaw = g["meta/yaw_odom_rad"][:]
    Tct = g["meta/T_crs_target"][:]
    acc = {r: {reg: {"elev_abs": 0.0, "n": 0, "risk_sq": 0.0, "nr": 0, "xr_abs": 0.0, "nx": 0} for reg in REGIONS.values()} for r in RANGES}
    fused_vs_single = {r: {"fused_abs": 0.0, "single_abs": 0.0, "n": 0} for r in RANGES}
    h_err, v_err, h_err_far = [], [], []
    for k in idx:
        k = int(k)
        T_odom_target = yaw_transform(*pos[k], yaw[k])
        T_true = truth.T_crs_odom(int(t[k])) @ T_odom_target
        # alignment error at the vehicle and 50 m ahead
        for pt, lst in ((np.array([0.0, 0, 0, 1]), h_err), (np.array([50.0, 0, 0, 1]), h_err_far)):
            lst.append(float(np.linalg.norm((Tct[k] @ pt)[:2] - (T_true @ pt)[:2])))
        v_err.append(float(Tct[k][2, 3] - T_true[2, 3]))
        for r in RANGES:
            _add_sample_errors(g, cfg, truth, k, r, T_odom_target, acc[r], fused_vs_single[r])
    out: dict = {"samples_evaluated": int(len(idx))}
    for r in RANGES:
        out[r] = {}
        for name, a in acc[r].items():
            out[r][name] = {
                "elevation_mae_m": round(a["elev_abs"] / a["n"], 4) if a["n"] else None,
                "risk_mse": round(a["risk_sq"] / a["nr"], 5) if a["nr"] else None,
                "xracer_elevation_mae_m": round(a["xr_abs"] / a["nx"], 4) if a["nx"] else None,
                "cells": a["n"],
            }
        fs = fused_vs_single[r]
        out[r]["fused_vs_single_map"] = {
            "fused_mae_m": round(fs["fused_abs"] / fs["n"], 4) if fs["n"] else None,
            "single_map_mae_m": round(fs["single_abs"] / fs["n"], 4) if fs["n"] else None,
            "cells": fs["n"],
        }
    out["dem_alignment"] = {
        "horizontal_at_vehicle_m": _quantiles(np.asarray(h_err)),
        "horizontal_50m_ahead_m": _quantiles(np.asarray(h_err_far)),
        "vertical_m": _quantiles(np.abs(np.asarray(v_err))),
    }
    return out


def _add_sample_errors(g, cfg: GtgenConfig, truth, k: int, r: str, T_odom_target: np.ndarray, acc: dict, fs: dict) -> None:
    """Accumulate sample ``k``'s label, risk and X-Racer errors of range ``r`` per region."""
    gr = cfg.grids.get(r)
    X, Y = grid_xy(gr.size, gr.resolution_m)
    te, trisk = truth.labels(T_odom_target, X, Y, int(g["meta/t_ns"][k]))
    el = g[f"labels/{r}/elevation_m"][k]
    reg = g[f"labels/{r}/region"][k]
    rk = g[f"labels/{r}/risk"][k]
    xe = g[f"xracer/{r}/elevation_m"][k]
    xc = g[f"xracer/{r}/confidence"][k]
    for code, name in REGIONS.items():
        m = (reg == code) & np.isfinite(el)
        a = acc[name]
        a["elev_abs"] += float(np.abs(el[m] - te[m]).sum())
        a["n"] += int(m.sum())
        mr = (reg == code) & np.isfinite(rk)
        a["risk_sq"] += float(((rk[mr] - trisk[mr]) ** 2).sum())
        a["nr"] += int(mr.sum())
        mx = (reg == code) & np.isfinite(xe)
        a["xr_abs"] += float(np.abs(xe[mx] - te[mx]).sum())
        a["nx"] += int(mx.sum())
    # averaging works: fused vs the single X-Racer map at t on cells both call confident
    both = codes.observed(reg) & np.isfinite(el) & np.isfinite(xe) & (xc > cfg.fuse.min_conf)
    fs["fused_abs"] += float(np.abs(el[both] - te[both]).sum())
    fs["single_abs"] += float(np.abs(xe[both] - te[both]).sum())
    fs["n"] += int(both.sum())


def _figures(g, rep: Report, out_dir: Path, fit, rfit, rej_reason) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    cov = rep.card.get("coverage", {})
    for i, r in enumerate(cov):
        keys = list(cov[r])
        ax[0].bar(np.arange(len(keys)) + 0.4 * i, [100 * cov[r][k] for k in keys], width=0.4, label=r)
        ax[0].set_xticks(np.arange(len(keys)) + 0.2, keys)
    ax[0].set_ylabel("% of cells")
    ax[0].set_title("label coverage per region")
    ax[0].legend()
    allfit = np.concatenate([fit, rfit[np.isfinite(rfit)]])
    ax[1].hist(allfit, bins=30, range=(0, 1), color="tab:blue")
    ax[1].set_title("ICP fitness (all aligned samples)")
    ax[1].set_xlabel("fitness")
    names = [codes.reason_name(c) for c in np.unique(rej_reason)]
    vals = [int((rej_reason == c).sum()) for c in np.unique(rej_reason)]
    ax[2].bar(["kept"] + names, [rep.card["samples_kept"]] + vals, color=["tab:green"] + ["tab:red"] * len(vals))
    ax[2].set_title("samples kept / rejected by reason")
    ax[2].tick_params(axis="x", rotation=30)
    fig.tight_layout()
    p = out_dir / "qa_overview.png"
    fig.savefig(p, dpi=80)
    plt.close(fig)
    paths.append(p)
    if rep.card["samples_kept"]:
        en = g["meta/crs_en_m"][:]
        fig, ax = plt.subplots(figsize=(6, 6))
        sc = ax.scatter(en[:, 0], en[:, 1], c=fit, cmap="viridis", vmin=0, vmax=1, s=12)
        ax.set_aspect("equal")
        ax.set_title("sample positions (DEM CRS), colour = ICP fitness")
        fig.colorbar(sc)
        p = out_dir / "qa_track.png"
        fig.savefig(p, dpi=80)
        plt.close(fig)
        paths.append(p)
    if rep.truth:
        fig, ax = plt.subplots(figsize=(7, 4))
        for i, r in enumerate(RANGES):
            vals = [rep.truth[r][reg]["elevation_mae_m"] or 0 for reg in REGIONS.values()]
            ax.bar(np.arange(3) + 0.4 * i, vals, width=0.4, label=r)
        ax.set_xticks(np.arange(3) + 0.2, list(REGIONS.values()))
        ax.set_ylabel("elevation MAE vs truth [m]")
        ax.set_title("label error against synth truth")
        ax.legend()
        p = out_dir / "qa_label_error.png"
        fig.savefig(p, dpi=80)
        plt.close(fig)
        paths.append(p)
    return paths
