"""The report's QA figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gtgen import codes
from gtgen.config import RANGES
from gtgen.report.stats import REGIONS
from gtgen.runtime.output import save_figure
from gtgen.storage.dataset import DatasetStore

OVERVIEW_PNG, TRACK_PNG, LABEL_ERROR_PNG, SIGNALS_PNG = "qa_overview.png", "qa_track.png", "qa_label_error.png", "qa_rejection_signals.png"
FIGURES = (OVERVIEW_PNG, TRACK_PNG, LABEL_ERROR_PNG, SIGNALS_PNG)  # every figure the report may write


def figures(ds: DatasetStore, rep, out_dir: Path, fit, rfit, rej_reason, overwrite: bool = False) -> list[Path]:
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
    ax[0].set_xlabel("region")
    ax[0].set_ylabel("cells [% of the grid]")
    ax[0].set_title("label coverage per region")
    ax[0].legend(title="range")
    allfit = np.concatenate([fit, rfit])
    ax[1].hist(allfit[np.isfinite(allfit)], bins=30, range=(0, 1), color="tab:blue")
    ax[1].set_title("ICP fitness (all aligned samples)")
    ax[1].set_xlabel("ICP fitness [0..1]")
    ax[1].set_ylabel("samples")
    names = [codes.reason_name(c) for c in np.unique(rej_reason)]
    vals = [int((rej_reason == c).sum()) for c in np.unique(rej_reason)]
    ax[2].bar(["kept"] + names, [rep.card["samples_kept"]] + vals, color=["tab:green"] + ["tab:red"] * len(vals))
    ax[2].set_title("samples kept / rejected by reason")
    ax[2].set_xlabel("kept, or rejection reason")
    ax[2].set_ylabel("samples")
    ax[2].tick_params(axis="x", rotation=30)
    fig.tight_layout()
    paths.append(save_figure(fig, out_dir / OVERVIEW_PNG, overwrite))
    plt.close(fig)
    if rep.card["samples_kept"]:
        en = ds.meta("crs_en_m")
        frame = "DEM CRS"
        if not np.isfinite(en).all():  # samples without a placement (no DEM): where odometry has them
            en, frame = ds.meta("pos_odom_m")[:, :2], "odom, no DEM"
        lo, hi = en.min(axis=0) - 120, en.max(axis=0) + 120  # the short grids' reach
        w, h = hi - lo
        fig, ax = plt.subplots(figsize=(10, float(np.clip(8.5 * h / w, 3.5, 12)) + 1))
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        icp = np.isfinite(fit)
        sc = ax.scatter(en[icp, 0], en[icp, 1], c=fit[icp], cmap="viridis", vmin=0, vmax=1, s=12)
        if not icp.all():  # kept by odometry over set-aside tiles (dem.carry_over_m), or no DEM
            ax.scatter(en[~icp, 0], en[~icp, 1], c="tab:gray", s=12, label="no ICP" if frame != "DEM CRS" else "kept by odometry, no ICP")
        _draw_tiles(ax, ds)
        ax.legend(fontsize=8, loc="upper right")
        ax.set_aspect("equal")
        ax.ticklabel_format(useOffset=False, style="plain")  # whole easting / northing, not an offset
        ax.tick_params(axis="x", rotation=30)
        ax.set_xlabel(f"easting [m] ({frame})" if frame == "DEM CRS" else f"x [m] ({frame})")
        ax.set_ylabel(f"northing [m] ({frame})" if frame == "DEM CRS" else f"y [m] ({frame})")
        ax.set_title("sample positions, colour = ICP fitness; DEM tiles by status, the corrected and set-aside ones with\n"
                     "their borders' height steps as read -> put back and measured offset dx, dy, dz +- 1 sigma [m]", fontsize=9)
        fig.colorbar(sc, ax=ax, shrink=0.8, label="ICP fitness [0..1]")
        fig.tight_layout()
        paths.append(save_figure(fig, out_dir / TRACK_PNG, overwrite))
        plt.close(fig)
    if rep.truth.get("micro"):
        fig, ax = plt.subplots(figsize=(7, 4))
        for i, r in enumerate(RANGES):
            vals = [rep.truth[r][reg]["elevation_mae_m"] or 0 for reg in REGIONS.values()]
            ax.bar(np.arange(3) + 0.4 * i, vals, width=0.4, label=r)
        ax.set_xticks(np.arange(3) + 0.2, list(REGIONS.values()))
        ax.set_xlabel("region")
        ax.set_ylabel("elevation MAE vs truth [m]")
        ax.set_title("label error against synth truth")
        ax.legend(title="range")
        paths.append(save_figure(fig, out_dir / LABEL_ERROR_PNG, overwrite))
        plt.close(fig)
    return paths


SIGNALS = (  # (signal recorded per kept and per rejected sample, label, threshold key in dem config, above is bad)
    ("icp_fitness", "ICP fitness [0..1]", "min_fitness", False),
    ("icp_rmse_m", "ICP inlier RMSE [m]", "max_rmse_m", True),
    ("dem_disagreement", "share of ground disagreeing with the DEM [0..1]", "max_disagreement", True),
    ("gnss_offset_m", "GNSS offset of the placed track [m]", "max_gnss_offset_m", True),
    ("vegetation_share", "share of observed cells left out as vegetation [0..1]", None, True),
)


def signal_figure(ds: DatasetStore, dem_cfg, out_dir: Path, overwrite: bool = False) -> Path:
    """Draw the distributions of the rejection signals, kept and rejected samples apart,
    with the thresholds dem-align used."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 7))
    corr_k = ds.meta("icp_correction")
    corr_r = ds.rejected("icp_correction")
    panels = [(ds.meta(name), ds.rejected(name), label, key) for name, label, key, _ in SIGNALS]
    panels.insert(2, (np.hypot(corr_k[:, 0], corr_k[:, 1]), np.hypot(corr_r[:, 0], corr_r[:, 1]), "ICP correction xy [m]", "max_correction_m"))
    for ax, (kept, rej, label, key) in zip(axes.ravel(), panels):
        kept, rej = kept[np.isfinite(kept)], rej[np.isfinite(rej)]
        both = np.concatenate([kept, rej])
        lo, hi = (both.min(), both.max()) if len(both) else (0.0, 1.0)
        bins = np.linspace(lo, hi if hi > lo else lo + 1.0, 30)  # one value alone: a unit-wide axis, not a 1e-9 one
        ax.hist([kept, rej], bins=bins, stacked=True, color=["tab:green", "tab:red"], label=["kept", "rejected"])
        if key is not None:
            ax.axvline(getattr(dem_cfg, key), color="k", ls="--", lw=1, label=f"dem.{key}")
        ax.set_title(label, fontsize=9)
        ax.set_xlabel(label, fontsize=8)
        ax.set_ylabel("samples", fontsize=8)
        ax.legend(fontsize=7)
    fig.suptitle("rejection signals of every sample ICP ran on")
    fig.tight_layout()
    p = save_figure(fig, out_dir / SIGNALS_PNG, overwrite)
    plt.close(fig)
    return p



