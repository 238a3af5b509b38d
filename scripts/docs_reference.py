"""The documentation's reference pages, made from the code at every build so they cannot
drift: every command's ``--help`` (from the typer app in ``gtgen/cli/``) and every config
key with its type, unit, default and range (from the pydantic models in ``gtgen/config/``
and the presets in ``gtgen/train/presets.py``).

An MkDocs hook (``mkdocs.yml``: ``hooks``): ``on_files`` adds ``reference/cli.md`` and
``reference/config.md`` to the site. Nothing here imports torch (the CLI imports its
heavy modules inside each command), so the build stays quick.

    python scripts/docs_reference.py config   # print a page (cli | config)
"""

from __future__ import annotations

import sys
import types
import typing
from pathlib import Path
from typing import Any, Literal

import annotated_types
import yaml
from pydantic import BaseModel
from pydantic.fields import FieldInfo

ROOT = Path(__file__).resolve().parent.parent
HELP_COLUMNS = 100  # the width --help is rendered at: the site's code blocks show it unwrapped
UNIT_SUFFIXES = {"_deg_per_100m": "deg/100 m", "_m_per_s": "m/s", "_per_m": "m/m", "_m": "m", "_s": "s", "_deg": "deg", "_rad": "rad", "_hz": "Hz", "_mps": "m/s", "_mb": "MiB", "_px": "px"}


# ---- config keys -----------------------------------------------------------------------

class Key(typing.NamedTuple):
    """One config key as the reference shows it."""

    name: str  # dotted, as a --config file spells it: 'fuse.window_s'
    type: str
    unit: str
    default: str
    range: str
    meaning: str


def config_keys() -> list[Key]:
    """Return every settable key of ``GtgenConfig`` (nested models walked; the cameras'
    topics under ``topics.cameras.<camera>``), in the order of ``configs/default.yaml``."""
    from gtgen.config import GtgenConfig

    keys: list[Key] = []

    def walk(model: BaseModel, prefix: str) -> None:
        for name, field in type(model).model_fields.items():
            value = getattr(model, name)
            if isinstance(value, BaseModel):
                walk(value, f"{prefix}{name}.")
            elif isinstance(value, dict) and value and all(isinstance(v, BaseModel) for v in value.values()):
                for k, sub in value.items():
                    walk(sub, f"{prefix}{name}.{k}.")
            else:
                keys.append(_key(prefix + name, field, value))

    walk(GtgenConfig(), "")
    return keys


def _key(name: str, field: FieldInfo, value: Any) -> Key:
    meaning = field.description or ""
    numeric = isinstance(value, (int, float, tuple)) and not isinstance(value, bool) or field.annotation in (float | None, int | None)
    return Key(name, _type_text(field.annotation), _unit(name, meaning) if numeric else "-", _default_text(value), _range_text(field), meaning)


def _type_text(ann: Any) -> str:
    """Return a type as YAML users read it: ``float``, ``str | null``, ``list[str]`` (a Literal's choices are its range)."""
    origin, args = typing.get_origin(ann), typing.get_args(ann)
    if origin is Literal:
        return " \\| ".join(dict.fromkeys(type(a).__name__ for a in args))
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(_type_text(a) for a in args)
    if ann is type(None):
        return "null"
    if origin is not None:
        return f"{origin.__name__}[{', '.join(_type_text(a) for a in args)}]"
    return getattr(ann, "__name__", str(ann))


def _unit(name: str, meaning: str) -> str:
    """Return the unit a key's description states (its first ``[...]`` that names one), else
    the one its name ends in (``_m``, ``_s``...), else ``-``."""
    import re

    for m in re.finditer(r"\[([^\]]{1,16})\]", meaning):
        text = m.group(1)
        if re.fullmatch(r"[a-zA-Z/^0-9]+", text):
            return text
    for suffix, unit in UNIT_SUFFIXES.items():
        if name.endswith(suffix):
            return unit
    return "-"


def _default_text(value: Any) -> str:
    if value is None:
        return "`null`"
    if isinstance(value, tuple):
        value = list(value)
    dumped = yaml.safe_dump(value, default_flow_style=True, width=1000).strip()
    return f"`{dumped.removesuffix('...').strip()}`"


def _range_text(field: FieldInfo) -> str:
    """Return what values the key takes: the bounds of its Field (``ge``, ``gt``, ``le``,
    ``lt``), the choices of a Literal, ``true / false``, and whether null is allowed."""
    ann = field.annotation
    args = typing.get_args(ann)
    nullable = type(None) in args
    inner = [a for a in args if a is not type(None)] if nullable else [ann]
    parts = []
    for a in inner:
        if typing.get_origin(a) is Literal:
            parts.append(", ".join(f"`{v}`" for v in typing.get_args(a)))
        elif a is bool:
            parts.append("`true`, `false`")
    lo = hi = ""
    for c in field.metadata:
        if isinstance(c, annotated_types.Ge):
            lo = f"{_num(c.ge)} <="
        elif isinstance(c, annotated_types.Gt):
            lo = f"{_num(c.gt)} <"
        elif isinstance(c, annotated_types.Le):
            hi = f"<= {_num(c.le)}"
        elif isinstance(c, annotated_types.Lt):
            hi = f"< {_num(c.lt)}"
    if lo or hi:
        parts.append(" ".join(p for p in (lo, "x", hi) if p))
    if nullable:
        parts.append("or `null`")
    return " ".join(parts) or "any"


