"""Throughput of extract + fuse + dem-align at paper grid sizes, per stage per sample, and
the share of dem-align that judging the DEM tiles by their borders takes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import zarr

from _common import OUT, drive, fresh_workspace, header, run_measured

# the DEM tiles of a drive judged by their borders (every tile of its folder): seconds, tiles
JUDGE = """
import sys, time
from pathlib import Path
from gtgen.config import load_config
from gtgen.dem.judge import judge_borders
from gtgen.dem.index import TileIndex
from gtgen.dem.tiles import DemMosaic
index = TileIndex.build(Path(sys.argv[1]))
mosaic = DemMosaic(index, sys.argv[2])
t = time.perf_counter()
judge_borders(mosaic, list(range(len(index.tiles))), load_config().dem)
print(time.perf_counter() - t, len(index.tiles))
"""

# dem-align with the kept samples built while the ICP chain runs (stream) or after it (the oracle)
ALIGN = """
import sys
from pathlib import Path
from gtgen.config import load_config
from gtgen.dataset.dem_align import run_dem_align
ws, dem, stream = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3] == "1"
run_dem_align(ws / "drive.zarr", ws / "fused.zarr", dem, ws / "again.zarr", load_config(), workers=2, overwrite=True, stream=stream)
"""


def stages(seconds: int) -> tuple[int, dict[str, float], dict[str, float], Path]:
    """Run extract, fuse and dem-align on the default drive of ``seconds``; return the
    samples, each stage's seconds and peak RSS [MiB], and the drive folder."""
    d = drive(seconds)
    ws = fresh_workspace(f"ws_pipeline_{seconds}s")
    t, rss = {}, {}
    t["extract"], rss["extract"] = run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "drive.zarr")])
    t["fuse"], rss["fuse"] = run_measured(["fuse", str(ws / "drive.zarr")])
    t["dem-align"], rss["dem-align"] = run_measured(["dem-align", str(ws / "drive.zarr"), "--dem", str(d / "dem")])
    n = zarr.open_group(str(ws / "drive.zarr"), mode="r")["samples/t_ns"].shape[0]
    return n, t, rss, d


if __name__ == "__main__":
    header("bench/pipeline.py")
    n, t, rss, d = stages(120)
    total = sum(t.values())
    print(f"{n} samples from a 120 s drive; total {total:.1f} s = {n / total:.2f} samples/s (goal >= 12; 14.2k samples in {14200 / (n / total) / 3600:.2f} h)")
    for k, v in t.items():
        print(f"  {k}: {v:.1f} s = {1000 * v / n:.0f} ms/sample, peak RSS {rss[k]:.0f} MiB")
    out = subprocess.run([sys.executable, "-c", JUDGE, str(d / "dem"), "EPSG:26910"], capture_output=True, text=True, check=True).stdout.split()
    dt, tiles = float(out[0]), int(out[1])
    print(f"  of dem-align: the DEM tiles judged by their borders, {tiles} tiles in {dt:.1f} s ({1000 * dt / tiles:.0f} ms a tile) = "
          f"{100 * dt / t['dem-align']:.1f} % of dem-align")
    ws = OUT / "ws_pipeline_120s"
    pairs = [(run_measured(["-c", ALIGN, str(ws), str(d / "dem"), "1"])[0], run_measured(["-c", ALIGN, str(ws), str(d / "dem"), "0"])[0])
             for _ in range(2)]
    print("  dem-align, kept samples built while the ICP chain runs / after it, in turn: "
          + ", ".join(f"{a:.1f} / {b:.1f} s ({a / b:.2f}x)" for a, b in pairs))
    # memory must not grow with the drive's length: the same stages on a quarter of it
    n30, _, rss30, _ = stages(30)
    print("peak RSS [MiB], 30 s drive -> 120 s drive: " + ", ".join(f"{k} {rss30[k]:.0f} -> {rss[k]:.0f}" for k in rss))
