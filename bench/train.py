"""Training and inference figures of one run, on this machine's device (CPU here):
steps/s of the tiny preset (CLI, 40 steps incl. start-up) and of the paper preset (its
network at batch 6), the peak memory of a paper-preset
step at batch 6 with the lifted tensor written out (the naive pooling, the oracle) and with
the chunked BEV pooling, inference milliseconds per sample of both presets, and the prior
fill against its full-resolution oracle. The loader's samples per second: ``bench/loader.py``.

A whole paper-preset step at batch 6 does not fit in this machine's 23 GB in float32 on the
CPU (killed by the kernel at 21.5 GB RSS with the chunked pooling), so the whole step runs at
``BENCH_PAPER_BATCH`` (default 1) and the BEV pooling alone, forward and backward, at the
paper's batch-6 shapes (the naive one only when the machine has the memory free for it);
``scripts/gpu_check.sh`` measures the batch-6 step on a GPU."""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys

from _common import OUT, bench_dataset, header, run_measured

# one paper-preset training step on random inputs of the paper's sizes: seconds of the
# second step and the process's peak RSS; argv: batch, pooling (chunked | naive)
PAPER_STEP = """
import resource, sys, time, torch
from gtgen.config import load_config
from gtgen.train import model as M
from gtgen.train.bev_pool import bev_pool_naive
from gtgen.train.loss import total_loss
from gtgen.train.trainer import preset_overrides, build_model
B, pooling = int(sys.argv[1]), sys.argv[2]
if pooling == "naive":
    M.bev_pool = lambda depth, feat, cell, n, chunk_mb: bev_pool_naive(depth, feat, cell, n)
cfg = load_config(None, preset_overrides("paper"))
tc = cfg.train
m = build_model(tc, cfg).train()
opt = torch.optim.Adam(m.parameters(), lr=1e-4)
S, Mi, P = tc.short_size, tc.micro_size, cfg.shards.max_voxel_points
g = torch.Generator().manual_seed(0)
K = torch.tensor([[400., 0, 320], [0, 400, 198], [0, 0, 1]])
T = torch.eye(4).repeat(B, 4, 1, 1)
for i, yaw in enumerate((0.0, 1.5708, -1.5708, 3.1416)):  # the four cameras looking around
    c, s = torch.cos(torch.tensor(yaw)), torch.sin(torch.tensor(yaw))
    R = torch.tensor([[0., 0, 1], [-1, 0, 0], [0, -1, 0]])
    T[:, i, :3, :3] = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ R
b = {"images": torch.randint(0, 256, (B, 4, 3, tc.image_height, tc.image_width), dtype=torch.uint8, generator=g),
     "K": K.repeat(B, 4, 1, 1), "T_target_cam": T, "points": torch.randn(B, P, 3, generator=g) * 40, "n_points": torch.full((B,), P),
     "raw": torch.zeros(B, 2, S, S), "prior": torch.zeros(B, 2, S, S), "prior_micro": torch.zeros(B, 2, Mi, Mi),
     "point_rand": torch.rand(B, P, generator=g)}
for r, n in (("micro", Mi), ("short", S)):
    b[f"{r}/elevation"] = torch.randn(B, n, n, generator=g) * 0.01
    b[f"{r}/risk"] = torch.rand(B, n, n, generator=g)
    b[f"{r}/region"] = torch.randint(1, 4, (B, n, n), generator=g)
times = []
for _ in range(2):
    t = time.perf_counter()
    loss, _ = total_loss(m(b), b, tc)
    opt.zero_grad(); loss.backward(); opt.step()
    times.append(time.perf_counter() - t)
print(times[-1], resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
"""

# the BEV pooling alone, forward and backward, at the paper preset's shapes for a batch:
# seconds and the process's peak RSS; argv: batch, pooling (chunked | naive)
POOL = """
import resource, sys, time, torch
from gtgen.config import load_config
from gtgen.train.bev_pool import bev_pool, bev_pool_naive
from gtgen.train.trainer import preset_overrides
B, pooling = int(sys.argv[1]), sys.argv[2]
tc = load_config(None, preset_overrides("paper")).train
D = len(torch.arange(tc.depth_min_m, tc.depth_max_m + 1e-6, tc.depth_step_m))
N, P, C, cells = 4 * B, -(-tc.image_height // 8) * -(-tc.image_width // 8), tc.image_channels, B * tc.short_size ** 2
g = torch.Generator().manual_seed(0)
depth = torch.rand(N, D, P, generator=g).softmax(1).requires_grad_()
feat = torch.randn(N, P, C, generator=g).requires_grad_()
cell = torch.randint(0, 2 * cells, (N, D, P), generator=g)  # about half beyond the grid, as the far bins are
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
t = time.perf_counter()
out = bev_pool(depth, feat, cell, cells, tc.bev_pool_chunk_mb) if pooling == "chunked" else bev_pool_naive(depth, feat, cell, cells)
out.sum().backward()
print(time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - base)
"""

