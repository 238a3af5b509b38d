"""The layout's promises, read from the code: stores are opened and their arrays named in
``gtgen/storage/`` only, one process pool, one bilinear sampler."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from gtgen.storage.schema import FORMATS

ROOT = Path(__file__).resolve().parents[1]
CODE = sorted(p for d in ("gtgen", "pipelines") for p in (ROOT / d).rglob("*.py"))
OUTSIDE_STORAGE = [p for p in CODE if "storage" not in p.relative_to(ROOT).parts]


def _strings(tree: ast.AST) -> list[tuple[int, str]]:
    """Return (line, text) of every string literal that is not a docstring; an f-string's
    fields read as '{}'."""
    docs = {id(n.body[0].value) for n in ast.walk(tree) if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef))
            and n.body and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.JoinedStr):
            out.append((n.lineno, "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in n.values)))
        elif isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs:
            out.append((n.lineno, n.value))
    return out


def _array_patterns() -> list[re.Pattern]:
    """Return a pattern per array path of every store format, its range and name parts
    free to be f-string fields ('labels/{}/elevation_m' matches 'labels/micro/elevation_m')."""
    pats = set()
    for fmt in FORMATS.values():
        for s in fmt.arrays:
            parts = s.path.split("/")
            if len(parts) == 3:  # group/range/name: the range may be a field
                parts[1] = rf"(?:{re.escape(parts[1])}|\{{\}})"
                pats.add("/".join([re.escape(parts[0]), parts[1], re.escape(parts[2])]))
            else:
                pats.add(re.escape(s.path))
            if s.path.startswith("samples/map_index_"):
                pats.add(r"samples/map_index_\{\}")
    return [re.compile(rf"^{p}$") for p in pats]


def test_no_stage_spells_an_array_path_or_opens_a_zarr_group():
    pats = _array_patterns()
    assert any(p.match("labels/{}/elevation_m") for p in pats)  # the check itself sees f-strings
    found = []
    for p in OUTSIDE_STORAGE:
        src = p.read_text()
        tree = ast.parse(src)
        for line, text in _strings(tree):
            if any(pat.match(text) for pat in pats):
                found.append(f"{p.relative_to(ROOT)}:{line}: {text!r}")
        for n in ast.walk(tree):
            if isinstance(n, ast.Attribute) and n.attr in ("open_group", "open_array", "open") and \
                    isinstance(n.value, ast.Name) and n.value.id == "zarr":
                found.append(f"{p.relative_to(ROOT)}:{n.lineno}: zarr.{n.attr}")
    assert not found, "outside gtgen/storage/:\n" + "\n".join(found)


def test_one_process_pool_and_no_fork():
    offenders = [str(p.relative_to(ROOT)) for p in CODE if p.name != "pool.py" and re.search(
        r"ProcessPoolExecutor|multiprocessing\.Pool|get_context\(\s*['\"]fork|mp\.Pool\(", p.read_text())]
    assert not offenders, offenders


def test_one_bilinear_sampler():
    hits = [str(p.relative_to(ROOT)) for p in CODE if re.search(r"map_coordinates|def _?bilinear", p.read_text())]
    assert hits == ["gtgen/grids.py"], hits


def test_the_torch_cell_index_is_the_numpy_one():
    import numpy as np
    import torch

    from gtgen.grids import xy_to_index
    from gtgen.train.pillars import cell_index

    rng = np.random.default_rng(0)
    size, res = 250, 0.8
    x = rng.uniform(-110, 110, 5000)
    y = rng.uniform(-110, 110, 5000)
    x[:5] = [-100.0, 99.2, 100.0, -100.0 + 1e-9, 99.99999]  # cell borders and the grid's edges
    want = xy_to_index(x, y, size, res)
    got = cell_index(torch.from_numpy(x), torch.from_numpy(y), size, res)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a.numpy(), b)


def test_the_terrain_samples_its_tiles_with_the_one_bilinear_rule():
    import numpy as np

    from gtgen.config import SynthConfig
    from gtgen.grids import bilinear
    from gtgen.synth.terrain import TILE_RES_M, Obstacles, Terrain

    none = np.zeros(0)
    t = Terrain(SynthConfig(seed=3), Obstacles(np.zeros((0, 2)), none, none, np.zeros((0, 2)), none, none, none))
    n = 64
    g = t.eval_grid(-0.5 * TILE_RES_M, -0.5 * TILE_RES_M, TILE_RES_M, n, n)["ground"]  # cell (i, j) at (i, j) * res
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, (n - 1) * TILE_RES_M, (2, 500))
    np.testing.assert_allclose(t.sample(u, v)[0], bilinear(g, u / TILE_RES_M, v / TILE_RES_M), atol=1e-4)


def test_dataset_does_not_import_the_trainer():
    """The dataset stage comes before training: gtgen/dataset/ imports nothing of gtgen.train
    (users reach the torch view through gtgen.api, which imports it lazily)."""
    found = []
    for p in sorted((ROOT / "gtgen" / "dataset").rglob("*.py")):
        for n in ast.walk(ast.parse(p.read_text())):
            names = [a.name for a in n.names] if isinstance(n, ast.Import) else [n.module or ""] if isinstance(n, ast.ImportFrom) else []
            found += [f"{p.relative_to(ROOT)}:{n.lineno}: {m}" for m in names if m == "gtgen.train" or m.startswith("gtgen.train.")]
    assert not found, found
