"""Atomic outputs, what gtgen may replace or remove, and locks: the one place where they live.

Every stage writes its output (a store folder or a file) under a temporary name beside it
and renames it into place only when complete, so a kill, a full disk or an error leaves
nothing that a later stage accepts. gtgen's temporary names carry a token of their run
(``<name>.<pid>-<8 hex digits>.partial``; ``.old`` for the output a replacement moves
aside, ``.scratch`` for a writer's own scratch), and each is recorded in the machine's gtgen
folder before it exists (``Temporaries``): a record per output being written, held by a
``flock`` while its writer lives. So a temporary name never is a user's file, and gtgen
removes only what it recorded: on every exit path of the writer (an error, Ctrl-C, SIGTERM
through the CLI), or, when the kernel killed it, at the next write of the same output on
this machine (the dead writer's lock is released, its record says what it left).

An existing output is replaced only when gtgen wrote it (``owned``: a gtgen store, or a
file bearing ``SIGNATURE``, which every file gtgen writes carries near its start or end),
or with ``overwrite`` (the CLI's ``--overwrite``); anything else at the path is the user's
and stops the command with a one-line error. No output goes inside a gtgen store
(``check_outside_stores``, part of ``check_replace``): a store holds only what its stage
wrote. A symlink is repointed only when gtgen made it (``point_link``).

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
import glob
import hashlib
import json
import os
import re
import secrets
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from gtgen.errors import GtgenError, LockedError, OutputExistsError

PARTIAL = ".partial"
LOCK = ".lock"
SIGNATURE = "written by gtgen"  # in every file gtgen writes (JSON key, PNG text, TIFF tag, MCAP metadata, YAML comment)
_SIGNATURE_WINDOW = 1 << 22  # bytes searched at each end of a file
TEMP_TAGS = ("partial", "old", "scratch")  # the temporary names of an output: <name>.<token>.<tag>
_TOKEN = r"\d+-[0-9a-f]{8}"


def partials(path: Path) -> list[Path]:
    """Return the partial outputs of ``path`` that runs left beside it (unfinished or killed)."""
    pattern = re.compile(re.escape(path.name) + r"\." + _TOKEN + re.escape(PARTIAL))
    return [p for p in map(Path, glob.glob(glob.escape(str(path)) + ".*" + PARTIAL)) if pattern.fullmatch(p.name)]


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


def _path_key(path: Path) -> str:
    """Return the key of ``path`` in the lock folder's names (a hash of its absolute path)."""
    return hashlib.sha256(os.path.abspath(path).encode()).hexdigest()[:16]


def lock_path(path: Path) -> Path:
    """Return the lock file of ``path`` (named after its absolute path, in ``lock_dir``)."""
    return lock_dir() / f"{_path_key(path)}-{Path(os.path.abspath(path)).name}{LOCK}"


def owned(path: Path) -> bool:
    """Whether ``path`` holds something gtgen wrote: a gtgen store (its ``zarr.json``
    names a gtgen store kind) or a file bearing ``SIGNATURE``. A name is no proof: a
    user's ``x.partial`` is the user's."""
    if path.is_dir():
        return store_kind(path) is not None
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


