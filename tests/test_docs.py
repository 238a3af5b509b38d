"""The README's promises that code can check: its Python block runs as written."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def readme_python_block() -> str:
    """Return the ```python block under "From Python, for your own training code"."""
    text = (ROOT / "README.md").read_text()
    m = re.search(r"From Python, for your own training code:\s*\n```python\n(.*?)```", text, re.S)
    assert m, "README.md has no python block under 'From Python, for your own training code'"
    return m.group(1)


def test_readme_python_block_runs_as_written(dataset, tmp_path):
    """In a fresh interpreter, on the test dataset in place of gtgen_ws/dataset.zarr."""
    code = readme_python_block()
    assert code.count('"gtgen_ws/dataset.zarr"') == 1
    code = code.replace('"gtgen_ws/dataset.zarr"', repr(str(dataset)))
    p = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
