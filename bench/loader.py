"""How fast ``ShardDataset`` feeds a model through a DataLoader (it must keep a GPU fed:
>= 50 samples/s for the paper preset with 2 workers), for both presets with 0 and 2
workers, and per read: the training read (``baselines=False``: what the trainer's loss and
model take) against the evaluation read (with the X-Racer and raw-grid baselines, which
the trainer read too before it left them out), taken in turn so their ratio holds when the
machine's speed drifts.

Expected (stated before the change): the baselines are 3 of a range's 6 grids a sample
(X-Racer elevation and risk, the raw min-z view) and the region codes went from int64 to
uint8, so the training read decodes 4 fewer stored grids and ships about half the bytes
(paper preset: about 13 -> 7 MB a sample); the prior fill, about half of a sample's time,
is the same in both, so about 1.1x on the paper preset.

The 120 s default drive's dataset (cached in ``bench/out``), or ``BENCH_DATASET``.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from _common import bench_dataset, header

LOADER = """
import sys, time, torch
from pathlib import Path
from torch.utils.data import DataLoader
from gtgen.config import load_config
from gtgen.train.trainer import preset_overrides, _collate
from gtgen.train.data import ShardDataset
cfg = load_config(None, preset_overrides(sys.argv[3]))
ds = ShardDataset(Path(sys.argv[1]), cfg.train, split="train", baselines=sys.argv[4] == "eval")
workers = int(sys.argv[2])
dl = DataLoader(ds, batch_size=cfg.train.batch_size, shuffle=True, num_workers=workers, collate_fn=_collate,
                generator=torch.Generator().manual_seed(0), persistent_workers=workers > 0)
it = iter(dl); next(it)  # workers started, first batch out
n, t = 0, time.perf_counter()
while n < 240:
    try:
        b = next(it)
    except StopIteration:
        it = iter(dl); continue
    n += len(b["index"])
print(n / (time.perf_counter() - t))
"""


def rate(dataset: Path, workers: int, preset: str, read: str) -> float:
    """Return the samples per second of one DataLoader run (in a fresh process)."""
    p = subprocess.run([sys.executable, "-c", LOADER, str(dataset), str(workers), preset, read], capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"bench/loader.py: a measurement failed:\n{p.stderr[-2000:]}")
    return float(p.stdout.split()[-1])


if __name__ == "__main__":
    header("bench/loader.py")
    dataset = bench_dataset()
    for preset in ("tiny", "paper"):
        for workers in (0, 2):
            ev, tr = rate(dataset, workers, preset, "eval"), rate(dataset, workers, preset, "train")
            goal = "; goal >= 50" if workers == 2 else ""
            print(f"ShardDataset ({preset} preset, {workers} workers): training read {tr:.1f} samples/s, evaluation read {ev:.1f} "
                  f"({tr / ev:.2f}x{goal})")
