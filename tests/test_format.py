"""Chunks and shards written and read as files equal what zarr writes and reads (the oracle)."""

import numpy as np
import pytest
import zarr

from gtgen.storage import schema as sc
from gtgen.storage.chunks import ChunkFiles, Encoded, check_encoded_chunks, chunk_file
from gtgen.storage.codecs import compressors, encode_chunk
from gtgen.storage.dataset_writer import ShardWriter, write_block
from gtgen.storage.packing import packing_of
from gtgen.storage.specs import row_shape


def _rows(rng, n=5):
    v = rng.normal(size=(n, 6, 7)).astype(np.float32)
    v[1] = np.nan  # a row zarr does not store
    v[2, :3] = np.nan
    return v


def test_encoded_chunks_are_the_bytes_zarr_writes(tmp_path):
    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    v = np.random.default_rng(0).normal(size=(2, 5, 7)).astype(np.float32)
    for sep in "/.":
        a = root.create_array(f"a{sep == '.'}", shape=v.shape, dtype="float32", chunks=(1, 5, 7), compressors=compressors(),
                              chunk_key_encoding={"name": "default", "separator": sep})
        a[:] = v
        assert check_encoded_chunks(a) == (sep, "zstd")
        assert chunk_file(tmp_path / "s.zarr", a.path, (1, 0, 0), sep).read_bytes() == encode_chunk(v[1])
    other = root.create_array("b", shape=v.shape, dtype="float32", chunks=(1, 5, 7))  # zarr's default codecs
    with pytest.raises(ValueError, match="does not store chunks"):
        check_encoded_chunks(other)


def _chunk_files(array_dir):
    return sorted(p.relative_to(array_dir) for p in array_dir.rglob("*") if p.is_file() and p.name != "zarr.json")


@pytest.mark.parametrize("sep", "/.")
def test_chunk_files_equal_zarr(tmp_path, sep):
    rng = np.random.default_rng(0)
    v = _rows(rng)
    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    kw = {"shape": v.shape, "dtype": "float32", "chunks": (1, 6, 7), "fill_value": np.nan, "compressors": compressors(),
          "chunk_key_encoding": {"name": "default", "separator": sep}}
    ours, theirs = ChunkFiles(root.create_array("ours", **kw)), root.create_array("theirs", **kw)
    assert ours.direct
    for k in range(len(v)):
        ours.write(k, v[k])
    theirs[:] = v
    a = zarr.open_group(str(tmp_path / "s.zarr"), mode="r")
    np.testing.assert_array_equal(a["ours"][:], v)
    files = _chunk_files(tmp_path / "s.zarr" / "ours")
    assert files == _chunk_files(tmp_path / "s.zarr" / "theirs")
    for f in files:  # byte for byte, and no file for the all-NaN row
        assert (tmp_path / "s.zarr" / "ours" / f).read_bytes() == (tmp_path / "s.zarr" / "theirs" / f).read_bytes()
    assert len(files) == len(v) - 1
    back = ChunkFiles(a["theirs"])
    for k in range(len(v)):
        r = back.read(k)
        np.testing.assert_array_equal(r, v[k])
        r += 1  # a new, writable array
    ours.write(0, np.full((6, 7), np.nan, np.float32))  # a row overwritten with fill loses its file
    np.testing.assert_array_equal(zarr.open_group(str(tmp_path / "s.zarr"), mode="r")["ours"][0], np.full((6, 7), np.nan))


def test_damaged_chunk_file_is_a_store_error(tmp_path):
    from gtgen.errors import StoreError

    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    f = ChunkFiles(root.create_array("a", shape=(2, 6, 7), dtype="float32", chunks=(1, 6, 7), fill_value=np.nan, compressors=compressors()))
    f.write(1, np.ones((6, 7), np.float32))
    f._file(1).write_bytes(f._file(1).read_bytes()[:-5])
    with pytest.raises(StoreError, match="cannot be decoded.*re-run"):
        f.read(1)


def test_chunk_files_fall_back_to_zarr_for_other_layouts(tmp_path):
    v = _rows(np.random.default_rng(1))
    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    for name, kw in {"default_codecs": {"chunks": (1, 6, 7)}, "two_rows": {"chunks": (2, 6, 7), "compressors": compressors()},
                     "part_rows": {"chunks": (1, 3, 7), "compressors": compressors()}}.items():
        f = ChunkFiles(root.create_array(name, shape=v.shape, dtype="float32", fill_value=np.nan, **kw))
        assert not f.direct
        for k in range(len(v)):
            f.write(k, v[k])
        np.testing.assert_array_equal(np.stack([f.read(k) for k in range(len(v))]), v)
        assert not isinstance(f.encoded(0), Encoded)


class _Flat(dict):
    """A sample as write_block takes it, given by array path."""

    def arrays(self) -> dict:
        return self


