"""Rewrite the generated tables of data_schema.md from the formats in gtgen/storage/schema.py."""

from __future__ import annotations

import re
import sys
from pathlib import Path

from gtgen.storage.schema import DATASET, DRIVE, FUSED
from gtgen.storage.specs import markdown_table

TABLES = {"drive": list(DRIVE.arrays), "fused": list(FUSED.arrays), "dataset": list(DATASET.arrays)}


def render(text: str) -> str:
    """Return ``text`` with every generated table block replaced by the code's version."""
    for name, specs in TABLES.items():
        pat = re.compile(rf"(<!-- BEGIN {name} -->\n)(?:.*?\n)?(<!-- END {name} -->)", re.S)
        text = pat.sub(lambda m: m.group(1) + markdown_table(specs) + "\n" + m.group(2), text)
    return text


if __name__ == "__main__":
    doc = Path(__file__).resolve().parent.parent / "data_schema.md"
    new = render(doc.read_text())
    if "--check" in sys.argv:
        sys.exit(0 if new == doc.read_text() else 1)
    doc.write_text(new)
