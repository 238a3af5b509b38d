"""Every command through the real CLI: exit codes and messages."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import run_cli


def test_version_and_module_entry():
    from gtgen import __version__

    p = run_cli("--version")
    assert p.returncode == 0 and p.stdout.strip() == f"gtgen {__version__}"
    p = subprocess.run([sys.executable, "-m", "gtgen", "--help"], capture_output=True, text=True)
    assert p.returncode == 0
    for cmd in ("synth", "extract", "fuse", "dem-align", "report", "viz"):
        assert cmd in p.stdout


def test_help_has_examples():
    for cmd in ("synth", "extract", "fuse", "dem-align", "report", "viz"):
        p = run_cli(cmd, "--help")
        assert p.returncode == 0 and "Examples" in p.stdout, cmd


def test_bad_config_value_is_one_line(tmp_path):
    c = tmp_path / "c.yaml"
    c.write_text("fuse:\n  min_conf: 2\n")
    p = run_cli("fuse", "--config", c)
    assert p.returncode == 1 and "fuse.min_conf" in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_dem_align_report_viz_through_the_cli(dataset, drive_store, tmp_path):
    ws = drive_store.parent
    p = run_cli("dem-align", ws / "drive.zarr", "-o", tmp_path / "ds.zarr", "-c", "tests/data/small.yaml")
    assert p.returncode == 0, p.stderr
    assert "samples kept" in p.stdout and "ICP fitness" in p.stdout
    p = run_cli("report", tmp_path / "ds.zarr", "-o", tmp_path / "rep")
    assert p.returncode == 0, p.stderr
    assert "DEM alignment error" in p.stdout and (tmp_path / "rep" / "qa_overview.png").is_file()
    p = run_cli("viz", tmp_path / "ds.zarr", "--sample", "2", "-o", tmp_path / "s.png")
    assert p.returncode == 0 and (tmp_path / "s.png").stat().st_size > 10_000
    p = run_cli("viz", tmp_path / "ds.zarr", "--sample", "100000", "-o", tmp_path / "s.png")
    assert p.returncode == 1 and "out of range" in p.stderr
    p = run_cli("dem-align", ws / "drive.zarr", "--dem", tmp_path / "nope", "-o", tmp_path / "x.zarr", "-c", "tests/data/small.yaml")
    assert p.returncode == 1 and "DEM" in p.stderr and "does not exist" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.parametrize("args", [(), ("extract",), ("--bogus",), ("fuse", "--window", "abc"), ("nosuchcmd",)])
def test_usage_errors_print_usage_and_exit_2(args, tmp_path):
    p = run_cli(*args, cwd=tmp_path, timeout=60)
    assert p.returncode == 2, (args, p.returncode, p.stderr)
    assert "Traceback" not in p.stderr + p.stdout
    assert "Usage: gtgen " in " ".join((p.stderr + p.stdout).split())
