"""Rewrite the generated tables of data_schema.md from the code's ArraySpec lists."""

from __future__ import annotations

import re
import sys
from pathlib import Path

from gtgen.bag.store import DRIVE_ARRAYS
from gtgen.format import markdown_table
from gtgen.fuse.store import FUSED_ARRAYS
from gtgen.shards.schema import DATASET_ARRAYS

TABLES = {"drive": DRIVE_ARRAYS, "fused": FUSED_ARRAYS, "dataset": DATASET_ARRAYS}


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
