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
from collections.abc import Callable
from pathlib import Path
from typing import Any, Optional, get_args

import typer
from typer.core import TyperGroup

from gtgen import __version__
from gtgen.errors import ConfigError, GtgenError, RankError


class Group(TyperGroup):
    """The command group whose help names each parameter's type in words (``PATH...``,
    ``NUMBER``), as the usage line does, where typer would print the Python annotation
    (``<list[Path]>``) and ``<bool>`` beside every flag."""

    def __init__(self, **attrs: Any) -> None:
        super().__init__(**attrs)
        _plain_types(self)


_TYPE_WORDS = {Path: "PATH", int: "INTEGER", float: "NUMBER", str: "TEXT"}


def _plain_types(cmd: Any) -> None:
    """Show the types of ``cmd``'s parameters (its --help option's too, made on demand),
    and of its subcommands', as ``_type_word`` says."""
    for param in cmd.params:
        param.display_type_rich = lambda ctx, p=param: _type_word(p)
    make_help = cmd.get_help_option

    def help_option(ctx: Any) -> Any:
        opt = make_help(ctx)
        if opt is not None:
            opt.display_type_rich = lambda ctx: None
        return opt

    cmd.get_help_option = help_option
    for sub in getattr(cmd, "commands", {}).values():
        _plain_types(sub)


def _type_word(param: Any) -> str | None:
    """Return how help shows ``param``'s type: an option's metavar, a word, or nothing for
    a flag."""
    if getattr(param, "is_flag", False):
        return None
    if getattr(param, "metavar", None) and not isinstance(param, typer.core.TyperArgument):
        return str(param.metavar)
    d = param.type_descriptor
    ann = get_args(d.annotation)[0] if d.is_list else d.annotation
    word = _TYPE_WORDS.get(ann, getattr(ann, "__name__", str(ann)).upper())
    if not d.is_list:
        return word
    return f"{word}..." if isinstance(param, typer.core.TyperArgument) else f"{word} (repeatable)"


app = typer.Typer(
    cls=Group,
    add_completion=False,
    no_args_is_help=True,
    rich_markup_mode="markdown",
    help="""gtgen: pseudo ground truth for BEV elevation and traversability learning (RoadRunner M&M).

**Examples** (in one folder: the workspace gtgen_ws/)

```
gtgen extract bag.mcap
gtgen fuse --window 60
gtgen dem-align --dem usgs_1m/
gtgen report
gtgen train
```
""",
    pretty_exceptions_enable=False,
)

WORKSPACE = Path("gtgen_ws")
MAX_WORKERS = 256  # more processes than any machine gtgen runs on has cores: a typo, not a request
ConfigOpt = typer.Option(None, "--config", "-c", metavar="FILE", help="partial YAML over the defaults in configs/")
OverwriteOpt = typer.Option(False, "--overwrite", help="replace an existing output even if gtgen did not write it")


def setting(key: str) -> Callable[[Any], Any]:
    """Return an option callback that holds a value to the bounds of config key ``key``
    ('fuse.window_s'), so that ``--window inf`` is a usage error naming the option."""

    def check(value: Any) -> Any:
        if value is None:
            return None
        from gtgen.config import check_value

        try:
            return check_value(key, value)
        except ConfigError as err:
            raise typer.BadParameter(str(err)) from None

    return check


def console():
    """Return the console that tables are printed on."""
    import shutil

    from rich.console import Console

    return Console(width=max(120, shutil.get_terminal_size((120, 40)).columns))


def load(config: Optional[Path], *overrides: dict[str, Any]):
    """Return the config of ``--config`` (if given) with ``overrides`` on top."""
    from gtgen.config import load_config

    return load_config(config, *overrides)


def read_yaml(path: Path, what: str = "config file") -> dict:
    """Return the mapping of a YAML file (a ``--config`` file, a manifest: ``what``)."""
    from gtgen.config import read_yaml as read

    return read(path, what)


def table(title: str, rows: list[tuple[str, Any]]) -> None:
    """Print a two-column summary table (a missing value shows as n/a)."""
    from rich.table import Table

    t = Table(title=title, show_header=False)
    t.add_column("", style="bold")
    t.add_column("")
    for k, v in rows:
        t.add_row(str(k), na(v))
    console().print(t)


def na(v: Any, unit: str = "") -> str:
    """Return ``v`` and its ``unit`` for a table cell, or 'n/a' for a value that does not
    exist (None: a region without cells, a rate without samples)."""
    return "n/a" if v is None else f"{v}{unit}"


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
    sys.unraisablehook = _quiet_closed_loop
    sys.exit(1)


def _quiet_closed_loop(unraisable: Any) -> None:
    """After an error: drop the "Event loop is closed" of zarr reads cut short, collected
    at exit (the second campaign's TRACEBACK-1); anything else is shown as Python would."""
    exc = unraisable.exc_value
    if isinstance(exc, RuntimeError) and "Event loop is closed" in str(exc):
        return
    sys.__unraisablehook__(unraisable)


def _terminated(signum: int, frame: Any) -> None:
    raise SystemExit(128 + signum)


def main() -> None:
    """Run the CLI: a usage error (a bad option value, a missing argument) prints the usage
    and the error on one line and exits 2; gtgen errors and OS errors (a full disk, a
    permission) print one line and exit 1. SIGTERM ends the command as Ctrl-C does, through
    its clean-up (the temporary outputs go), with exit code 143."""
    import signal

    signal.signal(signal.SIGTERM, _terminated)
    try:
        code = app(prog_name="gtgen", standalone_mode=False)
    except typer.TyperException as err:  # click's usage errors
        _usage_error(err)
    except typer.Abort:
        typer.echo("error: aborted", err=True)
        sys.exit(1)
    except RankError:  # under torchrun, rank 0 prints the error its processes share
        sys.exit(1)
    except GtgenError as err:
        _fail(str(err))
    except OSError as err:
        _fail(f"{err.strerror or err}" + (f": '{err.filename}'" if err.filename else ""))
    except MemoryError:
        _fail("out of memory; lower the sizes in the config (grids, images, shards.max_voxel_points, train.batch_size)")
    sys.exit(code if isinstance(code, int) else 0)


def _usage_error(err: Any) -> None:
    """Print a usage error as the usage line and one line of error, and exit with its code
    (2). The usage that no arguments ask for has been printed as the help already."""
    ctx = getattr(err, "ctx", None)
    if type(err).__name__ != "NoArgsIsHelpError":
        if ctx is not None:
            typer.echo(ctx.get_usage(), err=True)
        hint = f" (see '{ctx.command_path} --help')" if ctx is not None else ""
        typer.echo(f"error: {' '.join(err.format_message().split())}{hint}", err=True)
    sys.exit(err.exit_code)
