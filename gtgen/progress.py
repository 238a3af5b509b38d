"""The one progress helper (and the process pool that reports through it): library code
reports progress only through this."""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")

log = logging.getLogger("gtgen")


@contextmanager
def _bar(total: float | None, desc: str) -> Iterator[object]:
    if not sys.stderr.isatty():
        yield None
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        transient=True,
    ) as prog:
        task = prog.add_task(desc, total=total)
        yield (prog, task)


def track(items: Iterable[T], desc: str, total: float | None = None, status=None) -> Iterator[T]:
    """Yield ``items`` unchanged while showing a progress bar on a terminal.

    ``status``, if given, is called after each item and its text is shown after ``desc``
    (the trainer shows its loss this way).
    """
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    log.debug("%s: %s items", desc, total)
    with _bar(total, desc) as handle:
        for item in items:
            yield item
            if handle is not None:
                prog, task = handle  # type: ignore[misc]
                prog.update(task, advance=1, description=f"{desc} {status()}" if status else desc)


class ProcessJobs:
    """Runs jobs (picklable functions and arguments) on a spawn process pool, in order;
    with one worker, in this process. The pool lives until ``close``, so several rounds
    of jobs pay for worker start-up once."""

    def __init__(self, workers: int, warm=None) -> None:
        """``warm``, a picklable function, is run ``workers`` times at once (each worker
        usually takes one; it imports what the jobs need), so that start-up overlaps with
        what the caller does before the first jobs."""
        self.pool = None
        if workers > 1:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            self.pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"))
            if warm is not None:
                for _ in range(workers):
                    self.pool.submit(warm)

    def map(self, fn, jobs: list[tuple], label: str | None = None) -> Iterator:
        """Yield ``fn(*job)`` for each job in order; a progress bar over jobs if ``label``
        (leave it out when the jobs show their own)."""
        results = (fn(*j) for j in jobs) if self.pool is None else self.pool.map(fn, *zip(*jobs))
        return results if label is None else track(results, label, total=len(jobs))

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> ProcessJobs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
