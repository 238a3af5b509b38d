"""Atomic outputs, what gtgen may replace, and locks: the one place where they live.

Every stage writes its output (a store folder or a file) under ``<name>.partial`` and
renames it into place only when complete, so a kill, a full disk or an error leaves
nothing that a later stage accepts; the partial output is removed on failure, and so are
the folders made for it. An existing output is replaced only when gtgen wrote it
(``owned``: a gtgen store, or a file bearing ``SIGNATURE``, which every file gtgen
writes carries near its start or end), or with ``overwrite`` (the CLI's
``--overwrite``); anything else at the path is the user's and stops the command with
a one-line error.

While it writes, a stage holds an exclusive lock on its output and a shared lock on each
input (``flock`` on a lock file named after the path, in a lock folder of the machine's:
``$GTGEN_LOCK_DIR``, else ``$XDG_RUNTIME_DIR/gtgen-locks``, else a per-user folder in the
temp folder; never beside the user's files). A second command that would write the same
output, or write one the first one reads, stops with a one-line error naming the lock
instead of racing. The kernel releases the locks of a killed process, so no stale lock
outlives it. Locks coordinate the commands of one machine.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

from gtgen.errors import GtgenError, LockedError, OutputExistsError

PARTIAL = ".partial"
LOCK = ".lock"
SIGNATURE = "written by gtgen"  # in every file gtgen writes (JSON key, PNG text, TIFF tag, MCAP metadata, YAML comment)
_SIGNATURE_WINDOW = 1 << 22  # bytes searched at each end of a file


def partial_path(path: Path) -> Path:
    """Return where ``path`` is written before it is complete."""
    return path.with_name(path.name + PARTIAL)


def signature() -> str:
    """Return the signature of gtgen's files, with this version."""
    from gtgen import __version__

    return f"{SIGNATURE} {__version__}"


def lock_dir() -> Path:
    """Return the folder of the machine's gtgen lock files (see the module docstring)."""
    env = os.environ.get("GTGEN_LOCK_DIR")
    if env:
        return Path(env)
    run = os.environ.get("XDG_RUNTIME_DIR")
    if run and os.path.isdir(run):
        return Path(run) / "gtgen-locks"
    return Path(tempfile.gettempdir()) / f"gtgen-locks-{os.getuid()}"


def lock_path(path: Path) -> Path:
    """Return the lock file of ``path`` (named after its absolute path, in ``lock_dir``)."""
    full = os.path.abspath(path)
    return lock_dir() / f"{hashlib.sha256(full.encode()).hexdigest()[:16]}-{Path(full).name}{LOCK}"


def owned(path: Path) -> bool:
    """Whether ``path`` holds something gtgen wrote: a gtgen store (its ``zarr.json``
    names a gtgen store kind), a partial output, or a file bearing ``SIGNATURE``."""
    if path.name.endswith(PARTIAL):
        return True
    if path.is_dir():
        try:
            attrs = json.loads((path / "zarr.json").read_text()).get("attributes", {})
        except (OSError, ValueError, AttributeError):
            return False
        return str(attrs.get("store", "")).startswith("gtgen-")
    try:
        with open(path, "rb") as f:
            head = f.read(_SIGNATURE_WINDOW)
            size = os.fstat(f.fileno()).st_size
            tail = b""
            if size > _SIGNATURE_WINDOW:
                f.seek(max(size - _SIGNATURE_WINDOW, _SIGNATURE_WINDOW))
                tail = f.read()
    except OSError:
        return False
    sig = SIGNATURE.encode()
    return sig in head or sig in tail


def check_replace(path: Path, overwrite: bool = False) -> None:
    """Raise OutputExistsError if writing ``path`` would replace something gtgen did not
    write (unless ``overwrite``)."""
    if overwrite or not (path.exists() or path.is_symlink()) or owned(path):
        return
    what = "folder" if path.is_dir() else "file"
    raise OutputExistsError(f"output '{path}' is an existing {what} that gtgen did not write; choose another output "
                            "or pass --overwrite to replace it")


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


def _make_parents(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; return those created, deepest first."""
    made: list[Path] = []
    p = folder
    while not p.exists() and p != p.parent:
        made.append(p)
        p = p.parent
    folder.mkdir(parents=True, exist_ok=True)
    return made


def _remove_made(made: list[Path]) -> None:
    """Remove the folders ``made`` for an output that failed, where still empty."""
    for d in made:
        try:
            d.rmdir()
        except OSError:
            return


@contextlib.contextmanager
def output_folder(folder: Path) -> Iterator[Path]:
    """Make ``folder`` (and its missing parents) for outputs written inside it one by one;
    if the block fails, remove the folders made here that are still empty (outputs already
    written inside stay, with their folders)."""
    made = _make_parents(folder)
    try:
        yield folder
    except BaseException:
        _remove_made(made)
        raise


@contextlib.contextmanager
def atomic_output(path: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield the partial path to write ``path`` into (a file or a folder, made by the
    caller); on success it replaces ``path``, on any failure it is removed, with the
    folders made for it. Refuses (OutputExistsError) to replace what gtgen did not write,
    unless ``overwrite``. No lock: use inside ``stage_output`` or a held ``lock``."""
    check_replace(path, overwrite)
    made = _make_parents(path.parent)
    tmp = partial_path(path)
    remove(tmp)
    try:
        yield tmp
        if not (tmp.exists() or tmp.is_symlink()):
            raise GtgenError(f"nothing was written for '{path}'")
        check_replace(path, overwrite)  # what appeared there meanwhile is not ours to replace either
        _replace(tmp, path)
    except OSError as err:
        remove(tmp)
        _remove_made(made)
        full = _no_space(err, path)
        if full is not None:
            raise full from err
        raise
    except BaseException:
        remove(tmp)
        _remove_made(made)
        raise


def write_atomic(path: Path, data: bytes | str, overwrite: bool = False) -> None:
    """Write a whole file atomically (written beside, then renamed); the caller's ``data``
    carries ``SIGNATURE`` (see ``write_json``)."""
    with atomic_output(path, overwrite) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)


def write_json(path: Path, obj: dict, overwrite: bool = False, **dumps: object) -> None:
    """Write ``obj`` as a JSON file atomically, with ``written_by`` (the signature) as its first key."""
    write_atomic(path, json.dumps({"written_by": signature(), **obj}, **dumps), overwrite)  # type: ignore[arg-type]


def save_figure(fig: object, path: Path, overwrite: bool = False, dpi: int = 80) -> Path:
    """Save a matplotlib figure as a PNG atomically (the signature in its text chunk); return ``path``."""
    with atomic_output(path, overwrite) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, metadata={"Software": signature()})  # type: ignore[attr-defined]
    return path


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
        file.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        fd = os.open(file, os.O_RDWR | os.O_CREAT, 0o600)
    except OSError as err:
        raise GtgenError(f"cannot make the lock file '{file}' ({err.strerror}); set GTGEN_LOCK_DIR to a writable folder") from err
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
def stage_output(path: Path, reads: Sequence[Path] = (), overwrite: bool = False) -> Iterator[Path]:
    """Yield the partial path of a stage's output ``path`` while holding its lock and a
    shared lock on each input in ``reads``; the output appears only when the block succeeds
    (see ``atomic_output`` for what it may replace)."""
    check_replace(path, overwrite)  # before any work
    with contextlib.ExitStack() as stack:
        stack.enter_context(lock(path))
        for p in reads:
            if Path(p).resolve() != Path(path).resolve():
                stack.enter_context(lock(Path(p), shared=True))
        yield stack.enter_context(atomic_output(path, overwrite))
