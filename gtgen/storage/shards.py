"""Shards of Zarr v3 ``sharding_indexed`` arrays, read and written as bytes.

Contract (the Zarr v3 sharding codec, for the per-sample arrays gtgen creates): a shard
file holds its encoded inner chunks back to back, then the index, ``n`` x (offset,
nbytes) uint64 little endian (2**64 - 1 twice for an empty chunk), then the crc32c of
the index (index codecs ``bytes`` + ``crc32c``, index at the end). gtgen's per-sample
arrays have one sample per inner chunk and ``SAMPLES_PER_SHARD`` samples per shard, so a
sample moves between stores as its chunk's bytes, and a shard of new samples is
assembled from encoded chunks (``storage/chunks.py``) without zarr's per-call cost.

Why by hand: merging a drive into a dataset copies every sample's bytes without
decoding and re-encoding them, and dem-align writes each shard once with one file write
(its fused grids pass through as bytes); through zarr, dem-align took about 1.4 times as
long. Every function first checks the layout in ``zarr.json``
(``sample_layout``); callers fall back to zarr where it differs.

Oracle: ``tests/test_format.py`` (shards written here read back through zarr and the
reverse) and ``tests/test_pipelines.py`` (a merged dataset equals its drives').
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gtgen.storage.chunks import array_json, chunk_file, chunk_key
from gtgen.storage.codecs import codec_of, encodes_like_gtgen
from gtgen.storage.packing import CF_KEYS

_EMPTY = 2**64 - 1


def sample_layout(arr: Any) -> dict | None:
    """Return what must match for byte copies of ``arr``'s samples (from its ``zarr.json``),
    or None unless it is sharded along axis 0 with one sample per inner chunk, whole rows,
    the index at the end with bytes + crc32c index codecs, and '/' chunk keys. Packed
    arrays' bytes mean the same values only at the same steps (their CF attributes)."""
    meta = array_json(arr)
    codecs = (meta or {}).get("codecs") or []
    if len(codecs) != 1 or codecs[0].get("name") != "sharding_indexed":
        return None
    conf = codecs[0]["configuration"]
    names = [c.get("name") for c in conf.get("index_codecs", [])]
    if conf.get("index_location", "end") != "end" or names != ["bytes", "crc32c"] or conf["chunk_shape"][0] != 1:
        return None
    if list(conf["chunk_shape"][1:]) != list(arr.shape[1:]):
        return None
    enc = meta.get("chunk_key_encoding", {})
    if enc.get("name") != "default" or enc.get("configuration", {}).get("separator", "/") != "/":
        return None
    attrs = meta.get("attributes", {})
    return {"dtype": meta["data_type"], "fill": str(meta["fill_value"]), "grid": meta["chunk_grid"], "codecs": codecs,
            "tail": list(arr.shape[1:]), "packing": [attrs.get(k) for k in CF_KEYS]}


def samples_per_shard(layout: dict) -> int:
    """Return the samples of one shard of a ``sample_layout``."""
    return int(layout["grid"]["configuration"]["chunk_shape"][0])


def chunks_like_gtgen(layout: dict, dtype: Any) -> bool:
    """Whether the inner chunks of a ``sample_layout`` are encoded as ``encode_chunk`` does."""
    return encodes_like_gtgen(layout["codecs"][0]["configuration"]["codecs"], dtype)


def shard_file(root: Path, path: str, k: int, ndim: int) -> Path:
    """Return the file of shard ``k`` (along axis 0) of array ``path`` with ``ndim`` axes."""
    return chunk_file(root, path, (k,) + (0,) * (ndim - 1))


def read_shard(file: Path, n: int, check: Any = None, key: str = "") -> list[memoryview | None]:
    """Return the ``n`` encoded inner chunks of a shard file (None where empty), as views
    of the file's bytes (no copy); ``check(key, bytes or None)`` judges the file read whole
    (the source store's manifest check)."""
    raw = file.read_bytes() if file.is_file() else None
    if check is not None:
        check(key, raw)
    if raw is None:
        return [None] * n
    import google_crc32c

    data = memoryview(raw)
    index = bytes(data[-(16 * n + 4):])
    if len(index) != 16 * n + 4 or google_crc32c.value(index[:-4]) != int.from_bytes(index[-4:], "little"):
        raise ValueError(f"shard '{file}' has a bad index (expected {n} inner chunks)")
    entries = np.frombuffer(index[:-4], "<u8").reshape(n, 2)
    return [None if o == _EMPTY else data[int(o) : int(o) + int(m)] for o, m in entries]


def write_shard(file: Path, chunks: list[bytes | memoryview | None]) -> None:
    """Write a shard file of encoded inner chunks (None = empty), straight from the chunks'
    buffers (no joined copy). Shards are written inside a partial store only, so the file
    is written in place."""
    import google_crc32c

    index = np.full((len(chunks), 2), _EMPTY, "<u8")
    parts, pos = [], 0
    for i, c in enumerate(chunks):
        if c is not None:
            index[i] = (pos, len(c))
            parts.append(c)
            pos += len(c)
    ib = index.tobytes()
    parts += [ib, int(google_crc32c.value(ib)).to_bytes(4, "little")]
    file.parent.mkdir(parents=True, exist_ok=True)
    with open(file, "wb") as f:  # a buffer larger than the file's own goes straight to the file
        f.writelines(parts)


