"""Label error against a synthetic drive's truth: per range and region, and the DEM
alignment at the vehicle and 50 m ahead."""

from __future__ import annotations

import numpy as np

from gtgen import codes
from gtgen.config import RANGES, GtgenConfig
from gtgen.geometry import yaw_transform
from gtgen.grids import grid_xy
from gtgen.report.stats import REGIONS, quantiles
from gtgen.storage.dataset import DatasetStore


class LabelErrors:
    """Label, risk and X-Racer errors against a synthetic drive's truth, per range and
    region, and the DEM alignment at the vehicle and 50 m ahead, accumulated over samples
    (of one drive or several, each with its own truth)."""

    def __init__(self) -> None:
        self.acc = {r: {reg: {"elev_abs": 0.0, "n": 0, "risk_sq": 0.0, "nr": 0, "xr_abs": 0.0, "nx": 0} for reg in REGIONS.values()}
                    for r in RANGES}
        self.fused_vs_single = {r: {"fused_abs": 0.0, "single_abs": 0.0, "n": 0} for r in RANGES}
        self.fatal = {r: {"tp": 0, "fp": 0, "fn": 0, "n": 0} for r in RANGES}
        self.cover = {r: {part: {"ground_abs": 0.0, "seen_abs": 0.0, "n": 0} for part in ("vegetation", "bare")} for r in RANGES}
        self.h_err: list[float] = []
        self.v_err: list[float] = []
        self.h_err_far: list[float] = []
        self.samples = 0

    def add(self, ds: DatasetStore, cfg: GtgenConfig, truth, idx: np.ndarray) -> None:
        """Accumulate dataset samples ``idx`` (one drive, whose truth is ``truth``)."""
        t, pos, yaw, Tct = ds.meta("t_ns"), ds.meta("pos_odom_m"), ds.meta("yaw_odom_rad"), ds.meta("T_crs_target")
        for k in idx:
            k = int(k)
            T_odom_target = yaw_transform(*pos[k], yaw[k])
            T_true = truth.T_crs_odom(int(t[k])) @ T_odom_target
            if np.isfinite(Tct[k]).all():  # alignment error at the vehicle and 50 m ahead (none without a DEM)
                for pt, lst in ((np.array([0.0, 0, 0, 1]), self.h_err), (np.array([50.0, 0, 0, 1]), self.h_err_far)):
                    lst.append(float(np.linalg.norm((Tct[k] @ pt)[:2] - (T_true @ pt)[:2])))
                self.v_err.append(float(Tct[k][2, 3] - T_true[2, 3]))
            for r in RANGES:
                _add_sample_errors(ds, cfg, truth, k, int(t[k]), r, T_odom_target, self.acc[r], self.fused_vs_single[r], self.cover[r],
                                   self.fatal[r])
        self.samples += len(idx)

    def table(self) -> dict:
        """Return the errors as the report's JSON records them."""
        out: dict = {"samples_evaluated": int(self.samples)}
        for r in RANGES:
            out[r] = {}
            for name, a in self.acc[r].items():
                out[r][name] = {
                    "elevation_mae_m": round(a["elev_abs"] / a["n"], 4) if a["n"] else None,
                    "risk_mse": round(a["risk_sq"] / a["nr"], 5) if a["nr"] else None,
                    "xracer_elevation_mae_m": round(a["xr_abs"] / a["nx"], 4) if a["nx"] else None,
                    "cells": a["n"],
                }
            fs = self.fused_vs_single[r]
            out[r]["fused_vs_single_map"] = {
                "fused_mae_m": round(fs["fused_abs"] / fs["n"], 4) if fs["n"] else None,
                "single_map_mae_m": round(fs["single_abs"] / fs["n"], 4) if fs["n"] else None,
                "cells": fs["n"],
            }
            f = self.fatal[r]
            out[r]["fatal_risk"] = {
                "precision": round(f["tp"] / (f["tp"] + f["fp"]), 4) if f["tp"] + f["fp"] else None,
                "recall": round(f["tp"] / (f["tp"] + f["fn"]), 4) if f["tp"] + f["fn"] else None,
                "cells": f["n"],
            }
            # obs PC under vegetation (what the stack sees stands > 0.3 m above the ground) and on bare ground
            for part, c in self.cover[r].items():
                out[r][f"obs_pc_{part}"] = {
                    "vs_ground_mae_m": round(c["ground_abs"] / c["n"], 4) if c["n"] else None,
                    "vs_seen_mae_m": round(c["seen_abs"] / c["n"], 4) if c["n"] else None,
                    "cells": c["n"],
                }
        out["dem_alignment"] = {
            "horizontal_at_vehicle_m": quantiles(np.asarray(self.h_err)),
            "horizontal_50m_ahead_m": quantiles(np.asarray(self.h_err_far)),
            "vertical_m": quantiles(np.abs(np.asarray(self.v_err))),
        }
        return out


