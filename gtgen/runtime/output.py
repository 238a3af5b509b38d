"""Atomic outputs and locks: the one place where ``.partial`` and ``.lock`` files live.

Every stage writes its output (a store folder or a file) under ``<name>.partial`` and
renames it into place only when complete, so a kill, a full disk or an error leaves
nothing that a later stage accepts; the partial output is removed on failure. While it
writes, a stage holds an exclusive lock on its output and a shared lock on each input
(``flock`` on ``<name>.lock`` beside it). A second command that would write the same
store, or write a store the first one reads, stops with a one-line error naming the lock
instead of racing. The kernel releases the locks of a killed process, so no stale lock
outlives it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

from gtgen.errors import GtgenError, LockedError

PARTIAL = ".partial"
LOCK = ".lock"


def partial_path(path: Path) -> Path:
    """Return where ``path`` is written before it is complete."""
    return path.with_name(path.name + PARTIAL)


def lock_path(path: Path) -> Path:
    """Return the lock file of ``path``."""
    return path.with_name(path.name + LOCK)


def remove(path: Path) -> None:
    """Remove a file or folder if it exists."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _replace(tmp: Path, path: Path) -> None:
    """Put the completed ``tmp`` at ``path``: one rename for a file; two for a folder
    (the old one moves aside first and is removed after)."""
    if not tmp.is_dir():
        os.replace(tmp, path)
        return
    old = path.with_name(path.name + ".old")
    remove(old)
    if path.exists():
        path.rename(old)
    tmp.rename(path)
    remove(old)


def _no_space(err: OSError, path: Path) -> GtgenError | None:
    if err.errno in (errno.ENOSPC, errno.EDQUOT):
        return GtgenError(f"no space left on the device while writing '{path}'; free some space and run the command again")
    return None


@contextlib.contextmanager
def atomic_output(path: Path) -> Iterator[Path]:
    """Yield the partial path to write ``path`` into (a file or a folder, made by the
    caller); on success it replaces ``path``, on any failure it is removed. No lock: use
    inside ``stage_output`` or a held ``lock``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = partial_path(path)
    remove(tmp)
    try:
        yield tmp
        _replace(tmp, path)
    except OSError as err:
        remove(tmp)
        full = _no_space(err, path)
        if full is not None:
            raise full from err
        raise
    except BaseException:
        remove(tmp)
        raise


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write a whole file atomically (written beside, then renamed)."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)


def _busy(fd: int, path: Path, file: Path) -> LockedError:
    """Return the error for a lock ``fd`` that another process holds: a writer holds it
    when even a shared lock is refused (its pid and command are in the file)."""
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
        who = "read by another gtgen command"
    except BlockingIOError:
        text = file.read_text(errors="replace").strip() if file.is_file() else ""
        who = f"written by another gtgen command ({text})" if text else "written by another gtgen command"
    return LockedError(f"'{path}' is being {who}: lock '{file}' is held; wait for it to finish")


@contextlib.contextmanager
def lock(path: Path, shared: bool = False) -> Iterator[None]:
    """Hold the lock of ``path`` (exclusive, or ``shared`` for readers) while the block runs;
    raise LockedError at once if another process holds it."""
    file = lock_path(path)
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(file, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:
        if shared and err.errno in (errno.EACCES, errno.EROFS, errno.EPERM):
            yield  # a store nobody may write here needs no reader's lock
            return
        raise
    try:
        try:
            fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            raise _busy(fd, path, file) from None
        if not shared:
            os.ftruncate(fd, 0)
            os.write(fd, f"pid {os.getpid()}: {' '.join([Path(sys.argv[0]).name, *sys.argv[1:]])}".encode())
        try:
            yield
        finally:
            if not shared:
                os.ftruncate(fd, 0)
    finally:
        os.close(fd)


@contextlib.contextmanager
def stage_output(path: Path, reads: Sequence[Path] = ()) -> Iterator[Path]:
    """Yield the partial path of a stage's output ``path`` while holding its lock and a
    shared lock on each input in ``reads``; the output appears only when the block succeeds."""
    with contextlib.ExitStack() as stack:
        stack.enter_context(lock(path))
        for p in reads:
            if Path(p).resolve() != Path(path).resolve():
                stack.enter_context(lock(Path(p), shared=True))
        yield stack.enter_context(atomic_output(path))
