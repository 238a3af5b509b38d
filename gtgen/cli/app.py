"""The ``gtgen`` command line: the typer app, its shared options and helpers, and ``main``.

The only package that prints or exits. Every command reads and writes a workspace in
the current directory by default: ``gtgen extract bag.mcap`` -> ``./gtgen_ws/drive.zarr``;
``gtgen fuse`` reads it and writes ``./gtgen_ws/fused.zarr``; ``gtgen dem-align`` reads
both and writes ``./gtgen_ws/dataset.zarr``; ``gtgen train`` reads that. Explicit paths override. Heavy imports live inside the
commands so that ``--help`` is instant.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any, Optional

import typer

from gtgen import __version__
from gtgen.errors import GtgenError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    rich_markup_mode="markdown",
    help="gtgen: pseudo ground truth for BEV elevation and traversability learning (RoadRunner M&M).",
    pretty_exceptions_enable=False,
)

WORKSPACE = Path("gtgen_ws")
ConfigOpt = typer.Option(None, "--config", "-c", help="partial YAML over the defaults in configs/")
OverwriteOpt = typer.Option(False, "--overwrite", help="replace an existing output even if gtgen did not write it")


def console():
    """Return the console that tables are printed on."""
    import shutil

    from rich.console import Console

    return Console(width=max(120, shutil.get_terminal_size((120, 40)).columns))


def load(config: Optional[Path], *overrides: dict[str, Any]):
    """Return the config of ``--config`` (if given) with ``overrides`` on top."""
    from gtgen.config import load_config

    return load_config(config, *overrides)


def read_yaml(path: Path) -> dict:
    """Return the mapping of a ``--config`` file."""
    from gtgen.config import read_yaml as read

    return read(path)


def table(title: str, rows: list[tuple[str, Any]]) -> None:
    """Print a two-column summary table."""
    from rich.table import Table

    t = Table(title=title, show_header=False)
    t.add_column("", style="bold")
    t.add_column("")
    for k, v in rows:
        t.add_row(str(k), str(v))
    console().print(t)


def fmt(v: Any, pct: bool = False) -> str:
    """Return a metric for a table: 3 decimals, a percentage, or n/a."""
    if v is None:
        return "n/a"
    return f"{v:.1f}%" if pct else f"{v:.3f}"


def _version(value: bool) -> None:
    if value:
        typer.echo(f"gtgen {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="print the version and exit"),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="log debug messages"),
) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")



def _fail(message: str) -> None:
    """Print one error line and exit 1. zarr's event loop may hold reads that an error cut
    short; their teardown at exit is not the user's business, so it stays quiet."""
    import warnings

    typer.echo(f"error: {message}", err=True)
    logging.getLogger("asyncio").setLevel(logging.CRITICAL)
    warnings.filterwarnings("ignore", message="coroutine .* was never awaited")
    sys.exit(1)


def main() -> None:
    """Run the CLI: usage errors print the usage and exit 2 (click's standalone mode);
    gtgen errors and OS errors (a full disk, a permission) print one line and exit 1."""
    try:
        app(prog_name="gtgen")
    except GtgenError as err:
        _fail(str(err))
    except OSError as err:
        _fail(f"{err.strerror or err}" + (f": '{err.filename}'" if err.filename else ""))
