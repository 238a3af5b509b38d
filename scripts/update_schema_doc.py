"""Rewrite the files generated from code: the tables of data_schema.md (from the formats in
gtgen/storage/schema.py), configs/default.yaml (from gtgen.config) and configs/presets/
(from gtgen.train.presets)."""

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
        text = pat.sub(lambda m, specs=specs: m.group(1) + markdown_table(specs) + "\n" + m.group(2), text)
    return text


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
