"""The one progress helper: library code reports progress only through ``track``."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Iterable, Iterator
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


def track(items: Iterable[T], desc: str, total: float | None = None, status: Callable[[], str] | None = None) -> Iterator[T]:
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