def _add_sample_errors(ds: DatasetStore, cfg: GtgenConfig, truth, k: int, t_ns: int, r: str, T_odom_target: np.ndarray, acc: dict,
                       fs: dict, cover: dict, fatal: dict) -> None:
    """Accumulate sample ``k``'s label, risk and X-Racer errors of range ``r`` per region."""
    gr = cfg.grids.get(r)
    X, Y = grid_xy(gr.size, gr.resolution_m)
    ground, trisk, seen = truth.labels(T_odom_target, X, Y, t_ns)
    el = ds.grid("labels", r, "elevation_m")[k]
    reg = ds.grid("labels", r, "region")[k]
    rk = ds.grid("labels", r, "risk")[k]
    xe = ds.grid("xracer", r, "elevation_m")[k]
    # X-Racer's confidence at t where stored (shards.qa_ranges), else the cells it saw
    # confidently at t: region 1 is those of the latest map stamped <= t, X-Racer's map at t
    xc_ok = (ds.grid("xracer", r, "confidence")[k] > cfg.fuse.min_conf) if ds.has_grid("xracer", r, "confidence") else reg == codes.OBS_PC
    for code, name in REGIONS.items():
        te = ground if code == codes.UNOBS else seen  # the DEM's truth is the ground; the stack's, what it sees
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
    # fatal risk (label >= train.fatal_risk) on observed cells against the truth's obstacles: fatal
    # true risk (rocks, trees, steep slopes) or anything standing taller than the ground clearance
    # (bushes too, which the truth's risk calls passable) of mapping.clearance_m
    lab = codes.observed(reg) & np.isfinite(rk)
    obstacle = (trisk >= cfg.train.fatal_risk) | (truth.standing(T_odom_target, X, Y, t_ns) >= cfg.mapping.clearance_m)
    p, q = rk[lab] >= cfg.train.fatal_risk, obstacle[lab]
    fatal["tp"] += int((p & q).sum())
    fatal["fp"] += int((p & ~q).sum())
    fatal["fn"] += int((~p & q).sum())
    fatal["n"] += int(lab.sum())
    # averaging works: fused vs the single X-Racer map at t on cells both call confident
    both = codes.observed(reg) & np.isfinite(el) & np.isfinite(xe) & xc_ok
    fs["fused_abs"] += float(np.abs(el[both] - seen[both]).sum())
    fs["single_abs"] += float(np.abs(xe[both] - seen[both]).sum())
    fs["n"] += int(both.sum())
    pc = (reg == codes.OBS_PC) & np.isfinite(el)
    veg = seen - ground > 0.3
    for part, m in (("vegetation", pc & veg), ("bare", pc & ~veg)):
        cover[part]["ground_abs"] += float(np.abs(el[m] - ground[m]).sum())
        cover[part]["seen_abs"] += float(np.abs(el[m] - seen[m]).sum())
        cover[part]["n"] += int(m.sum())
