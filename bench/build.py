"""Speed-up of 2 workers over 1 building 4 drives, and peak memory per worker."""

from __future__ import annotations

import shutil
import subprocess
import sys

from _common import OUT, header, run_measured

if __name__ == "__main__":
    header("bench/build.py")
    src = OUT / "build_src"
    if not (src / "d3" / "truth" / "truth.json").is_file():
        shutil.rmtree(src, ignore_errors=True)
        src.mkdir(parents=True)
        for i in range(4):
            subprocess.run([sys.executable, "-m", "gtgen", "synth", str(src / f"d{i}"), "--duration", "20", "--seed", str(i),
                            "--format", "mcap"], check=True, capture_output=True)
    t = {}
    for w in (1, 2):
        out = OUT / f"build_w{w}"
        shutil.rmtree(out, ignore_errors=True)
        t[w], rss = run_measured(["build", str(src), "-o", str(out), "--workers", str(w)])
        print(f"{w} worker(s): {t[w]:.1f} s; peak RSS of the largest process {rss:.0f} MiB")
    print(f"speed-up 2 workers over 1 on 4 drives: {t[1] / t[2]:.2f}x (goal >= 1.7x)")
