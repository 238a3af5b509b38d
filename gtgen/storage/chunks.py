"""Whole Zarr v3 chunks of gtgen's arrays, encoded, written, read and moved as files.

Contract (the Zarr v3 specification, for the arrays gtgen creates): an array's codecs
are one of ``storage/codecs.py``'s (zstd with its checksum; for packed integer arrays
blosc then crc32c), its chunk keys are the default encoding ``c<sep>i<sep>j...`` with separator '/' or '.',
and a chunk is stored as the zstd frame of its C-order little-endian bytes in that file
of a local store. A chunk whose values all equal the fill value is not stored (zarr's
``write_empty_chunks`` off); the store's manifest (``storage/integrity.py``) tells such a
chunk from a lost one, and the readers here take its ``check``.
The layout is read from the array's ``zarr.json`` and checked before any file is
touched; an array of another layout or store goes through zarr's public API instead.

Why by hand: zarr's per-call cost (its event loop) dominates gtgen's one-grid-per-chunk
arrays; a chunk file read or written here costs little more than its zstd frame (fuse and
dem-align spent nearly half their time in zarr calls before). A chunk's bytes do not
depend on the array's shape, so a chunk encoded ahead (extract's staging) can be moved
into any array of the same dtype and codecs by a rename.

Oracle: ``tests/test_format.py`` writes through these functions and reads through zarr
(and the reverse), array by array.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gtgen.errors import StoreError
from gtgen.storage.codecs import codec_of, decode_chunk, encode_chunk

Check = Callable[[str, Any], None]  # (chunk key, the file's bytes read whole, or None if absent): raises if the store is damaged


def array_json(arr: Any) -> dict | None:
    """Return the ``zarr.json`` document of ``arr`` when it lives in a local store, else None."""
    root = getattr(arr.store, "root", None)
    if root is None:
        return None
    try:
        return json.loads((Path(root) / arr.path / "zarr.json").read_text())
    except (OSError, ValueError):
        return None


def key_separator(meta: dict) -> str | None:
    """Return the default chunk-key separator of a ``zarr.json`` document, None for others."""
    enc = meta.get("chunk_key_encoding", {})
    sep = enc.get("configuration", {}).get("separator", "/")
    return sep if enc.get("name") == "default" and sep in ("/", ".") else None


def check_encoded_chunks(arr: Any) -> tuple[str, str]:
    """Return the chunk-key separator and codec of zarr array ``arr``; raise ValueError
    unless it stores chunks as :func:`encode_chunk` makes them, in a local store."""
    meta = array_json(arr)
    sep = key_separator(meta) if meta else None
    codec = codec_of(meta.get("codecs", []), arr.dtype) if meta else None
    if meta is None or sep is None or codec is None:
        raise ValueError(f"array '{arr.path}' does not store chunks as gtgen encodes them: {meta and meta.get('codecs')}")
    return sep, codec


def chunk_key(path: str, coords: tuple[int, ...], sep: str = "/") -> str:
    """Return the store key of chunk ``coords`` of array ``path`` (default chunk keys, ``sep``)."""
    return f"{path}/" + sep.join(["c", *map(str, coords)])


def chunk_file(store: Path, path: str, coords: tuple[int, ...], sep: str = "/") -> Path:
    """Return the file of chunk ``coords`` of array ``path`` in a local zarr v3 store
    whose default chunk keys use ``sep``."""
    return store.joinpath(*chunk_key(path, coords, sep).split("/"))


def make_parent(file: Path, made: set[Path] | None = None) -> None:
    """Create the folder of ``file`` unless ``made`` (the folders created so far) has it."""
    parent = file.parent
    if made is None or parent not in made:
        parent.mkdir(parents=True, exist_ok=True)
        if made is not None:
            made.add(parent)


def place_chunk(src: Path, dst: Path, move: bool, made: set | None = None) -> None:
    """Make chunk file ``dst`` hold the bytes of ``src``: renamed if ``move``, else a hard
    link (a copy where links fail). ``made`` caches the folders already created."""
    make_parent(dst, made)
    if move:
        os.replace(src, dst)
        return
    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def is_fill(value: np.ndarray, fill: Any) -> bool:
    """Return True if every element of ``value`` equals ``fill`` (NaN equals NaN): a chunk
    zarr does not store."""
    f = np.asarray(fill, value.dtype)
    if f.dtype.kind == "f" and np.isnan(f):
        return bool(np.isnan(value).all())
    return bool((value == f).all())


def encode_row(value: np.ndarray, dtype: Any, row_shape: tuple[int, ...], fill: Any, codec: str = "zstd") -> bytes | None:
    """Return the encoded chunk (of ``codec``) holding one row ``value`` of an array of
    ``dtype`` and ``fill`` whose chunks are single rows of ``row_shape``; None where it is
    all fill."""
    v = np.asarray(value, dtype).reshape(1, *row_shape)
    return None if is_fill(v, fill) else encode_chunk(v, codec)


@dataclass(frozen=True)
class Encoded:
    """One chunk as stored (``encode_chunk`` bytes, None where the chunk is all fill),
    with what decoding it needs; moves between stores of the same layout as bytes."""

    data: bytes | memoryview | None
    dtype: np.dtype
    shape: tuple[int, ...]
    fill: Any
    codec: str = "zstd"

    def decode(self) -> np.ndarray:
        """Return the chunk's values."""
        if self.data is None:
            return np.full(self.shape, self.fill, self.dtype)
        return decode_chunk(self.data, self.dtype, self.shape, self.codec)

    def same_layout(self, dtype: Any, fill: Any, codec: str = "zstd") -> bool:
        """Whether these bytes are a valid chunk of an array of ``dtype``, ``fill`` and ``codec``."""
        a, b = np.asarray(self.fill, self.dtype), np.asarray(fill, dtype)
        return (np.dtype(dtype) == self.dtype and codec == self.codec
                and bool(a == b or (a.dtype.kind == "f" and np.isnan(a) and np.isnan(b))))


