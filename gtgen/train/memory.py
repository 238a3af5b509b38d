"""Whether a training run fits the device's memory, checked before its first step.

A run that does not fit is killed by the kernel mid-step (on the CPU: "Killed", no
message) or stops with CUDA's out-of-memory error after minutes of start-up. Before any
work, ``check_memory`` compares the preset's estimated need at the configured batch with
what the device has free (``/proc/meminfo`` MemAvailable on the CPU,
``torch.cuda.mem_get_info`` on CUDA) and stops with one line saying which batch fits.

The estimate is linear in the samples a process steps on: ``Preset.memory_gib`` = (a
constant, a per-sample coefficient), the peak RSS of one float32 training step on the CPU
at the preset's sizes (``bench/train.py``'s whole-step script at two batches; the
numbers and the command are in ``gtgen/train/presets.py``). In mixed precision the
per-sample activations are taken at half (16-bit), an assumption, not a measurement; a
user who knows better sets ``train.check_memory: false``.
"""

from __future__ import annotations

import math
import os

import torch

from gtgen.config import TrainConfig
from gtgen.errors import TrainError

GIB = 2**30


def need_gib(tc: TrainConfig, batch: int, mixed: bool = False) -> float | None:
    """Return the estimated memory of one training process stepping on ``batch`` samples
    at ``tc``'s preset [GiB], or None when the preset has no estimate."""
    from gtgen.train.presets import PRESETS

    preset = PRESETS.get(tc.preset)
    if preset is None or preset.memory_gib is None:
        return None
    constant, per_sample = preset.memory_gib
    return constant + per_sample * batch * (0.5 if mixed else 1.0)


def available_bytes(device: torch.device) -> int | None:
    """Return the memory free for a new allocation on ``device`` [bytes] (None: unknown)."""
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    if device.type != "cpu":
        return None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def check_memory(tc: TrainConfig, device: torch.device, precision: str, world: int = 1) -> None:
    """Raise TrainError when a process's estimated need at ``tc.batch_size`` (its share over
    ``world`` processes; on the CPU, the processes of this machine together) exceeds what
    ``device`` has free, saying which batch fits."""
    if not tc.check_memory:
        return
    free = available_bytes(device)
    mixed = precision != "32"
    local = 1 if device.type == "cuda" else int(os.environ.get("LOCAL_WORLD_SIZE", world))  # processes sharing this memory

    def need(batch: int) -> float | None:
        one = need_gib(tc, math.ceil(batch / world), mixed)
        return None if one is None else one * local

    want = need(tc.batch_size)
    if free is None or want is None or want * GIB <= free:
        return
    where = f"{device.type}{f':{device.index}' if device.index is not None else ''}"
    head = (f"the {tc.preset} preset at train.batch_size {tc.batch_size} needs about {want:.1f} GiB of memory on {where}"
            f"{f' ({local} processes)' if local > 1 else ''}, and {free / GIB:.1f} GiB is free")
    fits = [b for b in range(world, tc.batch_size, world) if need(b) * GIB <= free]
    if fits:
        hint = f"train.batch_size: {fits[-1]} needs about {need(fits[-1]):.1f} GiB here"
    else:
        hint = f"even train.batch_size: {world} needs about {need(world):.1f} GiB: free memory, or use a device with more"
    raise TrainError(f"{head}: {hint} (train.check_memory: false skips this estimate)")
