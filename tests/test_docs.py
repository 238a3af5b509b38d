"""The documentation's promises that code can check: its Python block runs as written, the
generated reference holds every config key and command, and the README stays short with
links that resolve. (Links between the site's pages are checked by `make docs`, --strict.)"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

from markdown.extensions.toc import slugify

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 200


def docs_reference():
    spec = importlib.util.spec_from_file_location("docs_reference", ROOT / "scripts" / "docs_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def python_block() -> str:
    """Return the ```python block under "From Python, for your own training code" of
    docs/looking.md."""
    text = (ROOT / "docs" / "looking.md").read_text()
    m = re.search(r"From Python, for your own training code:\s*\n```python\n(.*?)```", text, re.S)
    assert m, "docs/looking.md has no python block under 'From Python, for your own training code'"
    return m.group(1)


def test_python_block_runs_as_written(dataset, tmp_path):
    """In a fresh interpreter, on the test dataset in place of gtgen_ws/dataset.zarr."""
    code = python_block()
    assert code.count('"gtgen_ws/dataset.zarr"') == 1
    code = code.replace('"gtgen_ws/dataset.zarr"', repr(str(dataset)))
    p = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]


def test_config_reference_names_every_key_with_its_default_and_range():
    from gtgen.config import GtgenConfig

    ref = docs_reference()
    page = ref.config_reference()
    rows = {line.split("|")[1].strip().strip("`"): line for line in page.splitlines() if line.startswith("| `")}
    dumped = GtgenConfig().model_dump()

    def leaves(d: dict, prefix: str = "") -> list[str]:
        return [k for name, v in d.items() for k in (leaves(v, f"{prefix}{name}.") if isinstance(v, dict) and v else [prefix + name])]

    keys = leaves(dumped)
    assert len(keys) > 150 and "fuse.window_s" in keys and "topics.cameras.left.info" in keys
    missing = [k for k in keys if k not in rows]
    assert not missing, f"keys not in the config reference: {missing}"
    assert [k.name for k in ref.config_keys()] == keys  # one row per key, in the defaults' order
    window = rows["fuse.window_s"].split("|")
    assert [c.strip() for c in window[2:6]] == ["float", "s", "`60.0`", "0 < x <= 86400"]
    assert [c.strip() for c in rows["train.risk_loss"].split("|")[5:6]] == ["`mse`, `weighted_mse`, `weighted_bce`"]
    assert "`null`" in rows["report.bad_horizontal_m"] and "0 < x or `null`" in rows["report.bad_horizontal_m"]


def test_cli_reference_holds_every_commands_help():
    ref = docs_reference()
    page = ref.cli_reference()
    names = [n for n, _ in ref.cli_commands()]
    for cmd in ("synth", "extract", "fuse", "dem-align", "build", "report", "viz", "verify", "train", "eval", "experiments", "export geotiff", "export mcap", "export onnx"):
        assert f"gtgen {cmd}" in names
        assert f"\n## gtgen {cmd}\n" in page and f"Usage: gtgen {cmd} [OPTIONS]" in page
    assert "--window" in page.split("## gtgen fuse\n")[1].split("\n## ")[0]  # each command's own options


def _anchors(page: Path) -> set[str]:
    """Return the ids of a page's headings, as MkDocs' toc (and GitHub) make them."""
    return {slugify(m.group(1), "-") for m in re.finditer(r"^#{1,6} (.*?)\s*$", page.read_text(), re.M)}


def test_readme_is_short_and_its_links_resolve():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= README_MAX_LINES
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    assert len(links) > 20
    for link in links:
        path, _, anchor = link.partition("#")
        target = ROOT / path
        assert target.is_file(), f"README links to {link}: no such file"
        if anchor:
            assert anchor in _anchors(target), f"README links to {link}: no such heading in {path}"
    # every page, and the dataset's as data_schema.md itself (docs/dataset.md only includes it)
    pages = {f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")} - {"docs/dataset.md"} | {"data_schema.md"}
    assert pages <= {link.partition("#")[0] for link in links}
