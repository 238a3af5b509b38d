"""Maps from raw lidar inside extract (topics.*: null): the mapping's time against the
drive's duration (goal: at least real time on 2 cores for three 32-beam lidars at 10 Hz)
and its peak memory on a 30 s and a 120 s drive (goal: flat, ratio about 1). The mapping's
own time is extract with lidar maps minus extract of the same drive with the stack's maps.
"""

from __future__ import annotations

import sys

from _common import drive, fresh_workspace, header, run_measured
from gtgen.config import configs_dir

if __name__ == "__main__":
    header("bench/mapping.py")
    lidar_cfg = str(configs_dir() / "lidar_maps.yaml")
    durations = [int(a) for a in sys.argv[1:]] or [30, 120]  # e.g. `python bench/mapping.py 15 30` for a quicker look
    rss = {}
    for dur in durations:
        d = drive(dur)
        ws = fresh_workspace(f"ws_mapping_{dur}")
        stack_s, _ = run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "stack.zarr")])
        lidar_s, rss[dur] = run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "lidar.zarr"), "--config", lidar_cfg])
        mapping_s = max(lidar_s - stack_s, 1e-9)
        print(f"{dur} s drive: extract with the stack's maps {stack_s:.1f} s, with maps from lidar {lidar_s:.1f} s: "
              f"mapping {mapping_s:.1f} s = {dur / mapping_s:.2f}x real time (goal >= 1); peak RSS {rss[dur]:.0f} MiB")
    a, b = durations[0], durations[-1]
    print(f"peak RSS {b} s / {a} s drive: {rss[b] / rss[a]:.2f} (goal about 1: memory flat in drive length)")
