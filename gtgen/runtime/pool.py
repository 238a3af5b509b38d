"""The one process pool of gtgen (extract, fuse, dem-align and the build run on it), and
bounded background threads for I/O.

Workers are never forked from the parent, which may hold open stores, threads and
open3d's thread pool: they are forked from a fork server (Python's ``forkserver``), a
clean interpreter started once per process that has imported numpy, zarr and gtgen's
storage, so a worker starts in milliseconds instead of importing them again as a spawned
one does (about a second of CPU each; where there is no fork server, workers are spawned).
Each worker gets one OpenMP / BLAS thread (unless the user set those variables): the pool
already keeps every core busy, and nested threads only contend.
"""

from __future__ import annotations

import multiprocessing.context as mpc
import os
import signal
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from typing import Any

from gtgen.errors import WorkerDiedError
from gtgen.runtime.progress import track

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
_QUIET_TRACKER = "ignore:resource_tracker:UserWarning"
# what the fork server imports once for every worker it forks: what every stage's jobs use
# (a job's own module is imported by the worker that first runs it)
PRELOAD = ("numpy", "zarr", "gtgen.storage.stores", "gtgen.grids", "gtgen.geometry")


def _start_worker(init: Callable[..., Any] | None, args: tuple) -> None:
    """Set up a worker: Ctrl-C is the parent's to handle (it stops the workers; a worker
    of its own would print a traceback for it), the worker ends when the process that
    owns the pool is gone (killed, say: it would otherwise wait for jobs forever), then
    ``init(*args)``. The worker was started with SIGINT blocked (``_sigint_blocked``): it
    is ignored before it is unblocked, so a Ctrl-C during start-up is dropped here too."""
    import faulthandler
    import multiprocessing
    import threading
    from multiprocessing.connection import wait

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    faulthandler.enable()  # a worker that crashes in native code prints where, above the pool's one-line error
    owner = multiprocessing.parent_process()  # the pool's process (not the fork server), its pipe's end

    def watch() -> None:
        wait([owner.sentinel])  # readable once the owner's end of the pipe is closed: it has exited
        os._exit(1)

    if owner is not None:
        threading.Thread(target=watch, daemon=True, name="gtgen-orphan-watch").start()
    if init is not None:
        init(*args)


@contextmanager
def _sigint_blocked() -> Iterator[None]:
    """Block SIGINT in this thread for the ``with`` block: a process started meanwhile
    inherits the mask (through fork and exec), and keeps the signal pending until it
    unblocks it; this process's own Ctrl-C is delivered when the mask is restored.
    multiprocessing's resource tracker is started first if it is not running: starting it
    unblocks SIGINT (``pthread_sigmask(SIG_UNBLOCK)`` after its own block), which would
    undo the block for the process started next."""
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


class _QuietSpawnProcess(mpc.SpawnProcess):
    """A spawned worker that starts with SIGINT blocked: a Ctrl-C that reaches a worker
    while it starts (its interpreter boots for a second or more on a busy machine, before
    ``_start_worker`` can ignore the signal) would end it half-way, print its traceback
    and break the pool the parent is stopping."""

    def start(self) -> None:
        with _sigint_blocked():
            super().start()


class _QuietSpawnContext(mpc.SpawnContext):
    Process = _QuietSpawnProcess


def _context() -> mpc.BaseContext:
    """Return the workers' start method: the fork server, started with SIGINT blocked (its
    workers inherit the mask, as ``_QuietSpawnProcess``'s do), or spawning where there is
    no fork server (Windows)."""
    import multiprocessing
    from multiprocessing import forkserver

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return _QuietSpawnContext()
    ctx = multiprocessing.get_context("forkserver")
    with _sigint_blocked():
        if forkserver._forkserver._forkserver_pid is None:  # its modules are fixed when it starts
            import atexit

            ctx.set_forkserver_preload(["__main__", *PRELOAD])
            # stopped and waited for at exit (Python leaves it to end unwaited): its workers'
            # CPU time and peak memory then count as this process's children's, in `time`,
            # rusage and the benchmarks, as spawned workers' did (a second stop is a no-op)
            atexit.register(forkserver._forkserver._stop)
        forkserver.ensure_running()
    return ctx


