"""The runtime every stage shares: locks, atomic outputs, the process pool."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import SMALL, run_cli
from gtgen.errors import GtgenError, LockedError
from gtgen.runtime.output import atomic_output, lock, partial_path, stage_output
from gtgen.runtime.pool import Pool


def _gtgen(*args: str, cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "gtgen", *map(str, args)], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.time() + timeout
    while not path.exists():
        assert proc.poll() is None, f"the command ended before writing {path}: {proc.stderr.read() if proc.stderr else ''}"
        assert time.time() < deadline, f"{path} never appeared"
        time.sleep(0.02)


def _workspace(drive_store: Path, tmp_path: Path) -> Path:
    ws = tmp_path / "gtgen_ws"
    ws.mkdir()
    (ws / "drive.zarr").symlink_to(drive_store)
    return ws


def test_two_concurrent_fuse_on_one_workspace(drive_store, tmp_path):
    """The second command stops at once with one line naming the lock; the first finishes."""
    ws = _workspace(drive_store, tmp_path)
    first = _gtgen("fuse", "-c", SMALL, "--workers", "1", cwd=tmp_path)
    try:
        _wait_for(ws / "fused.zarr.partial", first)
        os.killpg(first.pid, signal.SIGSTOP)  # frozen while it holds the lock
        second = run_cli("fuse", "-c", SMALL, cwd=tmp_path, timeout=120)
        os.killpg(first.pid, signal.SIGCONT)
        assert second.returncode == 1 and "Traceback" not in second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and "fused.zarr.lock" in lines[0] and "another gtgen command" in lines[0], lines
        assert first.wait(timeout=300) == 0, first.stderr.read()
    finally:
        if first.poll() is None:
            os.killpg(first.pid, signal.SIGKILL)
    assert (ws / "fused.zarr" / "zarr.json").is_file() and not partial_path(ws / "fused.zarr").exists()


def test_a_stage_killed_mid_write_leaves_nothing_the_next_stage_accepts(drive_store, tmp_path):
    ws = _workspace(drive_store, tmp_path)
    proc = _gtgen("fuse", "-c", SMALL, "--workers", "1", cwd=tmp_path)
    _wait_for(ws / "fused.zarr.partial" / "fused", proc)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (ws / "fused.zarr").exists()
    p = run_cli("dem-align", "-c", SMALL, cwd=tmp_path)
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "fused store" in p.stderr and "did not finish" in p.stderr
    p = run_cli("fuse", "-c", SMALL, cwd=tmp_path)  # the kernel released the dead command's lock
    assert p.returncode == 0, p.stderr
    assert not partial_path(ws / "fused.zarr").exists()


def test_a_failed_block_leaves_no_output_and_the_old_one_stays(tmp_path):
    out = tmp_path / "x.zarr"
    with stage_output(out) as tmp:
        tmp.mkdir()
        (tmp / "a").write_text("one")
        (tmp / "zarr.json").write_text('{"attributes": {"store": "gtgen-drive"}}')  # a store gtgen wrote: it may replace it
    with pytest.raises(RuntimeError), stage_output(out) as tmp:
        tmp.mkdir()
        (tmp / "a").write_text("two")
        raise RuntimeError("disk full, say")
    assert (out / "a").read_text() == "one" and not partial_path(out).exists()


def test_locks_exclusive_and_shared(tmp_path):
    store = tmp_path / "s.zarr"
    with lock(store):
        # a lock is per open file: a second open in this process sees it held
        with pytest.raises(LockedError, match=r"s\.zarr\.lock"):
            with lock(store, shared=True):
                pass
    with lock(store, shared=True), lock(store, shared=True):  # readers share
        with pytest.raises(LockedError, match="read by another gtgen command"):
            with lock(store):
                pass
    assert issubclass(LockedError, GtgenError) and issubclass(LockedError, BlockingIOError)


def test_atomic_file_output(tmp_path):
    f = tmp_path / "ckpt.pt"
    with atomic_output(f) as tmp:
        tmp.write_bytes(b"x")
        assert not f.exists()
    assert f.read_bytes() == b"x" and not partial_path(f).exists()


def _square(x: int) -> int:
    return x * x


def _fail(x: int) -> int:
    raise ValueError(f"job {x} failed")


def _threads() -> str | None:
    return os.environ.get("OMP_NUM_THREADS")


@pytest.mark.parametrize("workers", [1, 2])
def test_pool_map_submit_and_errors(workers, monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    with Pool(workers) as pool:
        assert list(pool.map(_square, [(i,) for i in range(5)])) == [0, 1, 4, 9, 16]
        assert sorted(pool.as_completed(_square, [(i,) for i in range(5)])) == [0, 1, 4, 9, 16]
        assert pool.submit(_square, 7).result() == 49
        with pytest.raises(ValueError, match="job 3 failed"):
            pool.submit(_fail, 3).result()
        # spawned workers get one OpenMP / BLAS thread unless the user set one
        assert pool.submit(_threads).result() == ("1" if workers > 1 else None)
    assert _threads() is None  # the parent's environment is restored
