"""The figures of ``scripts/gpu_check.sh``: training speed and memory from the run's
metrics.json, eval time per sample from eval.json, and the inference latency of the
checkpoint's network on the device (batch 1, the run's precision, median of GPU_CHECK_REPEATS runs, default 20).

    python scripts/gpu_check.py RUN_DIR EVAL_JSON DEVICE
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

from gtgen.train import distributed as D
from gtgen.train.checkpoint import load_checkpoint
from gtgen.train.evaluation import trained_model
from gtgen.train.onnx import example_inputs


def latency_ms(ckpt: Path, device: str, repeats: int = 20) -> tuple[float, str]:
    """Return the median inference time of one sample [ms] and the precision it ran in."""
    state, tc, data_cfg = load_checkpoint(ckpt)
    dev = D.resolve_device(device)
    precision = D.resolve_precision(tc.precision, dev)
    model = trained_model(state, tc, data_cfg).to(dev)
    images, K, T, pts, cells, raw, prior, prior_micro = example_inputs(tc, tc.short_size, n_points=20000)  # the presets' full model
    points = torch.zeros(1, len(pts), 3)
    points[0] = pts * 30
    batch = {"images": images, "K": K, "T_target_cam": T, "points": points, "n_points": torch.tensor([len(pts)]),
             "raw": raw, "prior": prior, "prior_micro": prior_micro}
    batch = {k: v.to(dev) for k, v in batch.items()}
    times = []
    with torch.no_grad(), D.autocast(dev, precision):
        for i in range(repeats + 3):
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            t = time.perf_counter()
            model(batch)
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            if i >= 3:  # after the warm-up (allocator, cuDNN's choice of kernels)
                times.append(time.perf_counter() - t)
    return 1000 * statistics.median(times), precision


def main(run: Path, eval_json: Path, device: str) -> None:
    m = json.loads((run / "metrics.json").read_text())
    ev = json.loads(eval_json.read_text())
    steps = len(m["history"])
    step_s = sum(h["step_s"] for h in m["history"][1:]) / max(steps - 1, 1)  # the first step warms up
    ms, precision = latency_ms(run / "ckpt.pt", device, int(os.environ.get("GPU_CHECK_REPEATS", "20")))
    peak = m["peak_memory_mib"]
    rows = [
        ("device", f"{m['device']}, precision {m['precision']}"),
        ("training", f"{1 / step_s:.2f} steps/s after the first step; {m['samples_per_s']:.1f} samples/s incl. data wait "
                     f"({100 * m['data_wait_share']:.0f} % of the time waiting for data), {steps} steps in {m['seconds']:.0f} s"),
        ("peak GPU memory (training)", f"{peak:.0f} MiB" if peak is not None else "n/a (CPU)"),
        ("eval", f"{1000 * ev['seconds_per_sample']:.1f} ms per sample on {ev['device']} ({ev['samples']} samples, batched)"),
        ("inference latency", f"{ms:.1f} ms per sample (batch 1, {precision})"),
    ]
    for k, v in rows:
        print(f"{k:28s} {v}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3])
