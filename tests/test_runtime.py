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
from gtgen.runtime.output import atomic_output, lock, partials, stage_output
from gtgen.runtime.pool import Pool


def _gtgen(*args: str, cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "gtgen", *map(str, args)], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def _wait_for(folder: Path, pattern: str, proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.time() + timeout
    while not list(folder.glob(pattern)):
        assert proc.poll() is None, f"the command ended before writing {pattern}: {proc.stderr.read() if proc.stderr else ''}"
        assert time.time() < deadline, f"{pattern} never appeared"
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
        _wait_for(ws, "fused.zarr.*.partial", first)
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
    assert (ws / "fused.zarr" / "zarr.json").is_file() and not partials(ws / "fused.zarr")


def test_a_stage_killed_mid_write_leaves_nothing_the_next_stage_accepts(drive_store, tmp_path):
    ws = _workspace(drive_store, tmp_path)
    proc = _gtgen("fuse", "-c", SMALL, "--workers", "1", cwd=tmp_path)
    _wait_for(ws, "fused.zarr.*.partial/fused", proc)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (ws / "fused.zarr").exists()
    p = run_cli("dem-align", "-c", SMALL, cwd=tmp_path)
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "fused store" in p.stderr and "did not finish" in p.stderr
    p = run_cli("fuse", "-c", SMALL, "--workers", "1", cwd=tmp_path)  # the kernel released the dead command's lock
    assert p.returncode == 0, p.stderr
    assert not partials(ws / "fused.zarr")


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
    assert (out / "a").read_text() == "one" and not partials(out)


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
    assert f.read_bytes() == b"x" and not partials(f)


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
        # the workers get one OpenMP / BLAS thread unless the user set one
        assert pool.submit(_threads).result() == ("1" if workers > 1 else None)
    assert _threads() is None  # the parent's environment is restored


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def test_a_worker_killed_mid_job_is_one_clear_error():
    """A worker the kernel kills (out of memory, say) ends the pool's block with
    WorkerDiedError, a GtgenError the CLI prints on one line (it was a BrokenProcessPool
    traceback)."""
    from gtgen.errors import WorkerDiedError

    with pytest.raises(WorkerDiedError, match="ended abruptly \\(signal SIGKILL"):
        with Pool(2) as pool:
            pool.submit(_die).result()


def _refuse_to_load() -> None:
    raise ValueError("no way back")


class _OneWay:
    """Pickles in the worker; loading it in the parent raises."""

    def __reduce__(self):
        return (_refuse_to_load, ())


def _one_way() -> _OneWay:
    return _OneWay()


def test_a_result_the_parent_cannot_read_is_named_not_called_a_dead_worker():
    """A result that does not unpickle in the parent breaks Python's pool as a dead worker
    would (BrokenProcessPool); the error says which it was, with the reading's own error
    (a message object of a class the parent did not know broke a suite run so)."""
    from gtgen.errors import WorkerDiedError

    with pytest.raises(WorkerDiedError, match=r"result could not be read back \(ValueError: no way back\)"):
        with Pool(2) as pool:
            pool.submit(_one_way).result()


def _sigint_held(pid: int) -> bool | None:
    """Whether process ``pid`` blocks or ignores SIGINT (None when it is gone)."""
    try:
        fields = dict(line.split(":\t", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":\t" in line)
    except OSError:
        return None
    bit = 1 << (signal.SIGINT - 1)
    return bool((int(fields["SigBlk"], 16) | int(fields["SigIgn"], 16)) & bit)


def test_a_worker_holds_off_ctrl_c_from_its_first_instruction():
    """A worker's interpreter boots for a second or more on a busy machine before its
    set-up ignores SIGINT; a Ctrl-C in that window ended it half-way with a traceback and
    broke the pool the parent was stopping (a run of the suite hung 30 s on it). Polled
    from its start until it runs a job, a worker blocks or ignores SIGINT at every look."""
    with Pool(2) as pool:
        futs = [pool.submit(time.sleep, 0.3) for _ in range(2)]
        pids = [p.pid for p in pool._ex._processes.values()]
        looks = 0
        while not all(f.done() for f in futs):
            for pid in pids:
                held = _sigint_held(pid)
                assert held is not False, f"worker {pid} would be ended by a Ctrl-C (look {looks})"
            looks += 1
        assert looks > 10 and all(_sigint_held(pid) for pid in pids)


POOL_SCRIPT = """
import os, signal, sys, time
from gtgen.runtime.pool import Pool

# as from a terminal: a shell's background job (``cmd &``) starts with SIGINT ignored,
# which Python then keeps, and the Ctrl-C case would wait for the busy workers' minute
signal.signal(signal.SIGINT, signal.default_int_handler)

def busy(x):
    t = time.time()
    while time.time() - t < 60:
        pass

if __name__ == "__main__":
    with Pool(2) as pool:
        futs = [pool.submit(busy, i) for i in range(4)]
        print(" ".join(str(p.pid) for p in pool._ex._processes.values()), flush=True)
        time.sleep(60)
"""


@pytest.mark.parametrize("how", ["ctrl-c", "killed"])
def test_stopping_the_parent_stops_the_workers_quietly(how, tmp_path):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) stops the
    workers without a traceback of theirs; a parent killed outright leaves no worker
    behind (they used to wait for jobs forever)."""
    script = tmp_path / "pool_script.py"
    script.write_text(POOL_SCRIPT)
    p = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True, cwd=Path(__file__).resolve().parents[1])
    pids = [int(x) for x in p.stdout.readline().split()]
    assert len(pids) == 2
    time.sleep(1.0)  # the workers are busy
    os.killpg(p.pid, signal.SIGINT) if how == "ctrl-c" else os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=30)
    err = p.stderr.read()
    for _ in range(50):  # at most 10 s: the workers end when their parent's end of a pipe closes
        if not any(os.path.exists(f"/proc/{pid}") and "Z" not in _state(pid) for pid in pids):
            break
        time.sleep(0.2)
    assert not any(os.path.exists(f"/proc/{pid}") and "Z" not in _state(pid) for pid in pids)
    if how == "ctrl-c":
        assert "SpawnProcess" not in err and "ForkServerProcess" not in err and "leaked" not in err and err.count("Traceback") <= 1, err


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except OSError:
        return "Z"


# -- gtgen removes only what it wrote, whatever the name -------------------------------------

def _users_lookalikes(out: Path) -> dict[Path, str]:
    """Make the user's own files and folders named as gtgen's temporary names once were."""
    mine = {out.with_name(out.name + ".old") / "notes.txt": "backup", out.with_name(out.name + ".partial"): "mine",
            out.with_name(out.name + ".scratch.partial"): "mine too", out.with_name(out.name + ".1-0123abcd.partial"): "look-alike"}
    for f, text in mine.items():
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(text)
    return mine


@pytest.mark.parametrize("kind", ["folder", "file"])
def test_outputs_never_remove_the_users_old_or_partial(kind, tmp_path):
    """A first write, a replacement and a failed write of an output leave the user's
    '<out>.old' folder and '<out>.partial' files as they were (they used to be removed)."""
    out = tmp_path / ("x.zarr" if kind == "folder" else "x.json")
    mine = _users_lookalikes(out)

    def write(text: str) -> None:
        with stage_output(out) as tmp:
            if kind == "folder":
                tmp.mkdir()
                (tmp / "zarr.json").write_text('{"attributes": {"store": "gtgen-drive"}}')
                (tmp / "a").write_text(text)
            else:
                tmp.write_text(f'{{"written_by": "written by gtgen", "a": "{text}"}}')

    write("one")
    write("two")  # replaces its own output
    with pytest.raises(RuntimeError), stage_output(out) as tmp:
        tmp.mkdir() if kind == "folder" else tmp.write_text("half")
        raise RuntimeError("failed")
    assert ((out / "a").read_text() if kind == "folder" else out.read_text()).count("two") == 1
    assert {f: f.read_text() for f in mine} == mine
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted({out.name, *(f.relative_to(tmp_path).parts[0] for f in mine)})


def _die_writing(out: Path) -> None:
    """Run a process that starts writing ``out`` (folder) and is killed by the kernel."""
    code = ("import os, signal, sys; from pathlib import Path; from gtgen.runtime.output import atomic_output\n"
            "with atomic_output(Path(sys.argv[1])) as tmp:\n    tmp.mkdir(); (tmp / 'half').write_text('x')\n"
            "    os.kill(os.getpid(), signal.SIGKILL)\n")
    assert subprocess.run([sys.executable, "-c", code, str(out)]).returncode == -signal.SIGKILL


def test_a_killed_writers_temporaries_go_at_the_next_write_and_nothing_else(tmp_path):
    out = tmp_path / "x.zarr"
    _die_writing(out)
    left = partials(out)
    assert len(left) == 1 and (left[0] / "half").is_file()  # the kernel's kill: no clean-up ran
    mine = _users_lookalikes(out)
    with atomic_output(out) as tmp:
        tmp.mkdir()
    assert not left[0].exists() and {f: f.read_text() for f in mine} == mine


def test_the_cli_cleans_up_on_sigterm(dataset, tmp_path):
    """SIGTERM ends a command through its clean-up: no temporary output is left (the
    command is held just before it renames its output into place)."""
    code = ("import sys, time; import gtgen.runtime.output as o; o._replace = lambda *a: time.sleep(120)\n"
            "from gtgen.cli import main; sys.argv[0] = 'gtgen'; main()")
    proc = subprocess.Popen([sys.executable, "-c", code, "viz", str(dataset), "-o", str(tmp_path / "s.png")], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    _wait_for(tmp_path, "s.png.*.partial", proc)
    os.killpg(proc.pid, signal.SIGTERM)
    assert proc.wait(timeout=60) == 143
    assert list(tmp_path.iterdir()) == []


def test_latest_is_repointed_only_when_gtgen_made_it(tmp_path):
    from gtgen.runtime.output import point_link

    runs = tmp_path / "runs"
    for name in ("a", "b", "mydata"):
        (runs / name).mkdir(parents=True)
    ours = {runs / "a", runs / "b"}
    latest = runs / "latest"
    assert point_link(latest, runs / "a", lambda p: p in ours) is None and os.readlink(latest) == "a"
    assert point_link(latest, runs / "b", lambda p: p in ours) is None and os.readlink(latest) == "b"
    latest.unlink()
    latest.symlink_to("mydata")  # the user's link
    note = point_link(latest, runs / "a", lambda p: p in ours)
    assert os.readlink(latest) == "mydata" and "points at 'mydata'" in note and "left as it is" in note
    latest.unlink()
    latest.symlink_to(runs / "a")  # the user's link, by an absolute path, to a run
    assert point_link(latest, runs / "b", lambda p: p in ours) is not None and os.readlink(latest) == str(runs / "a")
    latest.unlink()
    latest.write_text("a file")
    assert point_link(latest, runs / "b", lambda p: p in ours) is not None and latest.read_text() == "a file"
    assert sorted(p.name for p in runs.iterdir()) == ["a", "b", "latest", "mydata"]
