"""Sweep one dem-align threshold on a synthetic drive with truth and print the rejection
confusion table of each value (kept / rejected by truly good / bad, see gtgen.report).

    python scripts/adversity_sweep.py WORKSPACE --config configs/adversity.yaml \
        --key dem.max_tile_disagreement --values 0.1,0.2,0.3,0.5

WORKSPACE is a folder where ``gtgen synth drive``, ``gtgen extract`` and ``gtgen fuse`` ran
(it holds drive/ and gtgen_ws/{drive,fused}.zarr). Each value writes its own dataset under
WORKSPACE/sweep/; the drive and fused stores are read, not changed.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--config", type=Path, required=True)
    ap.add_argument("--key", required=True, help="a dotted config key, e.g. dem.max_tile_disagreement")
    ap.add_argument("--values", required=True, help="comma-separated values")
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args()

    from gtgen.config import load_config
    from gtgen.dataset.dem_align import run_dem_align
    from gtgen.report.rejections import rejection_truth
    from gtgen.storage.dataset import DatasetStore
    from gtgen.synth.truth import Truth

    ws = a.workspace / "gtgen_ws"
    section, name = a.key.split(".", 1)
    print(f"{a.key:>28} | kept good | kept bad | rejected good | rejected bad | bad rejected | good kept | reasons of rejected bad")
    for value in a.values.split(","):
        cfg = load_config(a.config, {section: {name: float(value)}})
        out = a.workspace / "sweep" / f"{a.key}={value}" / "dataset.zarr"
        run_dem_align(ws / "drive.zarr", ws / "fused.zarr", a.workspace / "drive" / "dem", out, cfg, a.workers)
        ds = DatasetStore(out)
        truths = {d: t for d, e in enumerate(ds.info.drives) if (t := Truth.find([b.path for b in e.bags])) is not None}
        r = rejection_truth(ds, cfg, truths)
        c = r["confusion"]
        print(f"{value:>28} | {c['kept']['good']:>9} | {c['kept']['bad']:>8} | {c['rejected']['good']:>13} | {c['rejected']['bad']:>12} | "
              f"{r['bad_rejected_pct']!s:>11}% | {r['good_kept_pct']!s:>8}% | {r['reasons']['bad']}")


if __name__ == "__main__":
    main()