_TILE_COLOURS = {"ok": "tab:green", "corrected": "tab:orange", "set_aside": "tab:red", "unjudged": "tab:gray"}


def _draw_tiles(ax, ds: DatasetStore) -> None:
    """Outline every DEM tile dem-align judged (colour = status); the corrected and set-aside
    ones with the height steps across their borders as read and put back, their measured
    offset and uncertainty, and for the corrected an arrow of the offset (x20)."""
    import rasterio
    from matplotlib.patches import Rectangle
    from rasterio.warp import transform_bounds

    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    seen = set()
    for entry in ds.info.drives:
        for t in entry.tiles:
            try:
                with rasterio.open(t.path) as src:
                    l, b, r, tp = transform_bounds(src.crs, entry.crs, *src.bounds)
            except Exception:  # noqa: BLE001 - a tile moved since: the figure goes without it
                continue
            c = _TILE_COLOURS.get(t.status, "k")
            seen.add(t.status)
            ax.add_patch(Rectangle((l, b), r - l, tp - b, fill=False, ec=c, lw=1.2, ls="-" if t.status != "unjudged" else ":"))
            if t.status in ("corrected", "set_aside") and t.offset_m[0] is not None:
                txt = "\n".join(f"{a} {o:+.2f} +- {sg:.2f}" for a, o, sg in zip("xyz", t.offset_m, t.sigma_m) if o is not None and sg is not None)
                steps = f"\nsteps {t.border_step_m:.2f} -> {t.border_step_put_back_m:.2f} m" if t.border_step_m is not None else ""
                cx, cy = min(max((l + r) / 2, x0), x1), min(max((b + tp) / 2, y0), y1)
                ax.text(cx, cy, f"{t.status.replace('_', ' ')}{steps}\n{txt}", fontsize=7, color=c, ha="center", va="center", clip_on=True,
                        bbox={"fc": "white", "ec": c, "alpha": 0.8})
                if t.status == "corrected":
                    ax.annotate("", xy=(cx + 20 * t.applied_m[0], cy + 20 * t.applied_m[1]), xytext=(cx, cy),
                                arrowprops={"arrowstyle": "->", "color": c})
    for status in sorted(seen):  # legend entries
        ax.plot([], [], color=_TILE_COLOURS.get(status, "k"), label=f"tile {status.replace('_', ' ')}")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