# inference of one sample (batch 1, no gradient) on the CPU, median of 5 after a warm-up;
# argv: preset
INFER = """
import statistics, sys, time, torch
from gtgen.config import load_config
from gtgen.train.trainer import preset_overrides, build_model
cfg = load_config(None, preset_overrides(sys.argv[1]))
tc = cfg.train
m = build_model(tc, cfg).eval()
S, Mi, P = tc.short_size, tc.micro_size, cfg.shards.max_voxel_points
g = torch.Generator().manual_seed(0)
b = {"images": torch.randint(0, 256, (1, 4, 3, tc.image_height, tc.image_width), dtype=torch.uint8, generator=g),
     "K": torch.tensor([[400., 0, 320], [0, 400, 198], [0, 0, 1]]).repeat(1, 4, 1, 1), "T_target_cam": torch.eye(4).repeat(1, 4, 1, 1),
     "points": torch.randn(1, P, 3, generator=g) * 40, "n_points": torch.tensor([P]), "raw": torch.zeros(1, 2, S, S),
     "prior": torch.zeros(1, 2, S, S), "prior_micro": torch.zeros(1, 2, Mi, Mi)}
b["T_target_cam"][..., :3, :3] = torch.tensor([[0., 0, 1], [-1, 0, 0], [0, -1, 0]])
with torch.no_grad():
    m(b)
    ts = []
    for _ in range(5):
        t = time.perf_counter(); m(b); ts.append(time.perf_counter() - t)
print(statistics.median(ts))
"""

FILL = """
import sys, time, numpy as np
from pathlib import Path
from gtgen.storage.dataset import DatasetStore
from gtgen.grids import filled, smoothed_min_z
info = DatasetStore(Path(sys.argv[1]))
raw = info.inputs("raw_elevation_m")  # decoded to metres (NaN: no point), as the loader reads it
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


def py(code: str, *args: str) -> list[str]:
    p = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"bench/train.py: a measurement failed:\n{p.stderr[-2000:]}")
    return p.stdout.split()


if __name__ == "__main__":
    header("bench/train.py")
    dataset = bench_dataset()
    run = OUT / "run_tiny"
    shutil.rmtree(run, ignore_errors=True)
    steps = 40
    dt, rss = run_measured(["train", str(dataset), "--preset", "tiny", "--steps", str(steps), "--run-dir", str(run)])
    print(f"tiny preset: {steps / dt:.2f} steps/s on CPU incl. start-up and 1 validation ({dt:.1f} s for {steps} steps); peak RSS {rss:.0f} MiB")
    # train.precision bf16-mixed on the CPU (autocast): worth it only where the CPU has bf16
    # matrix units (AMX, avx512_bf16); the same 40 steps in float32 and in bf16, in turn,
    # compared by the median step time the run records (start-up left out)
    import torch

    if torch.ops.mkldnn._is_mkldnn_bf16_supported():
        med = {}
        for prec in ("32", "bf16-mixed", "32", "bf16-mixed"):
            cfg = OUT / f"precision_{prec}.yaml"
            cfg.write_text(f"train:\n  precision: '{prec}'\n")
            shutil.rmtree(run, ignore_errors=True)
            run_measured(["train", str(dataset), "--preset", "tiny", "--steps", str(steps), "--run-dir", str(run), "--config", str(cfg)])
            hist = json.loads((run / "metrics.json").read_text())["history"]
            med.setdefault(prec, []).append(statistics.median(h["step_s"] for h in hist[5:]))
        a, b = (statistics.median(med[p]) for p in ("32", "bf16-mixed"))
        print(f"tiny preset step on this CPU: float32 {1000 * a:.0f} ms, bf16-mixed {1000 * b:.0f} ms ({b / a:.2f}x; median of "
              f"{len(med['32'])} runs each, in turn)")
    else:
        print("tiny preset step in bf16-mixed: not measured (this CPU has no bf16 matrix units: autocast would emulate bf16)")
    B = os.environ.get("BENCH_PAPER_BATCH", "1")
    runs = {p: py(PAPER_STEP, B, p) for p in ("chunked", "naive")}
    (tc_, mc), (tn, mn) = ((float(a), float(b)) for a, b in (runs["chunked"], runs["naive"]))
    print(f"paper preset, whole step at batch {B} on CPU: {1 / tc_:.3f} steps/s ({tc_:.1f} s per step); peak RSS {mc / 1024:.2f} GiB "
          f"with the chunked BEV pooling, {mn / 1024:.2f} GiB with the lifted tensor written out ({mc / mn:.2f}x; step time {tc_ / tn:.2f}x)")
    t6, m6 = (float(x) for x in py(POOL, "6", "chunked"))
    line = f"BEV pooling alone, forward + backward at the paper's batch-6 shapes: chunked {m6 / 1024:.2f} GiB above start-up, {t6:.1f} s"
    free = next(int(ln.split()[1]) for ln in open("/proc/meminfo") if ln.startswith("MemAvailable")) / 2**20
    if free > 16:
        n6, nm6 = (float(x) for x in py(POOL, "6", "naive"))
        line += f"; naive {nm6 / 1024:.2f} GiB, {n6:.1f} s ({m6 / nm6:.3f}x the memory)"
    else:
        line += f"; naive not run ({free:.0f} GiB free, it needs about 16)"
    print(line)
    for preset in ("tiny", "paper"):
        ms = 1000 * float(py(INFER, preset)[0])
        print(f"{preset} preset: inference {ms:.0f} ms per sample on CPU (batch 1, no gradient)" + (" (paper: 100 ms on a GPU)" if preset == "paper" else ""))
    ratio, ms, n = py(FILL, str(dataset))
    print(f"prior fill of the stored {n} x {n} min-z grids: the pyramid {float(ratio):.1f}x faster than every scale at full resolution ({float(ms):.1f} ms per grid)")