def copy_samples(a: Any, src_root: Path, dst: Any, dst_root: Path, path: str, off: int, n: int, check: Any = None) -> bool:
    """Copy samples [0, n) of array ``a`` (at ``path`` in the store at ``src_root``) to
    [off, off + n) of ``dst``'s array ``path`` as encoded bytes; return False (copying
    nothing) if the two layouts differ. ``check(key, bytes or None)`` judges each source
    shard file read whole (the source store's manifest check)."""
    b = dst[path]
    layout = sample_layout(a)
    if layout is None or layout != sample_layout(b) or a.shape[0] < n or b.shape[0] < off + n:
        return False
    K = samples_per_shard(layout)
    cache: tuple[int, list] = (-1, [])
    for k in range(off // K, (off + n - 1) // K + 1):
        out = shard_file(dst_root, path, k, a.ndim)
        chunks = read_shard(out, K)
        for g in range(max(off, k * K), min(off + n, (k + 1) * K)):
            s = g - off
            if cache[0] != s // K:
                key = chunk_key(path, (s // K,) + (0,) * (a.ndim - 1))
                cache = (s // K, read_shard(shard_file(src_root, path, s // K, a.ndim), K, check, key))
            chunks[g - k * K] = cache[1][s % K]
        write_shard(out, chunks)
    return True


class SampleReader:
    """Reads one sample (row ``k``) of a per-sample array, as ``arr[k]`` would.

    With gtgen's layout (``sample_layout`` and chunks ``encode_chunk`` makes) it reads the
    shard's index once, then each sample as one seek + read + zstd decode; otherwise it
    falls back to zarr. Why: a zarr read costs milliseconds of its event loop per call,
    which was most of what ShardDataset spent per training sample (16 reads). Oracle:
    ``tests/test_format.py`` (every sample equals zarr's).
    """

    def __init__(self, arr: Any, check: Any = None, check_size: Any = None, check_index: Any = None, whole_below: int = 0) -> None:
        """``check(key, bytes or None)`` judges a shard file read whole or found missing,
        ``check_size(key)`` one read in part and ``check_index(key, index bytes)`` its index
        (the store's manifest checks: an index from another shard or write ties no inner
        chunk to its place). A shard file of at most ``whole_below`` bytes is read whole on
        every read, and judged by ``check``: small shards hold inner chunks of one size,
        whose indexes are alike."""
        self.arr = arr
        self.check, self.check_size, self.check_index, self.whole_below = check, check_size, check_index, whole_below
        layout = sample_layout(arr)
        root = getattr(arr.store, "root", None)
        self.fast = layout is not None and root is not None and chunks_like_gtgen(layout, arr.dtype)
        if self.fast:
            self.root, self.path, self.ndim = Path(root), arr.path, arr.ndim
            self.n = samples_per_shard(layout)
            self.shape, self.dtype, self.fill = tuple(arr.shape[1:]), np.dtype(arr.dtype), arr.fill_value
            self.codec = codec_of(layout["codecs"][0]["configuration"]["codecs"], arr.dtype) or "zstd"
            self._index: dict[int, np.ndarray | None] = {}  # the index entries of each large shard read so far
            self._small: set[int] = set()

    def _entries(self, index: bytes, file: Path) -> np.ndarray:
        import google_crc32c

        if len(index) != 16 * self.n + 4 or google_crc32c.value(index[:-4]) != int.from_bytes(index[-4:], "little"):
            raise ValueError(f"shard '{file}' has a bad index (expected {self.n} inner chunks)")
        return np.frombuffer(index[:-4], "<u8").reshape(self.n, 2)

    def _chunk(self, s: int, i: int) -> bytes | None:
        """Return inner chunk ``i`` of shard ``s`` as stored (None: empty)."""
        file = shard_file(self.root, self.path, s, self.ndim)
        key = chunk_key(self.path, (s,) + (0,) * (self.ndim - 1))
        if s not in self._index and s not in self._small:
            size = file.stat().st_size if file.is_file() else None
            if size is None:
                if self.check is not None:
                    self.check(key, None)
                self._index[s] = None
            elif size <= self.whole_below:
                self._small.add(s)
            else:
                if self.check_size is not None:
                    self.check_size(key)
                with open(file, "rb") as f:
                    f.seek(-(16 * self.n + 4), 2)
                    index = f.read()
                if self.check_index is not None:
                    self.check_index(key, index)
                self._index[s] = self._entries(index, file)
        if s in self._small:
            data = file.read_bytes() if file.is_file() else None
            if self.check is not None:
                self.check(key, data)
            if data is None:
                return None
            o, m = self._entries(data[-(16 * self.n + 4):], file)[i]
            return None if o == _EMPTY else data[int(o) : int(o) + int(m)]
        entries = self._index[s]
        if entries is None or entries[i, 0] == _EMPTY:
            return None
        with open(file, "rb") as f:
            f.seek(int(entries[i, 0]))
            return f.read(int(entries[i, 1]))

    def __getitem__(self, k: int) -> np.ndarray:
        if not self.fast:
            return self.arr[k]
        from gtgen.storage.chunks import Encoded

        s, i = divmod(int(k), self.n)
        return Encoded(self._chunk(s, i), self.dtype, (1, *self.shape), self.fill, self.codec).decode()[0]