def _num(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def config_reference() -> str:
    """Return the config reference page: one table per section of ``GtgenConfig``."""
    from gtgen.config import EASY_WORLD, GtgenConfig
    from gtgen.train.presets import PRESETS

    keys = config_keys()
    out = [
        "# Config reference",
        "",
        "Every key a `--config FILE` may set, generated from the settings models in `gtgen/config/` at each "
        "build of this site. A config file is a partial YAML over these defaults (`configs/default.yaml` lists "
        "them with the same descriptions); a misspelt key is refused with the nearest valid one, and so is a "
        "value outside its range, `inf` or `nan`. Write a key `a.b.c` as nested YAML:",
        "",
        "```yaml",
        "fuse:",
        "  window_s: 60",
        "```",
        "",
        "Range: `0 < x` means greater than 0, `x <= 1` at most 1; `any` means any value of the type.",
        "",
    ]
    for section, field in GtgenConfig.model_fields.items():
        model = typing.get_args(field.annotation)[0] if typing.get_args(field.annotation) else field.annotation
        doc = (model.__doc__ or "").strip().replace("\n", " ")
        out += [f"## {section}", "", " ".join(doc.split()), ""]
        out += ["| key | type | unit | default | range | meaning |", "|---|---|---|---|---|---|"]
        out += [f"| `{k.name}` | {k.type} | {_cell(k.unit)} | {_cell(k.default)} | {_cell(k.range)} | {_cell(k.meaning)} |"
                for k in keys if k.name.split(".")[0] == section]
        out.append("")
        if section == "synth":
            out += ["`synth.world: easy` gives these keys the easy world's value where the config does not set them "
                    "(`gtgen.config.EASY_WORLD`):", "", "| key | easy world |", "|---|---|"]
            out += [f"| `synth.{k}` | {_cell(_default_text(v))} |" for k, v in EASY_WORLD.items()]
            out.append("")
        if section == "train":
            out += ["`gtgen train --preset NAME` (default `tiny`) lays these values over `train` before `--config` "
                    "(`gtgen/train/presets.py`, mirrored in `configs/presets/`):", ""]
            names = list(PRESETS)
            preset_keys = list(dict.fromkeys(k for p in PRESETS.values() for k in p.train))
            out += ["| key | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
            out += [f"| `train.{k}` | " + " | ".join(_cell(_default_text(PRESETS[n].train[k])) if k in PRESETS[n].train else "-" for n in names) + " |"
                    for k in preset_keys]
            out += ["", "(-: the preset leaves the key at its default, above.)", ""]
    return "\n".join(out)


# ---- the command line ------------------------------------------------------------------

def cli_commands() -> list[tuple[str, Any]]:
    """Return (``gtgen export geotiff``-style name, click command) of every command and
    command group of the CLI, in the order of ``gtgen --help``."""
    import typer

    from gtgen.cli import app

    out: list[tuple[str, Any]] = []

    def walk(name: str, cmd: Any) -> None:
        out.append((name, cmd))
        for sub_name, sub in getattr(cmd, "commands", {}).items():  # a group (typer's own click)
            walk(f"{name} {sub_name}", sub)

    walk("gtgen", typer.main.get_command(app))
    return out


def command_help(name: str) -> str:
    """Return ``name --help`` as the CLI prints it at HELP_COLUMNS columns, without colour."""
    from typer.testing import CliRunner

    from gtgen.cli import app

    args = [*name.split()[1:], "--help"]
    res = CliRunner().invoke(app, args, prog_name="gtgen", env={"COLUMNS": str(HELP_COLUMNS), "TERMINAL_WIDTH": str(HELP_COLUMNS), "NO_COLOR": "1"})
    if res.exit_code != 0:
        raise RuntimeError(f"'{name} --help' exited {res.exit_code}: {res.output[-500:]}")
    return "\n".join(line.rstrip() for line in res.output.splitlines()).strip("\n")


def cli_reference() -> str:
    """Return the CLI reference page: a table of the commands, then each one's help."""
    commands = cli_commands()
    out = [
        "# CLI reference",
        "",
        "Every command's `--help`, as it prints, generated from the typer app in `gtgen/cli/` at each build of "
        "this site. Every command exits 0 on success and prints a one-line `error: ...` otherwise (a usage error "
        "prints the usage line and the error and exits 2).",
        "",
        "| command | what it does |",
        "|---|---|",
    ]
    for name, cmd in commands[1:]:
        first = " ".join((cmd.help or "").strip().split("\n\n")[0].split())
        out.append(f"| [`{name}`](#{_anchor(name)}) | {_cell(first)} |")
    out.append("")
    for name, _ in commands:
        out += [f"## {name}", "", "```text", command_help(name), "```", ""]
    return "\n".join(out)


def _anchor(heading: str) -> str:
    """Return the id MkDocs' toc gives a heading of plain words."""
    return "-".join(heading.lower().split())


# ---- the MkDocs hook ---------------------------------------------------------------------

PAGES = {"reference/cli.md": cli_reference, "reference/config.md": config_reference}


def on_files(files: Any, config: Any) -> Any:
    """Add the generated reference pages to the site."""
    from mkdocs.structure.files import File

    for path, make in PAGES.items():
        files.append(File.generated(config, path, content=make()))
    return files


if __name__ == "__main__":
    sys.stdout.write(PAGES[f"reference/{sys.argv[1]}.md"]() + "\n")
