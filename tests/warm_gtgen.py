"""A warm ``gtgen`` for the tests: each command runs in a child forked from a server that
imported gtgen's commands and their heavy libraries (torch, zarr, open3d, rasterio) once.

A fresh ``python -m gtgen`` pays 2-3 s of imports per call, and the suite makes about a
hundred calls. The child is the command as a user runs it: its own process, ``sys.argv``
``gtgen ARGS``, the caller's working folder and environment, stdin from /dev/null, its
output in files, its exit code from ``gtgen.cli.main``. The server never runs a command
itself, so no thread pool (OpenMP, open3d) exists when it forks. It is started with
``python -c`` so that a command's spawned pool workers find no main script to re-import.

Protocol on the server's stdin / stdout: one pickled request (args, cwd, env, out, err,
timeout) per line of length, answered by the pickled exit code, or None on a timeout.
"""

from __future__ import annotations

import os
import pickle
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

# what the commands import inside their bodies (gtgen.cli keeps --help instant); torch's
# optimizers import torch._dynamo when the first is made (1.2-1.6 s a training command)
PRELOAD = ("gtgen.cli", "numpy", "scipy.ndimage", "zarr", "torch", "torch._dynamo", "open3d", "rasterio", "pyproj",
           "rich.console", "gtgen.synth", "gtgen.extract", "gtgen.fuse.run", "gtgen.dataset.dem_align", "gtgen.train.trainer")


def _read(stream) -> object | None:
    head = stream.read(4)
    if len(head) < 4:
        return None
    (n,) = struct.unpack("!I", head)
    return pickle.loads(stream.read(n))


def _write(stream, obj: object) -> None:
    data = pickle.dumps(obj)
    stream.write(struct.pack("!I", len(data)) + data)
    stream.flush()


def _child(args: list[str], cwd: str, env: dict[str, str], out: str, err: str) -> None:
    """Become ``gtgen ARGS`` and exit with its code (never returns)."""
    code = 1
    try:
        os.chdir(cwd)
        os.environ.clear()
        os.environ.update(env)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(os.open(out, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), 1)
        os.dup2(os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), 2)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.argv = ["gtgen", *args]
        from gtgen.cli import main

        try:
            main()
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            if exc.code is not None and not isinstance(exc.code, int):
                print(exc.code, file=sys.stderr)
        except KeyboardInterrupt:
            code = 130
        except BaseException:  # noqa: BLE001 - as the interpreter would: the traceback and exit 1
            import traceback

            traceback.print_exc()
            code = 1
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def serve() -> None:
    """Answer requests on stdin until it closes."""
    for name in PRELOAD:
        __import__(name)
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    while (req := _read(stdin)) is not None:
        args, cwd, env, out, err, timeout = req
        pid = os.fork()
        if pid == 0:
            stdin.close()
            _child(args, cwd, env, out, err)
        end = time.monotonic() + timeout
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                _write(stdout, os.waitstatus_to_exitcode(status))  # -N when killed by signal N, as subprocess says
                break
            if time.monotonic() > end:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                _write(stdout, None)
                break
            time.sleep(0.01)


class WarmGtgen:
    """One server per test process (started on first use), running one command at a time."""

    def __init__(self) -> None:
        self._proc: subprocess.Popen | None = None
        self._lock = threading.Lock()

    def _server(self) -> subprocess.Popen:
        if self._proc is None or self._proc.poll() is not None:
            here = str(Path(__file__).parent)
            code = f"import sys; sys.path.insert(0, {here!r}); import warm_gtgen; warm_gtgen.serve()"
            self._proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=dict(os.environ))
        return self._proc

    def run(self, args: list[str], cwd: Path | None, env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
        """Return the finished ``gtgen ARGS`` (text output), as ``subprocess.run`` would."""
        with self._lock, tempfile.TemporaryDirectory(prefix="warm_gtgen_") as tmp:
            out, err = os.path.join(tmp, "stdout"), os.path.join(tmp, "stderr")
            proc = self._server()
            _write(proc.stdin, (args, str(cwd or os.getcwd()), env, out, err, timeout))
            code = _read(proc.stdout)
            text = [Path(p).read_text(errors="replace") if os.path.exists(p) else "" for p in (out, err)]
            argv = ["gtgen", *args]
            if code is None:
                if proc.poll() is not None:
                    raise RuntimeError(f"the warm gtgen server died running {argv}")
                raise subprocess.TimeoutExpired(argv, timeout, output=text[0], stderr=text[1])
            return subprocess.CompletedProcess(argv, code, text[0], text[1])

    def close(self) -> None:
        if self._proc is not None:
            self._proc.stdin.close()
            self._proc.wait(timeout=30)
            self._proc = None
