"""Speed-up of 2 workers over 1 building 4 drives, and peak memory per worker."""

from __future__ import annotations

import shutil
import subprocess
import sys

from _common import OUT, drive, header, run_measured

if __name__ == "__main__":
    header("bench/build.py")
    src = OUT / "build_src"
    if not (src / "d3" / "truth" / "truth.json").is_file():
        shutil.rmtree(src, ignore_errors=True)
        src.mkdir(parents=True)
        for i in range(4):
            subprocess.run([sys.executable, "-m", "gtgen", "synth", str(src / f"d{i}"), "--duration", "20", "--seed", str(i),
                            "--format", "mcap"], check=True, capture_output=True)
    # this machine's speed drifts by +-20 % over minutes: alternate the two settings twice
    # and compare the best run of each, as timing tools do
    t: dict[int, list[float]] = {1: [], 2: []}
    for rep in range(2):
        for w in (1, 2):
            out = OUT / f"build_w{w}"
            shutil.rmtree(out, ignore_errors=True)
            dt, rss = run_measured(["build", str(src), "-o", str(out), "--workers", str(w)])
            shutil.rmtree(out)  # about 5 GB each
            t[w].append(dt)
            print(f"run {rep + 1}, {w} worker(s): {dt:.1f} s; peak RSS of the largest process {rss:.0f} MiB")
    print(f"speed-up 2 workers over 1 on 4 drives (best of 2 each): {min(t[1]) / min(t[2]):.2f}x (goal >= 1.7x); "
          f"per alternation: {', '.join(f'{a / b:.2f}x' for a, b in zip(t[1], t[2]))}")
    # one long drive: the build gives both workers to its stages
    one = drive(60)
    t1 = {}
    for w in (1, 2):
        out = OUT / f"build_one_w{w}"
        shutil.rmtree(out, ignore_errors=True)
        t1[w], rss = run_measured(["build", str(one), "-o", str(out), "--workers", str(w)])
        shutil.rmtree(out)
        print(f"one 60 s drive, {w} worker(s): {t1[w]:.1f} s; peak RSS of the largest process {rss:.0f} MiB")
    print(f"speed-up 2 workers over 1 on one 60 s drive: {t1[1] / t1[2]:.2f}x")
