"""Shared helpers of the benchmarks: cached synthetic drives, timing and peak RSS.

Every measured step runs in a fresh subprocess so its peak RSS is its own. Benchmarks
print ratios measured in one run; nothing here asserts on time.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

OUT = Path(__file__).resolve().parent / "out"
PY = sys.executable


def run_measured(args: list[str], cwd: Path | None = None) -> tuple[float, float]:
    """Run ``python -m gtgen ARGS`` (or a '-c' snippet); return (seconds, peak RSS in MiB)."""
    cmd = [PY, *args] if args and args[0] == "-c" else [PY, "-m", "gtgen", *args]
    code = (
        "import resource, subprocess, sys, time, json; t=time.perf_counter(); "
        f"r=subprocess.run({cmd!r}, cwd={str(cwd) if cwd else None!r}, capture_output=True, text=True); "
        "dt=time.perf_counter()-t; ru=resource.getrusage(resource.RUSAGE_CHILDREN); "
        "print(json.dumps({'rc': r.returncode, 'dt': dt, 'rss': ru.ru_maxrss/1024, 'err': r.stderr[-2000:]}))"
    )
    p = subprocess.run([PY, "-c", code], capture_output=True, text=True)
    res = json.loads(p.stdout.strip().splitlines()[-1])
    if res["rc"] != 0:
        raise SystemExit(f"bench step failed: {' '.join(args)}\n{res['err']}")
    return res["dt"], res["rss"]


def drive(duration_s: float, seed: int = 0, fmt: str = "mcap") -> Path:
    """Return a cached synthetic drive folder of ``duration_s`` seconds (default sizes)."""
    out = OUT / f"drive_{int(duration_s)}s_seed{seed}_{fmt}"
    if not (out / "truth" / "truth.json").is_file():
        OUT.mkdir(parents=True, exist_ok=True)
        subprocess.run([PY, "-m", "gtgen", "synth", str(out), "--duration", str(duration_s), "--seed", str(seed),
                        "--format", fmt, "--overwrite"], check=True, capture_output=True)
    return out


def bench_dataset() -> Path:
    """Return the dataset ``BENCH_DATASET`` names, else that of the 120 s default drive
    (built once into ``bench/out/ws_pipeline``)."""
    if "BENCH_DATASET" in os.environ:
        return Path(os.environ["BENCH_DATASET"])
    d = drive(120)
    ws = OUT / "ws_pipeline"
    dataset = ws / "dataset.zarr"
    if not dataset.is_dir():
        ws.mkdir(parents=True, exist_ok=True)
        run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "drive.zarr")])
        run_measured(["fuse", str(ws / "drive.zarr")])
        run_measured(["dem-align", str(ws / "drive.zarr"), "--dem", str(d / "dem")])
    return dataset


def fresh_workspace(name: str) -> Path:
    """Return an empty folder ``bench/out/<name>`` (removed and made anew), removed again
    when the bench exits (stores of a long drive take GBs), unless GTGEN_BENCH_KEEP=1."""
    import atexit
    import shutil

    ws = OUT / name
    shutil.rmtree(ws, ignore_errors=True)
    ws.mkdir(parents=True)
    if os.environ.get("GTGEN_BENCH_KEEP") != "1":
        atexit.register(shutil.rmtree, ws, True)
    return ws


def dir_size_mb(p: Path) -> float:
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) / 2**20 if p.is_dir() else p.stat().st_size / 2**20


def header(title: str) -> None:
    print(f"== {title} ({os.cpu_count()} cores) ==")


__all__ = ["OUT", "PY", "run_measured", "drive", "fresh_workspace", "dir_size_mb", "header", "time", "resource"]
