"""Array specifications: the one way gtgen declares an on-disk array.

Each store layout (drive store in ``gtgen/bag/store.py``, dataset in
``gtgen/shards/schema.py``) is a list of :class:`ArraySpec`; ``data_schema.md``
mirrors those lists and a test checks that they agree.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class ArraySpec:
    """One array: path in the store, dtype, shape (symbols), units, frame, fill, meaning."""

    path: str
    dtype: str
    shape: str
    units: str
    frame: str
    fill: str
    doc: str

    def fill_value(self) -> object:
        """Return the fill value as a Python object for zarr."""
        if self.fill == "NaN":
            return float("nan")
        if self.fill in ("-", ""):
            return 0
        return np.dtype(self.dtype).type(float(self.fill) if "float" in self.dtype else int(self.fill)).item()


def find(specs: list[ArraySpec], path: str) -> ArraySpec:
    """Return the spec of array ``path`` in ``specs``."""
    for s in specs:
        if s.path == path:
            return s
    raise KeyError(path)


def markdown_table(specs: list[ArraySpec]) -> str:
    """Return ``specs`` as the markdown table used in data_schema.md."""
    rows = ["| array | dtype | shape | units | frame | fill | meaning |", "|---|---|---|---|---|---|---|"]
    rows += [f"| `{s.path}` | {s.dtype} | {s.shape} | {s.units} | {s.frame} | {s.fill} | {s.doc} |" for s in specs]
    return "\n".join(rows)


def dimension_names(spec: ArraySpec) -> list[str]:
    """Return xarray-friendly dimension names of ``spec`` (from its shape symbols)."""
    leaf = spec.path.rsplit("/", 1)[-1]
    named = {"S": "sample", "R": "rejected", "P": "point", "H": "row", "W": "col", "S + 1": "sample_edge"}
    out: list[str] = []
    grid_axes = iter(("x", "y"))
    for i, sym in enumerate(s.strip() for s in spec.shape.strip("()").split(",") if s.strip()):
        if sym in named:
            out.append(named[sym])
        elif sym.startswith("n_") or sym in ("n", "nx", "ny"):
            out.append(next(grid_axes))
        else:
            out.append(f"{leaf}_{i}")
    return out


def compressors() -> list:
    """Return the codec of every gtgen array: zstd level 1 (about 2x faster to write than
    zarr's default level, same size on elevation maps; measured in bench/extract.py)."""
    from zarr.codecs import ZstdCodec

    return [ZstdCodec(level=1)]


class RowAppender:
    """Appends rows to a 2-D zarr array in whole chunks along axis 0.

    ``zarr.Array.append`` per small batch resizes the array and rewrites a partly filled
    chunk every time; this buffers rows and writes only whole chunks, doubling the
    capacity when needed, and ``close`` writes the rest and trims the array.
    """

    def __init__(self, arr) -> None:
        self.arr = arr
        self.chunk = int(arr.chunks[0])
        self.buf: list = []
        self.buffered = 0
        self.written = 0

    def append(self, rows) -> None:
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
    per-call overhead is paid once per run instead of once per chunk. ``submit(fn,
    *args)`` runs each gathered write (for example on a thread pool); by default here."""

    LIMIT = 8  # indices per call

    def __init__(self, submit=None) -> None:
        self.submit = submit or (lambda fn, *args: fn(*args))
        self.runs: dict[tuple, tuple[object, int, list]] = {}

    def __enter__(self) -> Runs:
        return self

    def put(self, arr, index: int, value, rest: tuple = ()) -> None:
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


# -- whole encoded chunks, written and moved as files ---------------------------------
# A chunk of a (non-sharded) gtgen array is the zstd frame (``compressors()``) of its
# C-order little-endian bytes, in the file ``<array>/c/<i>/<j>/...`` (or ``c.<i>.<j>``
# with '.' keys) of a local store. Writing such files directly skips zarr's per-call
# overhead and the copy that gathers values into one write; a chunk's bytes do not depend
# on the array's shape, so a file written ahead can be moved into any array of the same
# dtype and codecs.
def encode_chunk(value: np.ndarray) -> bytes:
    """Return the encoded bytes of one whole chunk holding ``value``, as zarr writes them
    for an array with ``compressors()``."""
    from numcodecs import Zstd

    (codec,) = compressors()
    v = np.ascontiguousarray(value)
    if v.dtype.byteorder == ">":
        v = v.astype(v.dtype.newbyteorder("<"))
    return Zstd(level=codec.level, checksum=codec.checksum).encode(v)


def encodes_like_gtgen(codecs: list[dict], dtype) -> bool:
    """Whether a zarr v3 codec list (as in ``metadata.to_dict()``) stores chunks exactly
    as :func:`encode_chunk` makes them."""
    (codec,) = compressors()
    want = [{"name": "bytes", "configuration": {"endian": "little"}},
            {"name": "zstd", "configuration": {"level": codec.level, "checksum": codec.checksum}}]
    got = [{"name": c.get("name"), "configuration": c.get("configuration", {})} for c in codecs]
    if np.dtype(dtype).itemsize == 1:  # single bytes have no endianness
        got = [c if c["name"] != "bytes" else want[0] for c in got]
    return got == want


def check_encoded_chunks(arr) -> str:
    """Return the chunk-key separator of zarr array ``arr``; raise ValueError unless it
    stores chunks as :func:`encode_chunk` makes them, under default chunk keys."""
    md = arr.metadata.to_dict()
    enc = md.get("chunk_key_encoding", {})
    sep = enc.get("configuration", {}).get("separator", "/")
    codecs = md.get("codecs", [])
    if not encodes_like_gtgen(codecs, arr.dtype) or enc.get("name") != "default" or sep not in "/.":
        raise ValueError(f"array '{arr.path}' does not store chunks as gtgen encodes them: codecs {codecs}, keys {enc}")
    return sep


def chunk_file(store: Path, path: str, coords: tuple[int, ...], sep: str = "/") -> Path:
    """Return the file of chunk ``coords`` of array ``path`` in a local zarr v3 store
    whose default chunk keys use ``sep``."""
    return store.joinpath(path, *sep.join(["c", *map(str, coords)]).split("/"))


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


def is_fill(value: np.ndarray, fill) -> bool:
    """Return True if every element of ``value`` equals ``fill`` (NaN equals NaN): a chunk
    zarr does not store (``write_empty_chunks`` off)."""
    f = np.asarray(fill, value.dtype)
    if f.dtype.kind == "f" and np.isnan(f):
        return bool(np.isnan(value).all())
    return bool((value == f).all())


def encode_row(value: np.ndarray, dtype, row_shape: tuple[int, ...], fill) -> bytes | None:
    """Return the encoded chunk holding one row ``value`` of an array of ``dtype`` and
    ``fill`` whose chunks are single rows of ``row_shape``; None where it is all fill
    (zarr stores no such chunk)."""
    v = np.asarray(value, dtype).reshape(1, *row_shape)
    return None if is_fill(v, fill) else encode_chunk(v)


@dataclass(frozen=True)
class Encoded:
    """One chunk as stored (``encode_chunk`` bytes, None where the chunk is all fill),
    with what decoding it needs; moves between stores of the same layout as bytes."""

    data: bytes | None
    dtype: np.dtype
    shape: tuple[int, ...]
    fill: object

    def decode(self) -> np.ndarray:
        if self.data is None:
            return np.full(self.shape, self.fill, self.dtype)
        from numcodecs import Zstd

        return Zstd().decode(self.data, out=np.empty(self.shape, self.dtype.newbyteorder("<"))).astype(self.dtype, copy=False)

    def same_layout(self, dtype, fill) -> bool:
        """Whether these bytes are a valid chunk of an array of ``dtype`` and ``fill``."""
        a, b = np.asarray(self.fill, self.dtype), np.asarray(fill, dtype)
        return np.dtype(dtype) == self.dtype and bool(a == b or (a.dtype.kind == "f" and np.isnan(a) and np.isnan(b)))


class ChunkFiles:
    """The rows (index along axis 0) of a gtgen array whose chunks hold one whole row each,
    read and written as chunk files of a local store, skipping zarr's per-call cost
    (per 1 MB float32 grid: read 0.9 vs 1.6 ms, write 1.5 vs 4.0 ms, one thread each).

    Arrays of any other layout or store go through zarr, with the same values.
    """

    def __init__(self, arr) -> None:
        self.arr = arr
        self.row_shape = tuple(int(n) for n in arr.shape[1:])
        self.dtype = np.dtype(arr.dtype)
        self.fill = arr.fill_value
        self.sep: str | None = None
        root = getattr(arr.store, "root", None)
        if root is not None and tuple(arr.chunks) == (1, *self.row_shape):
            try:
                self.sep = check_encoded_chunks(arr)
            except ValueError:
                pass
        self.root = Path(root) if root is not None else None
        self._made: set[Path] = set()

    @property
    def direct(self) -> bool:
        return self.sep is not None

    def _file(self, k: int) -> Path:
        return chunk_file(self.root, self.arr.path, (int(k),) + (0,) * len(self.row_shape), self.sep)

    def encoded(self, k: int) -> Encoded | np.ndarray:
        """Return row ``k`` as stored (Encoded), or its values where the layout is not direct."""
        if not self.direct:
            return self.arr[int(k)]
        try:
            data = self._file(k).read_bytes()
        except FileNotFoundError:
            data = None
        return Encoded(data, self.dtype, (1, *self.row_shape), self.fill)

    def read(self, k: int) -> np.ndarray:
        """Return row ``k`` (a new, writable array); StoreError if its file is damaged."""
        e = self.encoded(k)
        if not isinstance(e, Encoded):
            return e
        try:
            return e.decode()[0]
        except Exception as err:  # noqa: BLE001 - zstd and numpy raise several kinds
            from gtgen.errors import StoreError

            raise StoreError(f"chunk file '{self._file(k)}' of array '{self.arr.path}' cannot be decoded ({err}); "
                             "the store is damaged: re-run the stage that wrote it") from err

    def write(self, k: int, value: np.ndarray) -> None:
        """Write row ``k`` (no file where it is all fill, as zarr does)."""
        if not self.direct:
            self.arr[int(k)] = value
            return
        data = encode_row(value, self.dtype, self.row_shape, self.fill)
        file = self._file(k)
        if data is None:
            file.unlink(missing_ok=True)
            return
        make_parent(file, self._made)
        file.write_bytes(data)
