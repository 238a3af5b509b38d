"""Fusion at paper grid sizes: fast vs naive oracle, window 120 s vs 15 s, RSS 1x vs 4x."""

from __future__ import annotations

from _common import drive, fresh_workspace, header, run_measured

NAIVE = """
import time, itertools, sys
from pathlib import Path
from gtgen.storage.drive import DriveStore
from gtgen.config import load_config
from gtgen.fuse.fusion import naive_fuse_range, fuse_range
from gtgen.fuse.run import map_source, sample_grids, params
cfg = load_config()
d = DriveStore(Path(sys.argv[1]))
g = cfg.grids.micro
maps = map_source(d, "micro", g.resolution_m)
samples = sample_grids(d, "micro", g.size, g.resolution_m)
n = int(sys.argv[2])
sel = samples[len(samples) // 3 : len(samples) // 3 + n]
t = time.perf_counter(); list(naive_fuse_range(maps, sel, params(cfg))); tn = time.perf_counter() - t
t = time.perf_counter(); list(fuse_range(maps, samples, params(cfg))); tf = time.perf_counter() - t
print(tn / n, tf / len(samples))
"""

if __name__ == "__main__":
    header("bench/fuse.py")
    d = drive(120)
    ws = fresh_workspace("ws_fuse")
    run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "drive.zarr")])
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-c", NAIVE, str(ws / "drive.zarr"), "6"], capture_output=True, text=True, check=True)
    naive_s, fast_s = map(float, p.stdout.split())
    print(f"micro range, window 60 s: naive oracle {naive_s:.2f} s/sample, fast {fast_s:.3f} s/sample: speed-up {naive_s / fast_s:.1f}x (goal >= 10x)")
    times = {}
    for w in (15, 120):
        times[w], _ = run_measured(["fuse", str(ws / "drive.zarr"), "--window", str(w), "-o", str(ws / f"f{w}.zarr")])
    print(f"fuse both ranges: window 15 s {times[15]:.1f} s, window 120 s {times[120]:.1f} s: ratio {times[120] / times[15]:.2f} (goal <= 1.3)")
    # memory is bounded by the window (60 s), not the drive: compare 1x and 4x of 60 s
    rss = {}
    for dur in (60, 240):
        dd = drive(dur)
        w2 = fresh_workspace(f"ws_fuse_{dur}")
        run_measured(["extract", str(dd / "drive.mcap"), "-o", str(w2 / "drive.zarr")])
        _, rss[dur] = run_measured(["fuse", str(w2 / "drive.zarr"), "--workers", "1", "-o", str(w2 / "fused.zarr")])
    print(f"fuse peak RSS: 60 s drive {rss[60]:.0f} MiB, 240 s drive {rss[240]:.0f} MiB: ratio {rss[240] / rss[60]:.2f} (goal: <= 2 GiB, flat)")
