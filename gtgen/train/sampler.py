"""The training's sample order: resumable at any step, and split over torchrun's processes.

Epoch e visits the samples in a permutation seeded by (seed, e), in global batches of
``batch`` samples (the last incomplete one is dropped, as long as one full batch fits);
step k takes global batch k of that endless sequence, and process r of w the r-th of the
w equal slices of it. So the order depends on the seed and the step only: a run resumed
at step k draws what an uninterrupted one draws, and w processes together see the global
batches one process sees (what ``DistributedSampler`` gives, plus the resume).
"""

from __future__ import annotations

from collections.abc import Iterator

import torch

from gtgen.errors import ConfigError


class StepBatchSampler:
    """A batch sampler for ``DataLoader(batch_sampler=...)``: yields this process's sample
    positions of every step from ``start_step`` on, without end."""

    def __init__(self, n: int, batch: int, seed: int, start_step: int = 0, rank: int = 0, world: int = 1) -> None:
        if batch % world:
            raise ConfigError(f"train.batch_size {batch} is not a multiple of the {world} processes; it is the global batch, split evenly")
        if n < world:
            raise ConfigError(f"{n} training samples cannot feed {world} processes")
        self.n, self.batch, self.seed, self.start, self.rank, self.world = n, batch, seed, start_step, rank, world
        # a dataset smaller than one batch gives one (smaller) batch per epoch, split evenly
        self.per_epoch = max(1, n // batch)
        self.used = min(batch, n - n % world) if n < batch else batch

    def step_indices(self, step: int) -> list[int]:
        """Return this process's sample positions of ``step``."""
        epoch, k = divmod(step, self.per_epoch)
        perm = torch.randperm(self.n, generator=torch.Generator().manual_seed(self.seed * 1_000_003 + epoch))
        glob = perm[k * self.batch : k * self.batch + self.used]
        part = self.used // self.world
        return glob[self.rank * part : (self.rank + 1) * part].tolist()

    def __iter__(self) -> Iterator[list[int]]:
        step = self.start
        while True:
            yield self.step_indices(step)
            step += 1
