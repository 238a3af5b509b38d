"""Throughput of extract + fuse + dem-align at paper grid sizes, per stage per sample."""

from __future__ import annotations

import zarr

from _common import drive, fresh_workspace, header, run_measured

if __name__ == "__main__":
    header("bench/pipeline.py")
    d = drive(120)
    ws = fresh_workspace("ws_pipeline")
    t = {}
    t["extract"], _ = run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "drive.zarr")])
    t["fuse"], _ = run_measured(["fuse", str(ws / "drive.zarr")])
    t["dem-align"], _ = run_measured(["dem-align", str(ws / "drive.zarr"), "--dem", str(d / "dem")])
    n = zarr.open_group(str(ws / "drive.zarr"), mode="r")["samples/t_ns"].shape[0]
    total = sum(t.values())
    print(f"{n} samples from a 120 s drive; total {total:.1f} s = {n / total:.2f} samples/s (goal >= 4; 14.2k samples in {14200 / (n / total) / 3600:.2f} h)")
    for k, v in t.items():
        print(f"  {k}: {v:.1f} s = {1000 * v / n:.0f} ms/sample")
