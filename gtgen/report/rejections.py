"""How well dem-align's decisions did on a synthetic drive: every sample it placed (kept,
rejected after ICP, or set aside with a tile it did not trust) against the truth, as a
confusion table of kept / rejected by truly good / bad, with the reasons of each
rejection. Samples that could not be placed (no DEM under them, too few observed cells, no
fused maps) are counted apart.

A sample is truly bad (``report.bad_*``) when its placement is farther from the truth
than ``bad_vertical_m`` (or ``bad_horizontal_m``, if set), or when its DEM fill would be
wrong by more than ``bad_fill_m`` on average over its short grid: the DEM height at the place the sample
was put minus the true ground where each cell truly is. That counts a placement off where
the terrain is not flat, a shifted or wrong tile and changed terrain alike. A kept sample
is not filled from the tiles dem-align set aside, so they do not count in its fill; a
sample set aside with them would have been filled from them, so for it they do.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gtgen import codes
from gtgen.config import GtgenConfig
from gtgen.geometry import yaw_transform
from gtgen.grids import grid_xy
from gtgen.report.stats import quantiles
from gtgen.storage.dataset import DatasetStore

FOOTPRINT_STEP = 5  # every 5th short cell along each axis: enough for a share of the grid


def _placed(ds: DatasetStore, drive: int) -> dict[str, np.ndarray]:
    """Return every sample of drive ``drive`` that got a placement: kept ones, then rejected
    ones ICP ran on or set aside with a tile."""
    rT, reason, rdrive = ds.rejected("T_crs_target"), ds.rejected("reason"), ds.rejected("drive")
    has = (rdrive == drive) & (np.isfinite(ds.rejected("icp_fitness")) | ((reason == codes.SUSPECT_TILE) & np.isfinite(rT[:, 0, 0])))
    mine = ds.meta("drive") == drive
    return {
        "t": np.concatenate([ds.meta("t_ns")[mine], ds.rejected("t_ns")[has]]),
        "T": np.concatenate([ds.meta("T_crs_target")[mine], rT[has]]),
        "pos": np.concatenate([ds.meta("pos_odom_m")[mine], ds.rejected("pos_odom_m")[has]]),
        "yaw": np.concatenate([ds.meta("yaw_odom_rad")[mine], ds.rejected("yaw_odom_rad")[has]]),
        "reason": np.concatenate([np.zeros(int(mine.sum()), np.uint8), reason[has]]),
    }


def _set_aside(entry: Any, crs: str) -> list[tuple[float, float, float, float]]:
    """Return the bounds (working CRS) of the DEM tiles dem-align did not use for a drive."""
    import rasterio
    from rasterio.warp import transform_bounds

    out = []
    for path in entry.suspect_tiles:
        with rasterio.open(path) as src:
            out.append(transform_bounds(src.crs, crs, *src.bounds))
    return out


def _put_back(entry: Any, crs: str) -> list[tuple[tuple[float, float, float, float], tuple[float, float, float]]]:
    """Return (bounds where it is read, applied offset) of the DEM tiles dem-align read put back for a drive."""
    import rasterio
    from rasterio.warp import transform_bounds

    out = []
    for t in entry.tiles:
        if t.status == "corrected":
            dx, dy, dz = t.applied_m
            with rasterio.open(t.path) as src:
                l, b, r, tp = transform_bounds(src.crs, crs, *src.bounds)
            out.append(((l - dx, b - dy, r - dx, tp - dy), (dx, dy, dz)))
    return out


def _errors(ds: DatasetStore, cfg: GtgenConfig, truth: Any, drive: int) -> tuple[np.ndarray, ...]:
    """Return per placed sample of drive ``drive`` its reason and its errors against the
    truth: horizontal and vertical placement, mean DEM fill error, and the GNSS fit's alone
    (horizontal, vertical, yaw [deg])."""
    p = _placed(ds, drive)
    entry = ds.info.drives[drive]
    aside = _set_aside(entry, entry.crs)
    back = _put_back(entry, entry.crs)
    gs = cfg.grids.short
    X, Y = (a[::FOOTPRINT_STEP, ::FOOTPRINT_STEP] for a in grid_xy(gs.size, gs.resolution_m))
    al = entry.alignment
    T_gnss = yaw_transform(al["gnss_tx_m"], al["gnss_ty_m"], al["dz_dem_m"], al["gnss_yaw_rad"])
    rows = []
    for i in range(len(p["t"])):
        T_odom_target = yaw_transform(*p["pos"][i], p["yaw"][i])
        T_true = truth.T_crs_odom(int(p["t"][i])) @ T_odom_target
        h = float(np.hypot(*(p["T"][i][:2, 3] - T_true[:2, 3])))
        v = float(abs(p["T"][i][2, 3] - T_true[2, 3]))
        Tu = p["T"][i]
        Eu, Nu = Tu[0, 0] * X + Tu[0, 1] * Y + Tu[0, 3], Tu[1, 0] * X + Tu[1, 1] * Y + Tu[1, 3]
        Et, Nt = T_true[0, 0] * X + T_true[0, 1] * Y + T_true[0, 3], T_true[1, 0] * X + T_true[1, 1] * Y + T_true[1, 3]
        used = np.ones(Eu.shape, bool)
        for l, b, r, t in aside if p["reason"][i] != codes.SUSPECT_TILE else ():
            used &= ~((Eu >= l) & (Eu < r) & (Nu > b) & (Nu <= t))
        Ed, Nd, dz = Eu.copy(), Nu.copy(), np.zeros(Eu.shape)  # where the DEM heights come from: put back tiles moved
        for (l, b, r, t), (ox, oy, oz) in back:
            on = (Eu >= l) & (Eu < r) & (Nu > b) & (Nu <= t)
            Ed[on], Nd[on], dz[on] = Eu[on] + ox, Nu[on] + oy, oz
        fill_err = (truth.dem_heights(Ed, Nd) - dz - Tu[2, 3]) - (truth.ground(Et, Nt) - T_true[2, 3])
        wrong = float(np.abs(fill_err)[used].mean()) if used.any() else 0.0
        G = T_gnss @ T_odom_target
        gyaw = np.degrees(abs(np.arctan2(G[1, 0] * T_true[0, 0] - G[0, 0] * T_true[1, 0], G[0, 0] * T_true[0, 0] + G[1, 0] * T_true[1, 0])))
        rows.append((h, v, wrong, float(np.hypot(*(G[:2, 3] - T_true[:2, 3]))), float(abs(G[2, 3] - T_true[2, 3])), float(gyaw)))
    cols = [np.array(c, np.float64) for c in zip(*rows)] if rows else [np.zeros(0)] * 6
    return (p["reason"], p["t"], *cols)


def rejection_truth(ds: DatasetStore, cfg: GtgenConfig, truths: dict[int, Any]) -> dict[str, Any]:
    """Return the confusion table, the reasons per class, and the placement errors of the
    placed samples and of the GNSS fit alone, over the drives with a truth (``truths``:
    drive index -> its Truth)."""
    rc = cfg.report
    per = [_errors(ds, cfg, truth, d) for d, truth in truths.items()]
    reason, t_placed, h, v, wrong, gh, gv, gy = (np.concatenate(c) for c in zip(*per))
    if not len(reason):
        return {}
    far = h > rc.bad_horizontal_m if rc.bad_horizontal_m is not None else np.zeros(len(h), bool)
    bad = far | (v > rc.bad_vertical_m) | (wrong > rc.bad_fill_m)
    kept = reason == codes.OK
    rdrive = ds.rejected("drive")
    unplaced = np.isin(rdrive, list(truths)) & ~np.isin(ds.rejected("t_ns"), t_placed)
    return {
        "confusion": {"kept": {"good": int((kept & ~bad).sum()), "bad": int((kept & bad).sum())},
                      "rejected": {"good": int((~kept & ~bad).sum()), "bad": int((~kept & bad).sum())}},
        "bad_rejected_pct": round(100.0 * (~kept & bad).sum() / max(bad.sum(), 1), 1) if bad.any() else None,
        "good_kept_pct": round(100.0 * (kept & ~bad).sum() / max((~bad).sum(), 1), 1) if (~bad).any() else None,
        "reasons": {cls: codes.reason_counts(reason[(~kept) & sel]) for cls, sel in (("bad", bad), ("good", ~bad))},
        "placement_error": {"horizontal_m": quantiles(h[kept]), "vertical_m": quantiles(v[kept])},
        "gnss_fit_alone_error": {"horizontal_m": quantiles(gh), "vertical_m": quantiles(gv), "yaw_deg": quantiles(gy)},
        "bad_by": {"horizontal": int(far.sum()), "vertical": int((v > rc.bad_vertical_m).sum()),
                   "fill": int((wrong > rc.bad_fill_m).sum())},
        "fill_error_m": {"kept": quantiles(wrong[kept]), "rejected": quantiles(wrong[~kept])},
        "not_placed": codes.reason_counts(ds.rejected("reason")[unplaced]),
        "bad_definition": rc.model_dump(),
    }
