"""Where training runs: the device, the float precision, and torchrun's processes.

Under ``torchrun`` (the environment has ``WORLD_SIZE`` > 1) every process joins one
process group (NCCL on CUDA, gloo on CPU) and trains on ``cuda:LOCAL_RANK`` (or the CPU)
with DDP; rank 0 alone takes the run folder's lock and writes checkpoints, logs and
curves. Every rank reads the same config and, on ``--resume``, the same checkpoint, so
seed, step and schedule agree; a setup error of rank 0 (a busy run folder, say) is sent to
the others, which stop without repeating it (rank 0 prints the one line; then torchrun
reports the failed processes in its own words).
"""

from __future__ import annotations

import contextlib
import datetime
import os
from collections.abc import Iterator
from dataclasses import dataclass

import torch

from gtgen.errors import ConfigError, RankError, TrainError

AMP_DTYPES = {"bf16-mixed": torch.bfloat16, "16-mixed": torch.float16}


@dataclass(frozen=True)
class Processes:
    """This process's place among torchrun's (rank 0 of 1 without torchrun)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0


def torchrun_env() -> Processes:
    """Return the process's rank, world size and local rank from torchrun's environment."""
    try:
        return Processes(int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1)), int(os.environ.get("LOCAL_RANK", 0)))
    except ValueError as err:
        raise ConfigError(f"torchrun's RANK / WORLD_SIZE / LOCAL_RANK are not integers: {err}") from err


def resolve_device(name: str, procs: Processes = Processes()) -> torch.device:
    """Return the torch device of ``train.device`` / ``--device``: ``auto`` is CUDA when
    torch sees a GPU, else the CPU; under torchrun a CUDA device is ``cuda:LOCAL_RANK``."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(name)
    except RuntimeError as err:
        raise ConfigError(f"device {name!r} is not a torch device; expected auto, cpu, cuda or cuda:N") from err
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise TrainError(f"device {name!r}: torch {torch.__version__} sees no CUDA device (a CPU build, or no GPU visible); use --device cpu")
        index = procs.local_rank if procs.world > 1 or dev.index is None else dev.index
        if index >= torch.cuda.device_count():
            raise TrainError(f"device cuda:{index}: only {torch.cuda.device_count()} CUDA devices are visible")
        return torch.device("cuda", index)
    if dev.type == "mps" and not torch.backends.mps.is_available():
        raise TrainError(f"device {name!r}: MPS is not available on this machine")
    return dev


def resolve_precision(precision: str, device: torch.device) -> str:
    """Return the precision ``train.precision`` means on ``device`` (``auto``: mixed on CUDA,
    bf16 where the GPU has it; 32 elsewhere)."""
    if precision != "auto":
        return precision
    if device.type != "cuda":
        return "32"
    return "bf16-mixed" if torch.cuda.is_bf16_supported() else "16-mixed"


def autocast(device: torch.device, precision: str) -> contextlib.AbstractContextManager:
    """Return the autocast context of ``precision`` on ``device`` (a no-op for 32)."""
    dtype = AMP_DTYPES.get(precision)
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=dtype)


@contextlib.contextmanager
def process_group(procs: Processes, device: torch.device) -> Iterator[None]:
    """Join torchrun's process group for the block (nothing to join in one process)."""
    if procs.world == 1:
        yield
        return
    import torch.distributed as dist

    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(device)
    dist.init_process_group(backend, timeout=datetime.timedelta(minutes=30))
    try:
        yield
    finally:
        dist.destroy_process_group()


def share_error(procs: Processes, message: str) -> None:
    """Raise TrainError(``message`` of rank 0) on every rank when rank 0 has one (RankError
    on the others: rank 0 alone reports it)."""
    if procs.world > 1:
        import torch.distributed as dist

        box = [message if procs.main else ""]
        dist.broadcast_object_list(box, src=0)
        message = box[0]
    if message:
        raise TrainError(message) if procs.main else RankError(message)


def mean_over(procs: Processes, values: torch.Tensor) -> torch.Tensor:
    """Return ``values`` averaged over the processes (themselves in one process)."""
    if procs.world == 1:
        return values
    import torch.distributed as dist

    out = values.clone()
    dist.all_reduce(out)
    return out / procs.world


def barrier(procs: Processes) -> None:
    if procs.world > 1:
        import torch.distributed as dist

        dist.barrier()
