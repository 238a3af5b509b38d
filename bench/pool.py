"""The pool's workers forked from a fork server against spawned ones (what gtgen did
before): a process that starts ``POOLS`` pools of 2 workers one after the other (a stage
of a long build, or a test worker of the suite), each running one job of fuse's module,
timed by wall clock and by the machine's busy CPU (/proc/stat: the fork server's children
are not the timed process's, so its own rusage misses them), in turn so that the ratio
holds when the machine's speed drifts; and ``gtgen fuse`` of the 120 s default drive
with either.

Expected (stated before the change): a spawned worker imports numpy, zarr and gtgen again
(about a second of CPU); a forked one starts in milliseconds, the fork server importing
them once per process. So about 2 s of CPU saved per pool after the first, and about one
import per stage.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

from _common import OUT, PY, drive, header, run_measured

POOLS = 4
SCRIPT = """
import sys
import gtgen.runtime.pool as pool
if sys.argv[1] == "spawn":
    pool._context = pool._QuietSpawnContext
from gtgen.runtime.pool import Pool
from gtgen.fuse.run import run_fuse  # noqa: F401  (the module a fuse worker runs)


def job(x):
    import gtgen.fuse.run  # noqa: F401
    return x


if __name__ == "__main__":
    for _ in range(int(sys.argv[2])):
        with Pool(2) as p:
            assert sorted(p.map(job, [(1,), (2,)])) == [1, 2]
"""

FUSE = """
import sys
import gtgen.runtime.pool as pool
if sys.argv[1] == "spawn":
    pool._context = pool._QuietSpawnContext
from gtgen.cli.app import main
if __name__ == "__main__":  # the workers import this script again as __mp_main__
    sys.argv = ["gtgen", "fuse", *sys.argv[2:]]
    main()
"""


def busy_s() -> float:
    """Return the machine's busy CPU seconds so far (user, nice, system, irq, softirq)."""
    import os

    f = Path("/proc/stat").read_text().split("\n", 1)[0].split()
    return sum(int(f[i]) for i in (1, 2, 3, 6, 7)) / os.sysconf("SC_CLK_TCK")


def measured(args: list[str]) -> tuple[float, float]:
    """Return (wall s, machine busy CPU s) of ``python ARGS``."""
    c, t = busy_s(), time.perf_counter()
    p = subprocess.run([PY, *args], capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"bench/pool.py: a measurement failed:\n{p.stderr[-2000:]}")
    return time.perf_counter() - t, busy_s() - c


if __name__ == "__main__":
    header("bench/pool.py")
    script = OUT / "pool_script.py"
    OUT.mkdir(parents=True, exist_ok=True)
    script.write_text(SCRIPT)
    for _ in range(3):
        (sw, sc), (fw, fc) = measured([str(script), "spawn", str(POOLS)]), measured([str(script), "forkserver", str(POOLS)])
        print(f"{POOLS} pools of 2 workers, spawned / forked from the fork server: wall {sw:.1f} / {fw:.1f} s ({fw / sw:.2f}x), "
              f"machine CPU {sc:.1f} / {fc:.1f} s ({fc / sc:.2f}x)")
    d = drive(120)
    ws = OUT / "ws_pool"
    if not (ws / "drive.zarr").is_dir():
        ws.mkdir(parents=True, exist_ok=True)
        run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "drive.zarr")])
    fuse = OUT / "pool_fuse.py"
    fuse.write_text(FUSE)
    for _ in range(2):
        res = []
        for how in ("spawn", "forkserver"):
            res.append(measured([str(fuse), how, str(ws / "drive.zarr"), "-o", str(ws / f"fused_{how}.zarr"), "--overwrite"]))
        (sw, sc), (fw, fc) = res
        print(f"gtgen fuse, 120 s drive, spawned / forked workers: wall {sw:.1f} / {fw:.1f} s ({fw / sw:.2f}x), "
              f"machine CPU {sc:.1f} / {fc:.1f} s ({fc / sc:.2f}x)")
