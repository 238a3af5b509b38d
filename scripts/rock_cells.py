"""Draw a rock's cells as labels made from lidar flag them, beside the truth: one PNG to look at
by hand (issue 38: an obstacle's cells fatal, its neighbours not).

    python scripts/rock_cells.py DRIVE "after=WS1/dataset.zarr" "before=WS2/dataset.zarr" -o rock.png

DRIVE is a synthetic drive folder (its truth beside the bag); each NAME=DATASET is a
dataset of that drive (for example ``scripts/lidar_risk_sweep.py``'s, made with two
configs). The rock drawn is the tallest one lying 10-40 m from the vehicle in a sample
where every dataset observes it; the window is 12 m around it. Per dataset and range:
fatal label cells (risk >= train.fatal_risk) red, observed cells below it grey, the rest
white; the truth's obstacle outline (rocks, trunks, crowns and bushes taller than the
clearance, at 5 cm) in blue; the truth's obstacle cells (at their centres, the report's
reference) in the first row.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("drive", type=Path)
    ap.add_argument("datasets", nargs="+", help="NAME=PATH of a dataset.zarr of that drive")
    ap.add_argument("-o", "--out", type=Path, default=Path("rock_cells.png"))
    ap.add_argument("--half", type=float, default=6.0, help="half the window's edge [m]")
    a = ap.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gtgen import codes
    from gtgen.config import RANGES
    from gtgen.geometry import yaw_transform
    from gtgen.grids import cell_centers
    from gtgen.storage.dataset import DatasetStore
    from gtgen.synth.truth import Truth

    named = [(n, DatasetStore(Path(p))) for n, p in (d.split("=", 1) for d in a.datasets)]
    ds0 = named[0][1]
    cfg = ds0.config
    truth = Truth.find([str(b) for b in sorted(a.drive.glob("*.mcap")) + sorted(a.drive.glob("*.bag"))])
    if truth is None:
        raise SystemExit(f"no truth beside the bags of {a.drive}")
    ob = truth.world.terrain.obstacles
    t, pos, yaw = ds0.meta("t_ns"), ds0.meta("pos_odom_m"), ds0.meta("yaw_odom_rad")
    fr = cfg.train.fatal_risk

    def rock_in_target(k: int) -> np.ndarray:  # rocks (n, 2) in sample k's target frame
        T = truth.T_crs_odom(int(t[k])) @ yaw_transform(*pos[k], yaw[k])
        E, N = ob.rock_uv[:, 0] + truth.origin[0] - T[0, 3], ob.rock_uv[:, 1] + truth.origin[1] - T[1, 3]
        return np.column_stack([T[0, 0] * E + T[1, 0] * N, T[0, 1] * E + T[1, 1] * N])

    best = None
    for k in range(ds0.n_samples):
        xy = rock_in_target(k)
        d = np.hypot(*xy.T)
        near = np.flatnonzero((d > 10) & (d < 40))
        if not len(near):
            continue
        judged = [_judged(ds, k, r) for _, ds in named for r in RANGES]  # each sample's grids read once
        for i in near:
            seen = all(j[_cell(xy[i], cfg.grids.get(r))] for j, r in zip(judged, RANGES * len(named)))
            if seen and (best is None or ob.rock_height[i] > best[2]):
                best = (k, i, float(ob.rock_height[i]))
    if best is None:
        raise SystemExit("no rock 10-40 m from the vehicle observed by every dataset")
    k, i, _ = best
    c = rock_in_target(k)[i]
    T = yaw_transform(*pos[k], yaw[k])
    fig, axes = plt.subplots(len(named) + 1, len(RANGES), figsize=(4.2 * len(RANGES), 4.2 * (len(named) + 1)), squeeze=False)
    fine = np.arange(-a.half, a.half, 0.05) + 0.025
    FX, FY = np.meshgrid(c[0] + fine, c[1] + fine, indexing="ij")
    _, frisk, _ = truth.labels(T, FX, FY, int(t[k]))
    fob = (frisk >= fr) | (truth.standing(T, FX, FY, int(t[k])) >= cfg.mapping.clearance_m)
    for col, r in enumerate(RANGES):
        g = cfg.grids.get(r)
        cc = cell_centers(g.size, g.resolution_m)
        ii = np.flatnonzero(np.abs(cc - c[0]) < a.half)
        jj = np.flatnonzero(np.abs(cc - c[1]) < a.half)
        X, Y = np.meshgrid(cc[ii], cc[jj], indexing="ij")
        _, trisk, _ = truth.labels(T, X, Y, int(t[k]))
        tob = (trisk >= fr) | (truth.standing(T, X, Y, int(t[k])) >= cfg.mapping.clearance_m)
        ext = (cc[jj[0]] - g.resolution_m / 2, cc[jj[-1]] + g.resolution_m / 2, cc[ii[0]] - g.resolution_m / 2, cc[ii[-1]] + g.resolution_m / 2)
        rows = [("truth at cell centres", tob.astype(float))]
        for name, ds in named:
            rk = ds.grid("labels", r, "risk")[k][np.ix_(ii, jj)]
            obs = codes.observed(ds.grid("labels", r, "region")[k][np.ix_(ii, jj)]) & np.isfinite(rk)
            fatal = obs & (rk >= fr)
            q = tob[obs]
            p = fatal[obs]
            rows.append((f"{name}: {int((p & q).sum())} right, {int((p & ~q).sum())} false, {int((~p & q).sum())} missed",
                         np.where(fatal, 1.0, np.where(obs, 0.35, 0.0))))
        for row, (title, img) in enumerate(rows):
            ax = axes[row, col]
            ax.imshow(img, origin="lower", extent=ext, cmap="Reds" if row else "Greys", vmin=0, vmax=1, interpolation="nearest")
            ax.contour(FY, FX, fob.astype(float), levels=[0.5], colors="tab:blue", linewidths=1.0)
            ax.set_title(f"{r} ({g.resolution_m} m): {title}", fontsize=8)
            ax.set_xlabel("y [m], target frame")
            ax.set_ylabel("x [m]")
    fig.suptitle(f"sample {k}: a rock of {ob.rock_height[i]:.2f} m, radius {ob.rock_radius[i]:.2f} m, at ({c[0]:.1f}, {c[1]:.1f}) m", fontsize=10)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"{a.out}: sample {k}, rock at ({c[0]:.1f}, {c[1]:.1f}) m")


def _judged(ds, k: int, r: str) -> np.ndarray:
    """Return the cells of range ``r`` of sample ``k`` of ``ds`` observed and with a risk."""
    from gtgen import codes

    return codes.observed(ds.grid("labels", r, "region")[k]) & np.isfinite(ds.grid("labels", r, "risk")[k])


def _cell(xy: np.ndarray, g) -> tuple[int, int]:
    """Return the grid cell (i, j) of target point ``xy`` on grid spec ``g``."""
    half = g.size * g.resolution_m / 2
    return int((xy[0] + half) // g.resolution_m), int((xy[1] + half) // g.resolution_m)


if __name__ == "__main__":
    main()
