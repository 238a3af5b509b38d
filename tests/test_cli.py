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


def _commands(cmd, path=()):
    """Yield (words, click command) of ``cmd`` and of every command and subcommand under it."""
    yield path, cmd
    for name, sub in getattr(cmd, "commands", {}).items():
        yield from _commands(sub, (*path, name))


def test_help_of_every_command_shows_its_examples_one_per_line_and_types_in_words():
    """At 80 columns, as most terminals are: each example of the docstring's fenced block
    is one whole line of the help, and no parameter type reads like a Python annotation."""
    import re

    import typer
    from typer.testing import CliRunner

    from gtgen.cli import app

    seen = 0
    for words, cmd in _commands(typer.main.get_command(app)):
        block = re.search(r"```\n(.*?)```", cmd.help, re.S)
        assert block, f"'gtgen {' '.join(words)}' has no fenced block of examples in its help"
        examples = [e.strip() for e in block.group(1).splitlines()]
        # torchrun launches gtgen as a module: the one example that starts otherwise.
        starts = ("gtgen ", "torchrun ")
        assert examples and all(e.startswith(starts) and len(e) <= 72 for e in examples), (words, examples)
        p = CliRunner().invoke(app, [*words, "--help"], env={"COLUMNS": "80"}, prog_name="gtgen")
        assert p.exit_code == 0, (words, p.output)
        lines = [line.strip() for line in p.stdout.splitlines()]
        assert all(e in lines for e in examples), (words, examples, p.stdout)
        assert sum(line.startswith(starts) for line in lines) == len(examples), words
        assert not re.search(r"<\w+>|list\[|None", p.stdout), (words, p.stdout)
        seen += 1
    assert seen == 16  # gtgen, its twelve commands and export's three


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
    assert "None" not in p.stdout and "n/a %" not in p.stdout  # a missing value reads n/a, without a unit
    assert "regions micro (% of labelled; paper Tab. I)" in p.stdout and "obs_f" in p.stdout and "(46.4%)" in p.stdout
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


def test_a_missing_table_value_reads_n_a(capsys):
    from gtgen.cli.app import na, table

    table("t", [("given", 0.5), ("missing", None)])
    out = capsys.readouterr().out
    assert "0.5" in out and "n/a" in out and "None" not in out
    assert na(None, " m") == "n/a" and na(0.25, " m") == "0.25 m"


def test_viz_title_stays_within_the_figure(dataset, tmp_path, monkeypatch):
    """The title is wrapped to the figure (it ran off both edges: "aset.zarr sample 5 ...
    grey no"), also under a long dataset name."""
    from gtgen import viz

    titles = []

    def save(fig, out, overwrite, dpi):  # the title's extent on the canvas the PNG is drawn on
        titles.append((fig._suptitle.get_window_extent(fig.canvas.get_renderer()), fig.bbox.width, fig._suptitle.get_text()))

    monkeypatch.setattr(viz, "save_figure", save)
    long = tmp_path / ("a_dataset_of_the_field_campaign_with_a_long_descriptive_name_" * 2 + ".zarr")
    long.symlink_to(dataset)
    for path in (dataset, long):
        viz.render_sample(path, 2, tmp_path / "s.png")
        box, width, text = titles[-1]
        assert box.x0 >= 0 and box.x1 <= width, (path.name, box, width)
        assert path.name in text.replace("\n", "")