class Pool:
    """Runs jobs (picklable functions and arguments) on ``workers`` processes;
    with one worker, in this process. The pool lives until ``close``, so several rounds
    of jobs pay for worker start-up once.

    ``warm``, a picklable function, is run once per worker at once (it imports what the
    jobs need), so that start-up overlaps with what the caller does before the first jobs.
    ``init`` = (function, arguments) is run once in each worker before any job (and here
    when the pool has one worker): it sets up state the jobs share, such as large arrays
    the workers map from files rather than receive with every job.
    """

    def __init__(self, workers: int, warm: Callable[[], Any] | None = None,
                 init: tuple[Callable[..., Any], tuple] | None = None) -> None:
        self.workers = max(1, int(workers))
        self._ex = None
        self._env: dict[str, str | None] = {}
        if self.workers == 1 and init is not None:
            init[0](*init[1])
        if self.workers > 1:
            import sys

            # workers stopped mid-job (``close(stop=True)``) may hold a lock of the job queue,
            # which the resource tracker then frees with a warning that means nothing here
            # (the tracker, started with the first pool, takes this process's warning options)
            if _QUIET_TRACKER not in sys.warnoptions:
                sys.warnoptions.append(_QUIET_TRACKER)
            from concurrent.futures import ProcessPoolExecutor

            # workers spawn on demand: the variables stay set while the pool lives
            self._env = {k: os.environ.get(k) for k in THREAD_VARS}
            for k in THREAD_VARS:
                os.environ.setdefault(k, "1")
            fn, args = init if init is not None else (None, ())
            self._ex = ProcessPoolExecutor(max_workers=self.workers, mp_context=_context(),
                                           initializer=_start_worker, initargs=(fn, args))
            if warm is not None:
                for _ in range(self.workers):
                    self._ex.submit(warm)

    @property
    def parallel(self) -> bool:
        """Whether jobs run in other processes."""
        return self._ex is not None

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        """Return the future of ``fn(*args)``; run at once here when the pool has one worker."""
        if self._ex is not None:
            return self._ex.submit(fn, *args)
        fut: Future = Future()
        try:
            fut.set_result(fn(*args))
        except BaseException as err:  # noqa: BLE001 - handed to the caller through the future
            fut.set_exception(err)
        return fut

    def map(self, fn: Callable[..., Any], jobs: list[tuple], label: str | None = None) -> Iterator:
        """Yield ``fn(*job)`` for each job in order; a progress bar over jobs if ``label``
        (leave it out when the jobs show their own)."""
        results = (fn(*j) for j in jobs) if self._ex is None else self._ex.map(fn, *zip(*jobs)) if jobs else iter(())
        return results if label is None else track(results, label, total=len(jobs))

    def imap(self, fn: Callable[..., Any], items: list, ahead: int | None = None) -> Iterator:
        """Yield ``fn(item)`` for each item in order, keeping at most ``ahead`` (default: two
        per worker) submitted beyond the one yielded, so that results do not pile up."""
        if self._ex is None:
            yield from (fn(x) for x in items)
            return
        ahead = ahead or 2 * self.workers
        pending: list[Future] = []
        for x in items:
            pending.append(self._ex.submit(fn, x))
            if len(pending) > ahead:
                yield pending.pop(0).result()
        while pending:
            yield pending.pop(0).result()

    def as_completed(self, fn: Callable[..., Any], jobs: list[tuple], label: str | None = None) -> Iterator:
        """Yield ``fn(*job)`` of every job as each finishes (in order with one worker)."""
        if self._ex is None:
            results: Iterator = (fn(*j) for j in jobs)
        else:
            from concurrent.futures import as_completed

            futs = [self._ex.submit(fn, *j) for j in jobs]
            results = (f.result() for f in as_completed(futs))
        return results if label is None else track(results, label, total=len(jobs))

    def close(self, stop: bool = False) -> None:
        """Stop the workers: waiting for running jobs and cancelling queued ones, or with
        ``stop`` (the caller failed or was interrupted) ending the running ones too."""
        if self._ex is not None:
            if stop:
                for p in self._processes():
                    p.terminate()
            self._ex.shutdown(wait=True, cancel_futures=True)
            self._ex = None
            for k, v in self._env.items():
                if v is None:
                    os.environ.pop(k, None)

    def _processes(self) -> list:
        """Return the worker processes (no public way before Python 3.14)."""
        return list((getattr(self._ex, "_processes", None) or {}).values())

    def __enter__(self) -> Pool:
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, tb: object) -> None:
        from concurrent.futures.process import BrokenProcessPool

        broken = isinstance(exc, BrokenProcessPool)
        procs = self._processes() if broken else []
        self.close(stop=exc is not None)
        if broken and exc.__cause__ is not None:  # the pool broke reading a result, not on a dead worker
            lines = [x.strip() for x in str(exc.__cause__).splitlines() if x.strip() not in ("", "'''")]
            raise WorkerDiedError(f"a worker's result could not be read back ({lines[-1] if lines else 'no message'}), so the output was not "
                                  "completed; this is a bug of gtgen: please report it with this line") from exc
        if broken:  # Python tells no more than that a worker is gone: how each one ended says more
            ends = sorted({_how_ended(p.exitcode) for p in procs if p.exitcode}) or ["unknown"]
            raise WorkerDiedError(f"a worker process of {self.workers} ended abruptly ({', '.join(ends)}; the pool stops the "
                                  "others with SIGTERM; SIGKILL is usually the system out of memory, or its set-up failed, "
                                  "printed above), so the output was not completed; run the command again, with fewer "
                                  "workers or smaller sizes if memory is short") from exc


def _how_ended(exitcode: int) -> str:
    """Return 'signal SIGKILL' or 'exit code 1' for a process's exit code."""
    if exitcode < 0:
        try:
            return f"signal {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"signal {-exitcode}"
    return f"exit code {exitcode}"


class BackgroundWrites:
    """Calls on two background threads (compression and file I/O release the GIL), so that
    encoding overlaps with reading; at most a few calls are in flight, which bounds memory.
    The first error is raised on the next ``submit`` or on exit."""

    def __init__(self, threads: int = 2, in_flight: int = 8) -> None:
        self.threads, self.in_flight = threads, in_flight

    def __enter__(self) -> BackgroundWrites:
        from concurrent.futures import ThreadPoolExecutor

        self.pool = ThreadPoolExecutor(max_workers=self.threads)
        self.pending: list[Future] = []
        return self

    def submit(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run ``fn(*args)`` on a thread."""
        self.pending.append(self.pool.submit(fn, *args))
        while len(self.pending) > self.in_flight:
            self.pending.pop(0).result()

    def drain(self) -> None:
        """Wait for every call submitted so far."""
        while self.pending:
            self.pending.pop(0).result()

    def __exit__(self, *exc: object) -> None:
        try:
            if exc[0] is None:
                self.drain()
        finally:
            self.pool.shutdown(wait=True, cancel_futures=True)