class ChunkFiles:
    """The rows (index along axis 0) of a gtgen array whose chunks hold one whole row each,
    read and written as chunk files of a local store, skipping zarr's per-call cost.

    Arrays of any other layout or store go through zarr, with the same values. ``check``
    (the store's manifest check) judges each chunk file read.
    """

    def __init__(self, arr: Any, check: Check | None = None) -> None:
        self.arr = arr
        self.check = check
        self.row_shape = tuple(int(n) for n in arr.shape[1:])
        self.dtype = np.dtype(arr.dtype)
        self.fill = arr.fill_value
        self.sep: str | None = None
        self.codec = "zstd"
        root = getattr(arr.store, "root", None)
        if root is not None and tuple(arr.chunks) == (1, *self.row_shape):
            try:
                self.sep, self.codec = check_encoded_chunks(arr)
            except ValueError:
                pass
        self.root = Path(root) if root is not None else None
        self._made: set[Path] = set()

    @property
    def direct(self) -> bool:
        """Whether rows are read and written as files."""
        return self.sep is not None

    def _key(self, k: int) -> str:
        return chunk_key(self.arr.path, (int(k),) + (0,) * len(self.row_shape), self.sep or "/")

    def _file(self, k: int) -> Path:
        return self.root.joinpath(*self._key(k).split("/"))

    def encoded(self, k: int) -> Encoded | np.ndarray:
        """Return row ``k`` as stored (Encoded), or its values where the layout is not direct."""
        if not self.direct:
            return self.arr[int(k)]
        try:
            data = self._file(k).read_bytes()
        except FileNotFoundError:
            data = None
        if self.check is not None:
            self.check(self._key(k), data)
        return Encoded(data, self.dtype, (1, *self.row_shape), self.fill, self.codec)

    def read(self, k: int) -> np.ndarray:
        """Return row ``k`` (a new, writable array); StoreError if its file is damaged."""
        e = self.encoded(k)
        if not isinstance(e, Encoded):
            return e
        try:
            return e.decode()[0]
        except Exception as err:  # noqa: BLE001 - zstd and numpy raise several kinds
            raise StoreError(f"chunk file '{self._file(k)}' of array '{self.arr.path}' cannot be decoded ({err}); "
                             "the store is damaged: re-run the stage that wrote it") from err

    def write(self, k: int, value: np.ndarray) -> None:
        """Write row ``k`` (no file where it is all fill, as zarr does)."""
        if not self.direct:
            self.arr[int(k)] = value
            return
        data = encode_row(value, self.dtype, self.row_shape, self.fill, self.codec)
        file = self._file(k)
        if data is None:
            file.unlink(missing_ok=True)
            return
        make_parent(file, self._made)
        file.write_bytes(data)


