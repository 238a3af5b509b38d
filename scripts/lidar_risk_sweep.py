"""Print the fatal-risk precision / recall of labels made from raw lidar, per seed and range,
against the synthetic world's truth (the measure of ``gtgen report``: ``LabelErrors``'s
``fatal_risk``, on every sample's observed cells).

    python scripts/lidar_risk_sweep.py --seeds 11,23,42,77 --duration 60 --workdir /tmp/lrs

Each seed's drive is made once (``WORKDIR/seed_S/drive``, reused on later runs); extract
(maps from lidar: ``configs/lidar_maps.yaml``, then ``--config`` if given), fuse and
``dem-align --no-dem`` run afresh each time, so the table is that of the gtgen on
PYTHONPATH (run it against an older checkout for a "before" row; ``--config`` with
``mapping: {cover_cell_m: null}`` gives the rule before the short cells were judged by
their cover, to the last digit). ``--clean`` removes each
seed's stores afterwards (the drives stay, for the next run).
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="11,23,42,77", help="comma-separated synth seeds")
    ap.add_argument("--duration", type=float, default=60.0, help="drive duration [s]")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/lidar_risk_sweep"))
    ap.add_argument("--config", type=Path, default=None, help="a partial YAML over configs/lidar_maps.yaml (e.g. mapping knobs)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--clean", action="store_true", help="remove the stores (not the drives) when done")
    a = ap.parse_args()

    import numpy as np

    from gtgen.config import build_config, configs_dir, load_config, read_yaml
    from gtgen.dataset.dem_align import run_dem_align
    from gtgen.extract import run_extract
    from gtgen.fuse.run import run_fuse
    from gtgen.report.labels import LabelErrors
    from gtgen.storage.dataset import DatasetStore
    from gtgen.synth import run_synth
    from gtgen.synth.truth import Truth

    layers = [read_yaml(configs_dir() / "lidar_maps.yaml")] + ([read_yaml(a.config)] if a.config else [])
    cfg = build_config(*layers, {"dem": {"enabled": False}})
    print(f"fatal risk from lidar vs truth ({a.duration:g} s drives; precision / recall on observed cells)")
    print("| seed | samples | micro P | micro R | short P | short R |")
    print("|---|---|---|---|---|---|", flush=True)
    for seed in (int(s) for s in a.seeds.split(",")):
        d = a.workdir / f"seed_{seed}"
        drive = d / "drive"
        if not (drive / "truth" / "truth.json").is_file():
            run_synth(load_config(None, {"synth": {"seed": seed, "duration_s": a.duration, "formats": "mcap"}}), drive, overwrite=True)
        ws = d / "ws"
        t0 = time.perf_counter()
        bags = sorted(drive.glob("*.mcap"))
        run_extract(bags, ws / "drive.zarr", cfg, workers=a.workers, overwrite=True)
        run_fuse(ws / "drive.zarr", ws / "fused.zarr", cfg, workers=a.workers, overwrite=True)
        run_dem_align(ws / "drive.zarr", ws / "fused.zarr", None, ws / "dataset.zarr", cfg, workers=a.workers, overwrite=True)
        ds = DatasetStore(ws / "dataset.zarr")
        truth = Truth.find([str(b) for b in bags])
        err = LabelErrors()
        err.add(ds, ds.config, truth, np.arange(ds.n_samples))
        tab = err.table()
        mi, sh = tab["micro"]["fatal_risk"], tab["short"]["fatal_risk"]
        print(f"| {seed} | {ds.n_samples} | {mi['precision']} | {mi['recall']} | {sh['precision']} | {sh['recall']} |"
              f"  ({time.perf_counter() - t0:.0f} s)", flush=True)
        if a.clean:
            shutil.rmtree(ws, ignore_errors=True)


if __name__ == "__main__":
    main()
