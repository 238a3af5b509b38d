"""The dataset's packed arrays (CF scale_factor / add_offset / _FillValue integers) read
back within half their step of the floats written, through gtgen, xarray and zarr-python;
NaN survives, values beyond the range are refused, and an older dataset is refused in one
line. The naive float path (the values as written) is the oracle."""

import json

import numpy as np
import pytest
import zarr

from gtgen.config import load_config
from gtgen.errors import StoreError
from gtgen.storage import schema as sc
from gtgen.storage.codecs import compressors, decode_chunk, encode_chunk
from gtgen.storage.dataset import DatasetStore
from gtgen.storage.dataset_writer import ShardWriter, write_block
from gtgen.storage.packing import Packing, PackingError, packing_for
from gtgen.storage.specs import row_shape

MICRO, SHORT, S = 12, 8, 5
STEPS = {"elevation_m": ("int32", 0.001), "fraction": ("uint16", 0.001), "time_s": ("int32", 0.001), "dem_m": ("int32", 0.01),
         "points_m": ("int32", 0.01)}


@pytest.mark.parametrize("key", sorted(STEPS))
def test_round_trip_within_half_a_step_and_nan_is_kept(key):
    dtype, step = STEPS[key]
    rng = np.random.default_rng(0)
    lo, hi = (0.0, 1.0) if dtype == "uint16" else (-300.0, 300.0)
    v = rng.uniform(lo, hi, (50, 40)).astype(np.float32)
    v[rng.random(v.shape) < 0.2] = np.nan
    pk = Packing(dtype, step)
    stored = pk.pack(v, "a")
    assert stored.dtype == np.dtype(dtype)
    assert (stored[np.isnan(v)] == pk.fill).all()
    back = pk.unpack(stored)
    np.testing.assert_array_equal(np.isnan(back), np.isnan(v))
    assert np.nanmax(np.abs(back - v)) <= step / 2 + 1e-4 * step + np.finfo(np.float32).eps * hi


def test_out_of_range_and_infinite_values_are_refused_by_name():
    pk = Packing("uint16", 0.001, setting="shards.precision.fraction")
    with pytest.raises(PackingError, match=r"array 'labels/micro/risk': value 70 .*coarsen shards.precision.fraction"):
        pk.pack(np.array([0.5, 70.0]), "labels/micro/risk")
    with pytest.raises(PackingError, match="value -0.5"):
        pk.pack(np.array([-0.5]), "x")
    with pytest.raises(PackingError, match="value inf"):
        Packing("int32", 0.001).pack(np.array([np.inf]), "x")
    assert Packing("int32", 0.001).pack(np.array([2.1e6]), "x")[0] == 2_100_000_000  # within int32 at 1 mm


