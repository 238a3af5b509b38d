"""Compare candidate elevation fusion rules against a synthetic drive's truth (issue #28).

For a few samples of an extracted synth drive, gathers every map of each sample's window
at the sample's cells (naively, one map at a time), then scores candidate rules on the
observed-at-t cells (region 1) against the true ground: on vegetation cells (crown or
bush more than 0.3 m above the ground, as the truth defines what the stack sees) and on
bare ones. Correctness only, no timing:

    gtgen synth d --config configs/adversity.yaml --duration 30 && gtgen extract d/drive.mcap
    python scripts/elevation_rules.py gtgen_ws/drive.zarr --samples 8
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

from gtgen.config import RANGES
from gtgen.fuse.fusion import window_bounds
from gtgen.fuse.lattice import gather_map, target_lattice_index, top_layer
from gtgen.fuse.run import map_source, params, sample_grids
from gtgen.geometry import yaw_transform
from gtgen.grids import grid_xy
from gtgen.storage.drive import DriveStore
from gtgen.synth.truth import Truth

SPLIT_M = (0.3, 0.5, 1.0)  # top-layer heights of the split rule tried [m]
STEP = {"micro": 4, "short": 1}  # keep every n-th cell per axis (memory of the (maps, cells) stack)


def _rules(E: np.ndarray, T: dict[float, np.ndarray]) -> dict[str, np.ndarray]:
    """Return each candidate's estimate per cell from observations E (maps, cells), NaN = none,
    and the per-map top-layer flags T per top height."""
    n = np.isfinite(E).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out = {"mean": np.nanmean(E, 0), "min": np.nanmin(E, 0), "q10": np.nanquantile(E, 0.1, 0), "q25": np.nanquantile(E, 0.25, 0),
               "median": np.nanmedian(E, 0)}
        lo = out["min"]
        for band in (0.3, 0.6):
            out[f"min+{band}"] = np.nanmean(np.where(E <= lo + band, E, np.nan), 0)
        q = out["q25"]
        out["q25+0.3"] = np.nanmean(np.where(E <= q + 0.3, E, np.nan), 0)
        for h, top in T.items():
            g = np.where(top, np.nan, E)
            out[f"split{h}"] = np.where(np.isfinite(g).any(0), np.nanmean(g, 0), out["mean"])
    return {k: np.where(n > 0, v, np.nan) for k, v in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("drive", type=Path)
    ap.add_argument("--samples", type=int, default=8)
    a = ap.parse_args()
    drive = DriveStore(a.drive)
    cfg = drive.config
    p = params(cfg)
    truth = Truth.find([b["path"] for b in drive.bags])
    if truth is None:
        raise SystemExit(f"no synth truth beside the bags of {a.drive}")
    for rng in RANGES:
        gr = cfg.grids.get(rng)
        maps = map_source(drive, rng, gr.resolution_m)
        grids = sample_grids(drive, rng, gr.size, gr.resolution_m)
        ks = np.unique(np.linspace(0, len(grids) - 1, min(a.samples, len(grids))).astype(int))
        st = STEP[rng]
        err: dict[str, dict[str, list]] = {}
        for k in ks:
            s = grids[int(k)]
            I, J = target_lattice_index(s.size, s.res, s.res, s.pos, s.yaw)
            I, J = I[::st, ::st], J[::st, ::st]
            lo, hi = window_bounds(s, maps, p)
            idx = np.nonzero((maps.t_ns >= lo) & (maps.t_ns <= hi))[0]
            E = np.full((len(idx), *I.shape), np.nan, np.float32)
            T = {h: np.zeros(E.shape, bool) for h in SPLIT_M}
            for n, i in enumerate(idx):
                m = maps[int(i)]
                e, _, c = gather_map(m, I, J)
                obs = np.isfinite(e) & (c > p.min_conf)
                E[n] = np.where(obs, e, np.nan)
                for h in SPLIT_M:
                    T[h][n] = gather_map(m, I, J, layer=top_layer(m, p.min_conf, 8.0, h))[0] == 1
            e0, _, c0 = gather_map(maps[s.current_map], I, J)
            cur = np.isfinite(e0) & (c0 > p.min_conf)
            X, Y = grid_xy(s.size, s.res)
            ground, _, seen = truth.labels(yaw_transform(*s.pos, s.yaw), X[::st, ::st], Y[::st, ::st], s.t_ns)
            veg = seen - ground > 0.3
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                seen_g = np.nanmin(E, 0) - s.pos[2] - ground < 0.3  # the ground was observed at least once
            for name, v in _rules(E, T).items():
                e = err.setdefault(name, {})
                for against, tv in (("ground", ground), ("seen", seen)):
                    d = np.abs(v - s.pos[2] - tv)
                    ok = cur & np.isfinite(d)
                    for part, m in (("veg", veg), ("veg_g", veg & seen_g), ("bare", ~veg), ("all", True)):
                        e.setdefault((against, part), []).append(d[ok & m])
        for against in ("ground", "seen"):
            print(f"{rng}: obs PC MAE vs true {against} [m] over {len(ks)} samples (veg_g: vegetation cells whose ground some map saw)")
            print(f"  {'rule':10s} {'vegetation':>10s} {'veg_g':>8s} {'bare':>8s} {'all':>8s}")
            for name, e in err.items():
                v, vg, b, al = (np.concatenate(e[(against, x)]) for x in ("veg", "veg_g", "bare", "all"))
                print(f"  {name:10s} {v.mean():10.3f} {vg.mean():8.3f} {b.mean():8.3f} {al.mean():8.3f}   (cells {len(v)} / {len(vg)} / {len(b)})")


if __name__ == "__main__":
    main()
