"""data_schema.md mirrors the code's formats; the dataset is what the schema says."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
from pydantic import BaseModel

from gtgen import codes
from gtgen.storage import schema as sc

ROOT = Path(__file__).resolve().parents[1]


def test_data_schema_md_matches_the_code():
    spec = importlib.util.spec_from_file_location("upd", ROOT / "scripts" / "update_schema_doc.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    doc = (ROOT / "data_schema.md").read_text()
    assert mod.render(doc) == doc, "data_schema.md is stale: run python scripts/update_schema_doc.py"
    for s in sc.DATASET.arrays:
        assert f"| `{s.path}` | {s.dtype} |" in doc


def _fields(model, prefix=""):
    """Every attribute name a dataset holds, nested lists of models as ``drives[i].name``."""
    import typing

    for name, f in model.model_fields.items():
        yield prefix + name
        args = typing.get_args(f.annotation)
        if typing.get_origin(f.annotation) is list and isinstance(args[0], type) and issubclass(args[0], BaseModel):
            yield from _fields(args[0], f"{prefix}{name}[{'ij'[prefix.count('[')]}].")


def test_data_schema_md_names_every_code_attribute_and_version():
    """Every reason, region and split code, every dataset attribute (drives[i].suspect_tiles
    too) and each store's version are in data_schema.md."""
    doc = (ROOT / "data_schema.md").read_text()
    for kind, table in (("reason", codes.REASONS), ("region", codes.REGIONS), ("split", codes.SPLITS)):
        for code, text in table.items():
            assert f"| {kind} | {code} | `{text.split(':')[0]}` |" in doc, (kind, code)
    names = list(_fields(sc.DatasetAttrs))
    assert "drives[i].suspect_tiles" in names and "drives[i].bags[j].sha256" in names
    for name in names:
        assert f"| `{name}` |" in doc, name
    for f in sc.FORMATS.values():
        assert f'attribute `store = "{f.kind}"`, `version = {f.version}`' in doc, f.kind


def test_dataset_has_every_documented_array_with_its_dtype_and_chunking(dataset, cfg):
    import zarr

    g = zarr.open_group(str(dataset), mode="r")
    S = g["meta/t_ns"].shape[0]
    for s in sc.DATASET.arrays:
        if s in sc.SCAN_ARRAYS:  # only with raw scans (the session drive has none): tests/test_lidar.py checks them
            continue
        a = g[s.path]
        assert a.dtype == np.dtype(s.dtype), s.path
        if s in sc.SAMPLE_ARRAYS + sc.CAMERA_ARRAYS:
            assert a.shape[0] == S and a.chunks[0] == 1, s.path
            assert a.shards is not None and a.shards[0] == sc.SAMPLES_PER_SHARD, s.path
    assert g["labels/micro/elevation_m"].shape == (S, cfg.grids.micro.size, cfg.grids.micro.size)
    assert g["inputs/raw_elevation_m"].shape == (S, cfg.grids.short.size, cfg.grids.short.size)
    a = g.attrs.asdict()
    assert a["version"] == sc.DATASET.version and a["gtgen_version"] and a["config"]["fuse"]["window_s"] == cfg.fuse.window_s
    assert len(a["drives"][0]["bags"][0]["sha256"]) == 64


def test_dataset_opens_with_xarray(dataset):
    import xarray as xr

    from gtgen.storage.dataset import DatasetStore

    ds = xr.open_zarr(str(dataset), group="labels/micro", consolidated=False)
    assert "elevation_m" in ds and ds["elevation_m"].ndim == 3
    el = ds["elevation_m"][:3].values  # CF-decoded by xarray alone: floats in metres (NaN where unlabelled)
    assert el.dtype.kind == "f" and np.isfinite(el).any()
    np.testing.assert_allclose(el, DatasetStore(dataset).grids("labels", "micro", "elevation_m", slice(0, 3)), atol=1e-6)
    ds = xr.open_zarr(str(dataset), group="meta", consolidated=False)
    assert int(ds["t_ns"].shape[0]) > 0


def test_region_semantics_in_the_dataset(dataset):
    from gtgen.storage.dataset import DatasetStore

    ds = DatasetStore(dataset)
    for r in ("micro", "short"):
        reg = ds.grids("labels", r, "region", slice(0, 4))
        el = ds.grids("labels", r, "elevation_m", slice(0, 4))
        dem = ds.grids("dem", r, "elevation_m", slice(0, 4))
        assert np.isfinite(el[reg > 0]).all() and np.isnan(el[reg == 0]).all()
        # DEM-filled: the same heights, each within half its step (1 mm labels, 1 cm DEM grid)
        np.testing.assert_allclose(el[reg == 3], dem[reg == 3], atol=0.0055)
        cnt = ds.grids("labels", r, "count", slice(0, 4))
        assert (cnt[(reg == 1) | (reg == 2)] > 0).all()