@pytest.mark.parametrize(("codec", "dtype"), [("blosc", "int32"), ("lz4", "float32")])
def test_blosc_chunks_are_zarrs_bytes_and_a_changed_byte_fails(tmp_path, codec, dtype):
    """Packed arrays ("blosc") and the intermediate float grids ("lz4"): the chunk bytes
    gtgen writes by hand are zarr's, and a changed byte fails the decode."""
    from gtgen.storage.codecs import codec_of

    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    v = np.random.default_rng(1).integers(-5000, 5000, (2, 9, 7)).astype(dtype) / (1 if dtype == "int32" else 7)
    v = v.astype(dtype)
    a = root.create_array("a", shape=v.shape, dtype=dtype, chunks=(1, 9, 7), compressors=compressors(codec))
    a[:] = v
    assert codec_of([c.to_dict() for c in a.metadata.codecs], dtype) == codec
    data = (tmp_path / "s.zarr" / "a" / "c" / "1" / "0" / "0").read_bytes()
    assert data == encode_chunk(v[1:2], codec)
    np.testing.assert_array_equal(decode_chunk(data, np.dtype(dtype), (1, 9, 7), codec), v[1:2])
    bad = bytearray(data)
    bad[len(bad) // 2] ^= 1
    with pytest.raises(ValueError, match="crc32c"):
        decode_chunk(bytes(bad), np.dtype(dtype), (1, 9, 7), codec)


class _Flat(dict):
    def arrays(self) -> dict:
        return self


def _config(qa_ranges):
    return load_config(None, {"grids": {"micro": {"size": MICRO, "resolution_m": 0.2}, "short": {"size": SHORT, "resolution_m": 0.8}},
                              "shards": {"qa_ranges": qa_ranges}})


def _samples(rng):
    """S samples of float values as dem-align makes them (NaN holes), by array path."""
    out = []
    for _ in range(S):
        s = _Flat()
        for spec in sc.SAMPLE_ARRAYS:
            shape = row_shape(spec, {"n_m": MICRO, "n_s": SHORT})
            if spec.packed == "fraction":
                v = rng.uniform(0, 1, shape).astype(np.float32)
            elif spec.packed:
                v = rng.normal(0, 20, shape).astype(np.float32)
            else:
                v = rng.integers(0, 4, shape).astype(spec.dtype) if np.dtype(spec.dtype).kind in "iu" else rng.normal(size=shape).astype(spec.dtype)
            if spec.packed:
                v[rng.random(shape) < 0.1] = np.nan
            s[spec.path] = v
        out.append(s)
    return out


def _dataset(tmp_path, qa_ranges):
    """A small dataset written through ShardWriter and write_block; its samples and voxel points."""
    cfg = _config(qa_ranges)
    path = tmp_path / "ds.zarr"
    rng = np.random.default_rng(3)
    samples = _samples(rng)
    w = ShardWriter(path, S, MICRO, SHORT, 0, 0, precision=cfg.shards.precision, qa_ranges=cfg.shards.qa_ranges)
    write_block(path, 0, samples)
    points = [rng.normal(0, 30, (n, 3)).astype(np.float32) for n in (7, 0, 11, 3, 5)]
    w.add_block(points)
    attrs = sc.DatasetAttrs(gtgen_version="test", config=json.loads(cfg.model_dump_json()), drives=[], image_size=(8, 8), cameras=[])
    w.close(attrs)
    return path, samples, points, cfg


def test_gtgen_xarray_and_zarr_read_the_same_floats_within_the_step(tmp_path):
    import xarray as xr

    path, samples, points, cfg = _dataset(tmp_path, ["micro", "short"])
    ds = DatasetStore(path)
    raw = zarr.open_group(str(path), mode="r")
    checked = 0
    for spec in sc.SAMPLE_ARRAYS:
        if not spec.packed:
            continue
        step = getattr(cfg.shards.precision, spec.packed)
        want = np.stack([s[spec.path] for s in samples])
        gtgen_rows = ds.read(spec.path)
        a = raw[spec.path]
        by_zarr = np.where(a[:] == a.attrs["_FillValue"], np.nan, a[:] * a.attrs["scale_factor"] + a.attrs["add_offset"])
        group, name = spec.path.rsplit("/", 1)
        by_xarray = xr.open_zarr(str(path), group=group, consolidated=False, zarr_format=3)[name].values
        for got in (gtgen_rows, by_zarr, by_xarray):
            np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=spec.path)
            assert np.nanmax(np.abs(got - want)) <= step / 2 * 1.001 + 1e-5, spec.path
        np.testing.assert_allclose(by_xarray, gtgen_rows, atol=1e-5, equal_nan=True)
        checked += 1
    assert checked == 17  # per range: 4 label grids, 3 X-Racer grids, the DEM; and the raw min-z grid
    np.testing.assert_array_equal(ds.grid("labels", "micro", "elevation_m")[2], ds.read("labels/micro/elevation_m")[2])
    flat = ds.voxel_points()(0, sum(len(p) for p in points))
    assert np.abs(flat - np.concatenate(points)).max() <= 0.005 * 1.001
    assert raw["inputs/voxel_points_m"].dtype == np.int32


def test_qa_grids_are_left_out_by_default_and_asked_for_by_name(tmp_path):
    path, samples, _, _ = _dataset(tmp_path, [])
    ds = DatasetStore(path)
    for p in sc.qa_paths():
        assert p not in ds.group
    assert not ds.has_grid("dem", "micro", "elevation_m") and ds.has_grid("labels", "micro", "elevation_m")
    with pytest.raises(StoreError, match=r"does not store the QA grid 'labels/short/count'.*shards.qa_ranges: \[micro, short\]"):
        ds.grid("labels", "short", "count")
    want = np.stack([s["labels/short/elevation_m"] for s in samples])
    assert np.nanmax(np.abs(ds.grids("labels", "short", "elevation_m", slice(0, S)) - want)) <= 0.0005 * 1.001


def test_an_older_dataset_is_refused_in_one_line(tmp_path):
    g = zarr.open_group(str(tmp_path / "old.zarr"), mode="w")
    g.attrs.update({"store": sc.DATASET.kind, "version": sc.DATASET.version - 1, "complete": True})
    with pytest.raises(StoreError) as err:
        DatasetStore(tmp_path / "old.zarr")
    msg = str(err.value)
    assert "\n" not in msg and f"version {sc.DATASET.version - 1}" in msg and "rebuild" in msg and "shards.precision" in msg


def test_packing_follows_the_config_steps():
    cfg = load_config(None, {"shards": {"precision": {"elevation_m": 0.002}}})
    pk = packing_for(sc.DATASET.spec("labels/micro/elevation_m"), cfg.shards.precision)
    assert pk.attrs() == {"scale_factor": 0.002, "add_offset": 0.0, "_FillValue": -(2**31)}
    assert packing_for(sc.DATASET.spec("labels/micro/region"), cfg.shards.precision) is None
    with pytest.raises(Exception, match="elevation_m"):
        load_config(None, {"shards": {"precision": {"elevation_m": 0.5}}})
