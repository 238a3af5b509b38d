"""Rewrite the files generated from code: the tables of data_schema.md (the arrays and the
store versions from the formats in gtgen/storage/schema.py, the dataset's attributes from
its models there, the codes from gtgen/codes.py), configs/default.yaml (from gtgen.config)
and configs/presets/ (from gtgen.train.presets)."""

from __future__ import annotations

import re
import sys
import typing
from pathlib import Path

from pydantic import BaseModel

from gtgen import codes
from gtgen.config import PrecisionConfig
from gtgen.storage.packing import fill_of
from gtgen.storage.schema import DATASET, DRIVE, FORMATS, FUSED, READ_BY, DatasetAttrs, qa_paths
from gtgen.storage.specs import markdown_table


def codes_table() -> str:
    """Return every stored code (reasons, regions, splits) as a markdown table."""
    rows = ["| kind | code | name | meaning |", "|---|---|---|---|"]
    for kind, table in (("reason", codes.REASONS), ("region", codes.REGIONS), ("split", codes.SPLITS)):
        for code, text in table.items():
            name, _, meaning = text.partition(": ")
            rows.append(f"| {kind} | {code} | `{name}` | {meaning or '-'} |")
    return "\n".join(rows)


def attribute_rows(model: type[BaseModel], prefix: str = "") -> list[tuple[str, str, str]]:
    """Return (name, type, meaning) of every field of ``model``, and of the models it
    holds in lists (``drives[i].name``), as the attribute names a reader writes."""
    rows = []
    for name, f in model.model_fields.items():
        ann = f.annotation
        inner = typing.get_args(ann)[0] if typing.get_origin(ann) is list else None
        held = inner if isinstance(inner, type) and issubclass(inner, BaseModel) else None
        shown = f"list of {held.__name__}" if held else _type_name(ann)
        meaning = f.description or (f"`{f.default}`" if f.default is not None and not f.is_required() and f.default_factory is None else "-")
        rows.append((prefix + name, shown, meaning))
        if held is not None:
            rows += attribute_rows(held, f"{prefix}{name}[{'ij'[prefix.count('[')]}].")
    return rows


def _type_name(ann: object) -> str:
    return ann.__name__ if isinstance(ann, type) else str(ann).replace("typing.", "")


def _cell(text: str) -> str:
    return text.replace("|", r"\|")  # a bare | ends a markdown table cell


def attributes_table() -> str:
    """Return the dataset's attributes (``DatasetAttrs``) as a markdown table."""
    rows = ["| attribute | type | meaning |", "|---|---|---|"]
    rows += [f"| `{n}` | {_cell(t)} | {_cell(m)} |" for n, t, m in attribute_rows(DatasetAttrs)]
    return "\n".join(rows)


def packing_table() -> str:
    """Return the dataset's packed arrays: stored dtype, step (its ``shards.precision`` key
    and default), NaN's stored value, whether it is a QA grid, and what reads it."""
    rows = ["| array | stored | step (default) | NaN stored as | kept | read by |", "|---|---|---|---|---|---|"]
    qa = set(qa_paths())
    for s in DATASET.arrays:
        if not s.packed:
            continue
        step = PrecisionConfig.model_fields[s.packed].default
        generic = s.path.replace("/micro/", "/{r}/").replace("/short/", "/{r}/")
        kept = "only for shards.qa_ranges" if s.path in qa else "always"
        rows.append(f"| `{s.path}` | {s.dtype} | `shards.precision.{s.packed}` ({step:g}) | {fill_of(s.dtype)} | {kept} | {READ_BY[generic]} |")
    return "\n".join(rows)


BLOCKS = {
    "packing": packing_table,
    "drive": lambda: markdown_table(list(DRIVE.arrays)),
    "fused": lambda: markdown_table(list(FUSED.arrays)),
    "dataset": lambda: markdown_table(list(DATASET.arrays)),
    "codes": codes_table,
    "dataset-attrs": attributes_table,
}


def render(text: str) -> str:
    """Return ``text`` with every generated block and every store heading's version
    replaced by the code's."""
    for name, make in BLOCKS.items():
        pat = re.compile(rf"(<!-- BEGIN {name} -->\n)(?:.*?\n)?(<!-- END {name} -->)", re.S)
        text = pat.sub(lambda m, make=make: m.group(1) + make() + "\n" + m.group(2), text)
    return re.sub(r'(attribute `store = "([\w-]+)"`, `version = )\d+',
                  lambda m: m.group(1) + str(FORMATS[m.group(2)].version), text)


def write_configs(root: Path) -> None:
    """Write configs/default.yaml and configs/presets/*.yaml from the code."""
    from gtgen.config import default_yaml
    from gtgen.train.presets import PRESETS, preset_yaml

    (root / "configs" / "default.yaml").write_text(default_yaml().strip() + "\n")
    for name in PRESETS:
        (root / "configs" / "presets" / f"{name}.yaml").write_text(preset_yaml(name))


if __name__ == "__main__":
    root = Path(__file__).resolve().parent.parent
    doc = root / "data_schema.md"
    if "--check" not in sys.argv:
        write_configs(root)
    new = render(doc.read_text())
    if "--check" in sys.argv:
        sys.exit(0 if new == doc.read_text() else 1)
    doc.write_text(new)
