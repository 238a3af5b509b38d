"""How long a 120 s synthetic drive takes at default sizes, and its size on disk."""

from __future__ import annotations

import shutil

from _common import OUT, dir_size_mb, header, run_measured

if __name__ == "__main__":
    header("bench/synth.py")
    out = OUT / "synth_120s"
    shutil.rmtree(out, ignore_errors=True)
    dt, rss = run_measured(["synth", str(out), "--duration", "120", "--format", "both"])
    print(f"synth 120 s drive (mcap + bag): {dt:.1f} s wall = {dt / 120:.2f} x drive duration (goal: < 120 s); peak RSS {rss:.0f} MiB")
    for p in sorted(out.iterdir()):
        print(f"  {p.name}: {dir_size_mb(p):.0f} MiB")