def store_kind(folder: Path) -> str | None:
    """Return the kind of the gtgen store at ``folder`` ('gtgen-dataset', ...), or None
    when it is none (no ``zarr.json`` naming a gtgen kind)."""
    try:
        attrs = json.loads((folder / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError, AttributeError):
        return None
    kind = attrs.get("store") if isinstance(attrs, dict) else None
    return kind if isinstance(kind, str) and kind.startswith("gtgen-") else None


def check_outside_stores(path: Path) -> None:
    """Raise OutputExistsError if ``path`` lies inside a gtgen store (through symlinks
    too): a store holds only what its stage wrote, and anything else in it makes
    ``gtgen verify`` call it damaged."""
    full = Path(os.path.abspath(path))
    real = full.parent.resolve()
    folders = [*full.parents, *((real, *real.parents) if real != full.parent else ())]
    for folder in folders:
        kind = store_kind(folder)
        if kind is not None:
            where = folder if Path(path).is_absolute() else os.path.relpath(folder)
            raise OutputExistsError(f"output '{path}' is inside the {kind.removeprefix('gtgen-')} store '{where}', which holds "
                                    "only what gtgen wrote into it; choose an output outside the store")


def check_replace(path: Path, overwrite: bool = False, file: bool = False) -> None:
    """Raise OutputExistsError if writing ``path`` would replace something gtgen did not
    write (unless ``overwrite``), put an output inside a gtgen store, or (``file``: the
    output is a file) replace a folder."""
    check_outside_stores(path)
    if file and path.is_dir():
        raise OutputExistsError(f"output '{path}' is a folder, and this output is one file: give the file's path "
                                "(a name inside the folder, say)")
    if overwrite or not (path.exists() or path.is_symlink()) or owned(path):
        return
    what = "folder" if path.is_dir() else "file"
    raise OutputExistsError(f"output '{path}' is an existing {what} that gtgen did not write; choose another output "
                            "or pass --overwrite to replace it")


def output_kind(path: Path) -> str:
    """Return what ``path`` holds, to tell one gtgen output from another: a store's kind,
    else the file's format by its first bytes (a checkpoint is a zip)."""
    if path.is_dir():
        kind = store_kind(path)
        return f"{kind.removeprefix('gtgen-')} store" if kind else "folder"
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError:
        return "file"
    for magic, kind in ((b"\x89PNG", "PNG image"), (b"PK", "checkpoint (zip)"), (b"\x89MCAP", "MCAP file"),
                        (b"II*\x00", "GeoTIFF"), (b"MM\x00*", "GeoTIFF"), (b"{", "JSON file")):
        if head.lstrip().startswith(magic):
            return kind
    return "file"


def check_not_over_inputs(path: Path, reads: Sequence[Path]) -> None:
    """Raise OutputExistsError if the output ``path`` is one of the command's inputs
    ``reads`` or a folder holding one (through symlinks too): replacing it would delete
    the input, so ``--overwrite`` does not lift this."""
    outs = {Path(os.path.abspath(path)), Path(path).resolve()}
    for p in reads:
        inps = {Path(os.path.abspath(p)), Path(p).resolve()}  # the input as named (a link) and what it is
        if outs & inps:
            raise OutputExistsError(f"output '{path}' is an input of this command; choose another output")
        if any(out in inp.parents for out in outs for inp in inps):
            raise OutputExistsError(f"output '{path}' holds '{p}', an input of this command, which replacing the output "
                                    "would delete (--overwrite too); choose another output")


def check_same_kind(path: Path, new: Path, overwrite: bool = False) -> None:
    """Raise OutputExistsError if ``path`` holds a gtgen output of another kind than the
    one written at ``new`` (unless ``overwrite``): a command's output over a checkpoint, a
    store of another stage or a figure is refused, not replaced."""
    if overwrite or not (path.exists() or path.is_symlink()):
        return
    old, made = output_kind(path), output_kind(new)
    if old != made:
        raise OutputExistsError(f"output '{path}' holds a gtgen {old}, and this command writes a {made}; nothing was replaced: "
                                "choose another output or pass --overwrite to replace it")


def remove(path: Path) -> None:
    """Remove a file or folder if it exists."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _temps_dir() -> Path:
    return lock_dir() / "temps"


class Temporaries:
    """The temporary names of one write of output ``path`` (``name(tag)``, a tag of
    ``TEMP_TAGS``), recorded before they exist and removed when the block ends, whatever
    ends it. Entering first removes what dead writers of the same output left (their
    records' locks are free)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.token = f"{os.getpid()}-{secrets.token_hex(4)}"
        self.prefix = f"{self.path.name}.{self.token}."
        self._fd: int | None = None
        self._record: Path | None = None

    def name(self, tag: str) -> Path:
        """Return the temporary path of ``tag`` (not made)."""
        if tag not in TEMP_TAGS:
            raise ValueError(f"temporary tag {tag!r}; expected one of {TEMP_TAGS}")
        return self.path.with_name(self.prefix + tag)

    def __enter__(self) -> Temporaries:
        _sweep(self.path)
        folder = _temps_dir()
        stem = f"{_path_key(self.path)}-{self.token}"
        try:
            folder.mkdir(parents=True, exist_ok=True, mode=0o700)
            new = folder / f"{stem}.new"
            fd = os.open(new, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        except OSError as err:
            raise GtgenError(f"cannot record a temporary output in '{folder}' ({err.strerror}); set GTGEN_LOCK_DIR to a writable folder") from err
        fcntl.flock(fd, fcntl.LOCK_EX)  # held while this process lives: a sweep sees the writer alive
        os.write(fd, json.dumps({"output": os.path.abspath(self.path), "prefix": self.prefix, "pid": os.getpid()}).encode())
        self._record = folder / f"{stem}.json"
        os.rename(new, self._record)  # a record appears whole and locked
        self._fd = fd
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            for tag in TEMP_TAGS:
                remove(self.name(tag))
        finally:
            if self._record is not None:
                self._record.unlink(missing_ok=True)
            if self._fd is not None:
                os.close(self._fd)


def _sweep(path: Path) -> None:
    """Remove the temporary names that writers of ``path`` recorded and left when killed
    (a record whose lock is free: the kernel released it with its process)."""
    for rec in glob.glob(str(_temps_dir() / f"{_path_key(path)}-*.json")):
        try:
            fd = os.open(rec, os.O_RDONLY)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            if os.fstat(fd).st_nlink == 0:  # its writer finished meanwhile and removed it
                continue
            doc = json.loads(os.read(fd, 1 << 16))
            if doc["output"] != os.path.abspath(path):
                continue
            for tag in TEMP_TAGS:
                remove(Path(doc["output"]).with_name(doc["prefix"] + tag))
            os.unlink(rec)
        except (OSError, ValueError, KeyError, TypeError):  # alive (the lock is held), or not a record of ours
            continue
        finally:
            os.close(fd)


@contextlib.contextmanager
def temporary(path: Path, tag: str = "scratch") -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (not made) for the block, removed after it."""
    with Temporaries(path) as t:
        yield t.name(tag)


def _replace(tmp: Path, path: Path, old: Path) -> None:
    """Put the completed ``tmp`` at ``path``: one rename for a file; two for a folder
    (the one there moves aside to ``old`` first, a temporary name of this write, and is
    removed after)."""
    if not tmp.is_dir():
        os.replace(tmp, path)
        return
    if path.exists() or path.is_symlink():
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
def atomic_output(path: Path, overwrite: bool = False, file: bool = False) -> Iterator[Path]:
    """Yield the temporary path to write ``path`` into (a file or a folder, made by the
    caller; ``file``: it must be a file); on success it replaces ``path``, on any failure it
    is removed, with the folders made for it. Refuses (OutputExistsError) to replace what
    gtgen did not write, unless ``overwrite``. No lock: use inside ``stage_output`` or a
    held ``lock``."""
    check_replace(path, overwrite, file)
    made = _make_parents(path.parent)
    try:
        with Temporaries(path) as temps:
            tmp = temps.name("partial")
            try:
                yield tmp
                if not (tmp.exists() or tmp.is_symlink()):
                    raise GtgenError(f"nothing was written for '{path}'")
                check_replace(path, overwrite, file)  # what appeared there meanwhile is not ours to replace either
                check_same_kind(path, tmp, overwrite)
                _replace(tmp, path, temps.name("old"))
            except OSError as err:
                full = _no_space(err, path)
                if full is not None:
                    raise full from err
                raise
    except BaseException:
        _remove_made(made)
        raise


def write_atomic(path: Path, data: bytes | str, overwrite: bool = False) -> None:
    """Write a whole file atomically (written beside, then renamed); the caller's ``data``
    carries ``SIGNATURE`` (see ``write_json``)."""
    with atomic_output(path, overwrite, file=True) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)


def write_json(path: Path, obj: dict, overwrite: bool = False, **dumps: object) -> None:
    """Write ``obj`` as a JSON file atomically, with ``written_by`` (the signature) as its first key."""
    write_atomic(path, json.dumps({"written_by": signature(), **obj}, **dumps), overwrite)  # type: ignore[arg-type]


def save_figure(fig: object, path: Path, overwrite: bool = False, dpi: int = 80) -> Path:
    """Save a matplotlib figure as a PNG atomically (the signature in its text chunk); return ``path``."""
    with atomic_output(path, overwrite, file=True) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, metadata={"Software": signature()})  # type: ignore[attr-defined]
    return path


def point_link(link: Path, target: Path, ours: Callable[[Path], bool]) -> str | None:
    """Make the symlink ``link`` point at ``target`` (a sibling, by its name) when nothing
    is at ``link`` or gtgen made what is there: a symlink to a sibling that ``ours`` says
    gtgen wrote. Return None when done, else why ``link`` was left as it is."""
    if link.is_symlink():
        was = os.readlink(link)
        if was == target.name:
            return None
        if os.sep in was or not ours(link.parent / was):
            return f"'{link}' points at '{was}', not at a folder gtgen wrote; left as it is (remove it, and gtgen makes it anew)"
    elif link.exists():
        return f"'{link}' is not a symlink gtgen made; left as it is"
    with Temporaries(link) as temps:
        tmp = temps.name("partial")
        tmp.symlink_to(target.name)
        os.replace(tmp, link)  # one rename: never a moment without the link
    return None


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
def stage_output(path: Path, reads: Sequence[Path] = (), overwrite: bool = False, file: bool = False) -> Iterator[Path]:
    """Yield the partial path of a stage's output ``path`` while holding its lock and a
    shared lock on each input in ``reads``; the output appears only when the block succeeds
    (see ``atomic_output`` for what it may replace; ``file``: the output is a file)."""
    check_replace(path, overwrite, file)  # before any work
    check_not_over_inputs(path, reads)
    with contextlib.ExitStack() as stack:
        stack.enter_context(lock(path))
        for p in reads:
            stack.enter_context(lock(Path(p), shared=True))
        yield stack.enter_context(atomic_output(path, overwrite, file))
