"""Training speed and memory of the tiny preset on CPU, the samples per second ShardDataset
delivers through a DataLoader with 0 and 2 workers (it must keep a GPU fed: >= 50/s on 2
cores), the prior fill against its full-resolution oracle, and the paper preset's forward
time."""

from __future__ import annotations

import shutil

from _common import OUT, drive, header, run_measured

FORWARD = """
import time, torch
from gtgen.config import load_config
from gtgen.train.trainer import preset_overrides, build_model
cfg = load_config(None, preset_overrides("paper"))
tc = cfg.train
m = build_model(tc, cfg).eval()
S = 60000
b = {"images": torch.randint(0, 256, (1, 4, 3, tc.image_height, tc.image_width), dtype=torch.uint8), "K": torch.tensor([[[400., 0, 320], [0, 400, 198], [0, 0, 1]]]).repeat(1, 4, 1, 1),
     "T_target_cam": torch.eye(4).repeat(1, 4, 1, 1), "points": torch.randn(1, S, 3) * 40, "n_points": torch.tensor([S]),
     "raw": torch.zeros(1, 2, tc.short_size, tc.short_size), "prior": torch.zeros(1, 2, tc.short_size, tc.short_size),
     "prior_micro": torch.zeros(1, 2, tc.micro_size, tc.micro_size)}
b["T_target_cam"][..., :3, :3] = torch.tensor([[0., 0, 1], [-1, 0, 0], [0, -1, 0]])
with torch.no_grad():
    m(b); t = time.perf_counter(); m(b); dt = time.perf_counter() - t
print(dt, sum(p.numel() for p in m.parameters()))
"""

LOADER = """
import sys, time, torch
from pathlib import Path
from torch.utils.data import DataLoader
from gtgen.config import load_config
from gtgen.train.trainer import preset_overrides, _collate
from gtgen.train.data import ShardDataset
cfg = load_config(None, preset_overrides(sys.argv[3]))
ds = ShardDataset(Path(sys.argv[1]), cfg.train, split="train")
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

FILL = """
import sys, time, numpy as np
from pathlib import Path
from gtgen.storage.dataset import DatasetStore
from gtgen.train.data import filled, smoothed_min_z
info = DatasetStore(Path(sys.argv[1]))
g = info.group
raw = g["inputs/raw_elevation_m"]
grids = [smoothed_min_z(raw[k], 5) for k in range(0, info.n_samples, max(1, info.n_samples // 12))]
t = [0.0, 0.0]
for rep in range(3):
    for i, kw in enumerate(({}, {"max_sigma_cells": np.inf})):
        t0 = time.perf_counter()
        for x in grids:
            filled(x, **kw)
        t[i] += time.perf_counter() - t0
print(t[1] / t[0], 1000 * t[0] / (3 * len(grids)), grids[0].shape[0])
"""

if __name__ == "__main__":
    header("bench/train.py")
    d = drive(120)
    ws = OUT / "ws_pipeline"
    if not (ws / "dataset.zarr").is_dir():
        ws.mkdir(parents=True, exist_ok=True)
        run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "drive.zarr")])
        run_measured(["fuse", str(ws / "drive.zarr")])
        run_measured(["dem-align", str(ws / "drive.zarr"), "--dem", str(d / "dem")])
    run = OUT / "run_tiny"
    shutil.rmtree(run, ignore_errors=True)
    steps = 40
    dt, rss = run_measured(["train", str(ws / "dataset.zarr"), "--preset", "tiny", "--steps", str(steps), "--run", str(run)])
    print(f"tiny preset: {steps / dt:.2f} steps/s on CPU incl. start-up ({dt:.1f} s for {steps} steps); peak RSS {rss:.0f} MiB")
    import subprocess
    import sys

    for preset in ("tiny", "paper"):
        for workers in (0, 2):
            p = subprocess.run([sys.executable, "-c", LOADER, str(ws / "dataset.zarr"), str(workers), preset], capture_output=True, text=True, check=True)
            print(f"ShardDataset ({preset} preset) through a DataLoader with {workers} workers: {float(p.stdout.split()[-1]):.1f} samples/s (goal >= 50)")
    p = subprocess.run([sys.executable, "-c", FILL, str(ws / "dataset.zarr")], capture_output=True, text=True, check=True)
    ratio, ms, n = p.stdout.split()
    print(f"prior fill of the stored {n} x {n} min-z grids: the pyramid {float(ratio):.1f}x faster than every scale at full resolution ({float(ms):.1f} ms per grid)")
    p = subprocess.run([sys.executable, "-c", FORWARD], capture_output=True, text=True, check=True)
    fw, n = p.stdout.split()
    print(f"paper preset: {int(n) / 1e6:.1f} M parameters; forward pass of one sample on CPU {float(fw) * 1000:.0f} ms (paper: 100 ms on a GPU)")