class RowAppender:
    """Appends rows to a 2-D zarr array in whole chunks along axis 0.

    ``zarr.Array.append`` per small batch resizes the array and rewrites a partly filled
    chunk every time; this buffers rows and writes only whole chunks, doubling the
    capacity when needed, and ``close`` writes the rest and trims the array.
    """

    def __init__(self, arr: Any) -> None:
        self.arr = arr
        self.chunk = int(arr.chunks[0])
        self.buf: list = []
        self.buffered = 0
        self.written = 0

    def append(self, rows: np.ndarray) -> None:
        """Append ``rows`` (n, ...)."""
        if len(rows):
            self.buf.append(rows)
            self.buffered += len(rows)
        if self.buffered >= self.chunk:
            self._flush(whole=True)

    def _flush(self, whole: bool) -> None:
        if not self.buffered:
            return
        allr = np.concatenate(self.buf) if len(self.buf) > 1 else self.buf[0]
        n = (len(allr) // self.chunk) * self.chunk if whole else len(allr)
        if n == 0:
            return
        if self.written + n > self.arr.shape[0]:
            self.arr.resize((max(2 * self.arr.shape[0], self.written + n), *self.arr.shape[1:]))
        self.arr[self.written : self.written + n] = allr[:n]
        self.written += n
        self.buf = [allr[n:]] if n < len(allr) else []
        self.buffered = len(allr) - n

    def close(self) -> int:
        """Write the buffered rows, trim the array to the rows appended; return their count."""
        self._flush(whole=False)
        if self.arr.shape[0] != self.written:
            self.arr.resize((self.written, *self.arr.shape[1:]))
        return self.written


class Runs:
    """Gathers writes to consecutive indices of one array into one zarr call: zarr's
    per-call cost is paid once per run instead of once per chunk. ``submit(fn, *args)``
    runs each gathered write (for example on a thread pool); by default here."""

    LIMIT = 8  # indices per call

    def __init__(self, submit: Any = None) -> None:
        self.submit = submit or (lambda fn, *args: fn(*args))
        self.runs: dict[tuple, tuple[Any, int, list]] = {}

    def __enter__(self) -> Runs:
        return self

    def put(self, arr: Any, index: int, value: np.ndarray, rest: tuple = ()) -> None:
        """Write ``value`` at ``arr[(index,) + rest]``, batched along ``index``."""
        key = (id(arr), rest)
        run = self.runs.get(key)
        if run is not None and run[1] + len(run[2]) == index and len(run[2]) < self.LIMIT:
            run[2].append(value)
            return
        if run is not None:
            self._flush(key)
        self.runs[key] = (arr, index, [value])

    def _flush(self, key: tuple) -> None:
        arr, start, values = self.runs.pop(key)
        self.submit(arr.__setitem__, (slice(start, start + len(values)),) + key[1], np.stack(values))

    def flush(self) -> None:
        """Write every gathered run."""
        for key in list(self.runs):
            self._flush(key)

    def __exit__(self, *exc: object) -> None:
        if exc[0] is None:
            self.flush()


class RangeReader:
    """Reads ``arr[a:b]`` of an array chunked along axis 0 only (whole trailing axes per
    chunk, as ``inputs/voxel_points_m``) from its chunk files, keeping the last decoded
    chunk; zarr where the layout or store differs. Why: one zarr call costs milliseconds of
    its event loop, a large part of what the loader spends on a sample."""

    def __init__(self, arr: Any, check: Check | None = None) -> None:
        self.arr = arr
        self.check = check
        self.sep: str | None = None
        self.codec = "zstd"
        root = getattr(arr.store, "root", None)
        if root is not None and tuple(arr.chunks[1:]) == tuple(arr.shape[1:]):
            try:
                self.sep, self.codec = check_encoded_chunks(arr)
            except ValueError:
                pass
        self.root = Path(root) if root is not None else None
        self.c = int(arr.chunks[0])
        self._last: tuple[int, np.ndarray] | None = None

    def _chunk(self, i: int) -> np.ndarray:
        if self._last is None or self._last[0] != i:
            key = chunk_key(self.arr.path, (i,) + (0,) * (self.arr.ndim - 1), self.sep)
            try:
                data = self.root.joinpath(*key.split("/")).read_bytes()
            except FileNotFoundError:
                data = None
            if self.check is not None:
                self.check(key, data)
            self._last = (i, Encoded(data, np.dtype(self.arr.dtype), (self.c, *self.arr.shape[1:]), self.arr.fill_value, self.codec).decode())
        return self._last[1]

    def __call__(self, a: int, b: int) -> np.ndarray:
        """Return rows ``a`` to ``b`` (exclusive)."""
        b = min(int(b), int(self.arr.shape[0]))
        if self.sep is None or b <= a:
            return self.arr[int(a):b]
        i0, i1 = int(a) // self.c, (b - 1) // self.c
        parts = [self._chunk(i) for i in range(i0, i1 + 1)]
        rows = parts[0] if len(parts) == 1 else np.concatenate(parts)
        return rows[int(a) - i0 * self.c:b - i0 * self.c].copy()
