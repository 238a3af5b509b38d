"""Shared fixtures: one small synthetic drive per test session, and the stages run on it.

The drive is made by the real ``run_synth`` from ``tests/data/small.yaml`` (seeded), so
every stage test sees the same bytes. Session fixtures are built lazily and reused.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from gtgen.config import GtgenConfig, load_config

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


@pytest.fixture(scope="session")
def drive_dir(tmp_path_factory, cfg) -> Path:
    from gtgen.synth import run_synth

    out = tmp_path_factory.mktemp("synth") / "drive"
    run_synth(cfg, out)
    return out


@pytest.fixture(scope="session")
def drive_store(tmp_path_factory, drive_dir, cfg) -> Path:
    from gtgen.extract import run_extract

    out = tmp_path_factory.mktemp("ws") / "drive.zarr"
    run_extract([drive_dir / "drive.mcap"], out, cfg)
    return out


@pytest.fixture(scope="session")
def fused_store(drive_store, cfg) -> Path:
    from gtgen.fuse.run import run_fuse

    out = drive_store.parent / "fused.zarr"
    run_fuse(drive_store, out, cfg, workers=1)
    return out


@pytest.fixture(scope="session")
def dataset(fused_store, drive_store, cfg) -> Path:
    from gtgen.dataset.dem_align import run_dem_align

    out = drive_store.parent / "dataset.zarr"
    run_dem_align(drive_store, fused_store, None, out, cfg)
    return out


@pytest.fixture(scope="session")
def with_val(dataset, tmp_path_factory) -> Path:
    """The test dataset with every fourth sample in the val split."""
    import shutil

    import zarr

    out = tmp_path_factory.mktemp("val") / "dataset.zarr"
    shutil.copytree(dataset, out)
    g = zarr.open_group(str(out), mode="r+")
    split = g["meta/split"][:]
    split[::4] = 1
    g["meta/split"][:] = split
    reseal(out)
    return out


def reseal(store: Path) -> None:
    """Record a store a test edited in place as written whole (as a gtgen that wrote it so
    would have), so that the edit, not the integrity check, is what the test meets."""
    import shutil

    from gtgen.storage.integrity import MANIFEST, write_manifest

    shutil.rmtree(store / MANIFEST, ignore_errors=True)
    write_manifest(store)


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run ``python -m gtgen ARGS`` and return the finished process (text output)."""
    env = dict(os.environ, COLUMNS="200")
    return subprocess.run([sys.executable, "-m", "gtgen", *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)


def needs_realdata() -> pytest.MarkDecorator:
    return pytest.mark.skipif(not REALDATA.is_dir(), reason=f"shared/realdata not found at {REALDATA}")
