"""Shared fixtures: one small synthetic drive per test session, and the stages run on it.

The drive is made by the real ``run_synth`` from ``tests/data/small.yaml`` (seeded), so
every stage test sees the same bytes. Session fixtures are built lazily, once per run:
the first xdist worker to need one builds it under a file lock, the others read it.

Each test process uses one OpenMP / BLAS / torch thread: the two xdist workers already
keep both cores busy, and nested threads only contend.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import fcntl  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from gtgen.config import GtgenConfig, load_config  # noqa: E402
from warm_gtgen import WarmGtgen  # noqa: E402

DATA = Path(__file__).parent / "data"
SMALL = DATA / "small.yaml"
# shared/realdata beside the repo (/work/main) or beside the folder of worktrees (/work/wt/<branch>)
REALDATA = next((p / "shared" / "realdata" for p in Path(__file__).resolve().parents[2:4] if (p / "shared" / "realdata").is_dir()),
                Path(__file__).resolve().parents[2] / "shared" / "realdata")


def small_config(**over) -> GtgenConfig:
    """Return the small test config, with optional overrides per section."""
    return load_config(SMALL, over) if over else load_config(SMALL)


@pytest.fixture(scope="session")
def cfg() -> GtgenConfig:
    return small_config()


def shared(tmp_path_factory: pytest.TempPathFactory, name: str, build: Callable[[Path], None]) -> Path:
    """Return the path ``name`` ('ws/drive.zarr') of this run's shared folder, made by
    ``build(path)`` once for all xdist workers (the first to ask builds it under a lock;
    a failed build leaves nothing behind)."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared"
    out = root / name
    out.parent.mkdir(parents=True, exist_ok=True)
    key = name.replace("/", "_")
    with open(root / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / f"{key}.done").exists():
            shutil.rmtree(out, ignore_errors=True)
            try:
                build(out)
            except BaseException:
                shutil.rmtree(out, ignore_errors=True)
                raise
            (root / f"{key}.done").touch()
    return out


@pytest.fixture(scope="session")
def drive_dir(tmp_path_factory, cfg) -> Path:
    from gtgen.synth import run_synth

    return shared(tmp_path_factory, "synth/drive", lambda out: run_synth(cfg, out))


@pytest.fixture(scope="session")
def drive_store(tmp_path_factory, drive_dir, cfg) -> Path:
    from gtgen.extract import run_extract

    return shared(tmp_path_factory, "ws/drive.zarr", lambda out: run_extract([drive_dir / "drive.mcap"], out, cfg))


@pytest.fixture(scope="session")
def fused_store(tmp_path_factory, drive_store, cfg) -> Path:
    from gtgen.fuse.run import run_fuse

    return shared(tmp_path_factory, "ws/fused.zarr", lambda out: run_fuse(drive_store, out, cfg, workers=1))


@pytest.fixture(scope="session")
def dataset(tmp_path_factory, fused_store, drive_store, cfg) -> Path:
    from gtgen.dataset.dem_align import run_dem_align

    return shared(tmp_path_factory, "ws/dataset.zarr", lambda out: run_dem_align(drive_store, fused_store, None, out, cfg))


@pytest.fixture(scope="session")
def with_val(dataset, tmp_path_factory) -> Path:
    """The test dataset with every fourth sample in the val split."""

    def build(out: Path) -> None:
        import zarr

        shutil.copytree(dataset, out)
        g = zarr.open_group(str(out), mode="r+")
        split = g["meta/split"][:]
        split[::4] = 1
        g["meta/split"][:] = split
        reseal(out)

    return shared(tmp_path_factory, "val/dataset.zarr", build)


def reseal(store: Path) -> None:
    """Record a store a test edited in place as written whole (as a gtgen that wrote it so
    would have), so that the edit, not the integrity check, is what the test meets."""
    from gtgen.storage.integrity import MANIFEST, write_manifest

    shutil.rmtree(store / MANIFEST, ignore_errors=True)
    write_manifest(store)


_WARM = WarmGtgen()


def run_cli(*args: object, cwd: Path | None = None, timeout: float = 600, columns: int = 200,
            env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Run ``gtgen ARGS`` as its own process (forked from a warm interpreter, see
    ``tests/warm_gtgen.py``) on a terminal ``columns`` wide, and return the finished
    process (text output). ``env`` replaces this process's environment."""
    return _WARM.run([str(a) for a in args], cwd, dict(env if env is not None else os.environ, COLUMNS=str(columns)), timeout)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    _WARM.close()
    session.config._gtgen_failed = exitstatus == pytest.ExitCode.TESTS_FAILED  # type: ignore[attr-defined]


# The tests' temporary folders go to a RAM disk when there is one with room: they write
# about 0.6 GB in thousands of small zarr chunk files, and on an ext4 disk that has just
# deleted many files (each run deletes the last but two) creating a file costs the
# kernel's inode search (``recently_deleted``), a quarter of the suite's CPU went to
# system time. ``--basetemp DIR`` (or GTGEN_TEST_TMP=disk) keeps pytest's own choice.
RAM_DISK = Path("/dev/shm")
RAM_DISK_ROOM = 2 << 30  # bytes free the suite asks of it
_RAM_PREFIX = "gtgen-tests-"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@pytest.hookimpl(tryfirst=True)  # before pytest's tmp_path factory reads --basetemp
def pytest_configure(config: pytest.Config) -> None:
    if config.option.basetemp or os.environ.get("PYTEST_XDIST_WORKER") or os.environ.get("GTGEN_TEST_TMP") == "disk":
        return
    try:
        st = os.statvfs(RAM_DISK)
        if not os.access(RAM_DISK, os.W_OK) or st.f_bavail * st.f_frsize < RAM_DISK_ROOM:
            return
        # the folders of earlier runs whose pytest is gone (killed, or kept after failures)
        for old in RAM_DISK.glob(f"{_RAM_PREFIX}{os.getuid()}-*"):
            pid = old.name.split("-")[3]
            if pid.isdigit() and not _alive(int(pid)):
                shutil.rmtree(old, ignore_errors=True)
        import tempfile

        base = tempfile.mkdtemp(prefix=f"{_RAM_PREFIX}{os.getuid()}-{os.getpid()}-", dir=RAM_DISK)
    except OSError:
        return
    config.option.basetemp = base
    config._gtgen_ram_basetemp = Path(base)  # type: ignore[attr-defined]


def pytest_unconfigure(config: pytest.Config) -> None:
    """Free the RAM disk's folder, unless tests failed (then it stays for a look, and the
    next run removes it)."""
    base = getattr(config, "_gtgen_ram_basetemp", None)
    if base is not None and not getattr(config, "_gtgen_failed", False):
        shutil.rmtree(base, ignore_errors=True)


def needs_realdata() -> pytest.MarkDecorator:
    return pytest.mark.skipif(not REALDATA.is_dir(), reason=f"shared/realdata not found at {REALDATA}")



def assert_same_store(a: Path, b: Path) -> None:
    """Assert that two zarr stores hold the same arrays with the same values (NaN where NaN)."""
    import numpy as np
    import zarr

    def arrays(store: Path) -> dict:
        return {k: v[...] for k, v in zarr.open_group(str(store), mode="r").members(max_depth=None) if isinstance(v, zarr.Array)}

    x, y = arrays(a), arrays(b)
    assert x.keys() == y.keys() and len(x) > 20
    for k in x:
        assert np.array_equal(x[k], y[k], equal_nan=x[k].dtype.kind == "f"), k