def _block(rng, S, micro, short, nb, src):
    """Samples of random values; the fused-like arrays as Encoded chunks of ``src``."""
    out = []
    for k in range(S):
        s = _Flat()
        for spec in sc.SAMPLE_ARRAYS + sc.CAMERA_ARRAYS:
            shape = row_shape(spec, {"n_m": micro, "n_s": short, "C": 4, "B": nb})
            dt = np.dtype(spec.dtype)
            if spec.packed:  # floats, packed by write_block
                v = (rng.uniform(0, 1, shape) if dt.kind == "u" else rng.normal(size=shape)).astype(np.float32)
            else:
                v = (rng.integers(0, 4, shape) if dt.kind == "u" else rng.integers(1, 4, shape) if dt.kind == "i"
                     else rng.normal(size=shape)).astype(dt)
            if spec.path == "labels/micro/risk" and k == 2:
                v[:] = np.nan  # all fill: no inner chunk
            s[spec.path] = v
        for path in ("labels/micro/risk", "xracer/short/confidence"):
            src[path][k] = s[path]
            s[path] = ChunkFiles(src[path]).encoded(k)
        count = rng.integers(1, 9, (1, micro, micro)).astype(np.uint8)  # another dtype: decoded and encoded anew
        s["labels/micro/count"] = Encoded(encode_chunk(count), np.dtype("uint8"), count.shape, 0)
        out.append(s)
    return out


def test_write_block_equals_zarr_writes(tmp_path):
    """Shards assembled from values and encoded chunks hold what zarr writes, byte for byte."""
    micro, short, nb, S = 12, 8, 72, 5  # a partial shard; nb: bytes of a JPEG row
    rng = np.random.default_rng(2)
    src = zarr.open_group(str(tmp_path / "src.zarr"), mode="w")
    for path, n in (("labels/micro/risk", micro), ("xracer/short/confidence", short)):
        src.create_array(path, shape=(S, n, n), dtype="float32", chunks=(1, n, n), fill_value=np.nan, compressors=compressors())
    samples = _block(rng, S, micro, short, nb, src)
    for name, direct in (("ours", True), ("zarr", False)):
        ShardWriter(tmp_path / f"{name}.zarr", 2 * sc.SAMPLES_PER_SHARD, micro, short, 4, nb, qa_ranges=("micro", "short"))
        write_block(tmp_path / f"{name}.zarr", sc.SAMPLES_PER_SHARD, samples, direct=direct)
    a, b = (zarr.open_group(str(tmp_path / f"{n}.zarr"), mode="r") for n in ("ours", "zarr"))
    for path in samples[0]:
        want = np.stack([v.decode()[0] if isinstance(v, Encoded) else v for v in (s[path] for s in samples)])
        pk = packing_of(a[path].attrs, a[path].dtype)
        want = want if pk is None else pk.pack(want)
        got = a[path][sc.SAMPLES_PER_SHARD : sc.SAMPLES_PER_SHARD + S]
        np.testing.assert_array_equal(got, want.astype(got.dtype))
        np.testing.assert_array_equal(got, b[path][sc.SAMPLES_PER_SHARD : sc.SAMPLES_PER_SHARD + S])
        shard = f"c/1{'/0' * (want.ndim - 1)}"
        assert (tmp_path / "ours.zarr" / path / shard).read_bytes() == (tmp_path / "zarr.zarr" / path / shard).read_bytes(), path
    assert (a["labels/micro/risk"][sc.SAMPLES_PER_SHARD + 2] == a["labels/micro/risk"].attrs["_FillValue"]).all()
    with pytest.raises(ValueError, match="not one shard"):
        write_block(tmp_path / "ours.zarr", 3, samples)


def test_sample_reader_equals_zarr_on_every_dataset_array(dataset, tmp_path):
    import zarr

    from gtgen.storage.schema import CAMERA_ARRAYS, SAMPLE_ARRAYS
    from gtgen.storage.shards import SampleReader

    g = zarr.open_group(str(dataset), mode="r")
    S = g["meta/t_ns"].shape[0]
    fast = 0
    for spec in SAMPLE_ARRAYS + CAMERA_ARRAYS:
        path = spec.path
        if path not in g:  # a QA grid (shards.qa_ranges)
            continue
        arr = g[path]
        r = SampleReader(arr)
        fast += r.fast
        for k in sorted({0, 1, S // 2, S - 1}):
            np.testing.assert_array_equal(r[k], arr[k], err_msg=path)
    assert fast >= 10
    # another layout (unsharded): the reader falls back to zarr
    z = zarr.create_array(str(tmp_path / "plain.zarr"), shape=(3, 4), chunks=(2, 4), dtype="f4", fill_value=np.nan)
    z[:] = np.arange(12, dtype="f4").reshape(3, 4)
    r = SampleReader(z)
    assert not r.fast
    np.testing.assert_array_equal(r[2], z[2])


def test_range_reader_equals_zarr(dataset, tmp_path):
    import zarr

    from gtgen.storage.chunks import RangeReader

    g = zarr.open_group(str(dataset), mode="r")
    arr = g["inputs/voxel_points_m"]
    off = g["inputs/voxel_offsets"][:]
    r = RangeReader(arr)
    assert r.sep is not None
    c = arr.chunks[0]
    for a, b in [(off[0], off[1]), (off[-2], off[-1]), (c - 5, c + 7), (0, 0), (len(off) and int(off[-1]) - 3, int(off[-1]) + 10)]:
        np.testing.assert_array_equal(r(a, b), arr[a:b])
    z = zarr.create_array(str(tmp_path / "p.zarr"), shape=(10, 3), chunks=(4, 2), dtype="f4", fill_value=0)
    z[:] = np.arange(30, dtype="f4").reshape(10, 3)
    r = RangeReader(z)
    assert r.sep is None
    np.testing.assert_array_equal(r(3, 9), z[3:9])
