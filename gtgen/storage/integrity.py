"""What a store holds, recorded when it is completed, and checked on every read.

Zarr reads a missing chunk as its fill value, and gtgen does not store chunks that are
all fill, so a deleted file cannot be told from "no data" by zarr alone; and a chunk's own
checksum (zstd's, or the crc32c codec's of a packed array, of every chunk and inner chunk;
the CRC32C of a shard's index) covers
its bytes, not its place, so two chunks swapped, one copied over another or one left from
an earlier write decode as data. Every gtgen store therefore records, as its last write,
a manifest of every file it holds: each chunk or shard file's size and CRC32C, the CRC32C
of each shard's index, and each metadata file's (``zarr.json``) CRC32C. The manifest is
the attributes of an empty array ``MANIFEST`` at the store's root (a member of the
hierarchy, so zarr and xarray list the store without complaint), excluded from itself.

Readers check through :class:`Manifest` what they read: a file read whole (every chunk
file, a shard read whole, and every file of at most ``SMALL_FILE`` bytes, such as the
shards of the per-sample metadata) against its size and CRC32C; a larger shard read in
part against its size and its index's CRC32C (a shard from elsewhere carries another
index: its inner chunks are of other sizes), each inner chunk by its own checksum. A chunk the manifest lists
but the store lacks, or that holds other bytes, is a :class:`DamagedStoreError` naming the
array, the rows (samples) it holds and the command that rebuilds the store; a chunk the
manifest does not list is all fill, as zarr says. ``verify`` checks a whole store: every
file's size and CRC32C, every metadata checksum, every chunk decoded; a file the store was
not written with is named, and told apart from damage when zarr never reads it (a note
beside the arrays).

Why CRC32C: google-crc32c (already a dependency; zarr's shard indexes use it) computes
it in hardware, at memory speed, so checking every chunk read whole costs little next to
its zstd decode (``bench/integrity.py``); a non-cryptographic hash suffices, since the
manifest guards against accidents (a copy, a swap, a stale file), not against an attacker
who could rewrite the manifest too.

The store's identity (``identity``) is a hash of what its manifest records of its arrays:
results computed from a store (runs, evaluations) record it and are reused only with it.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gtgen.errors import StoreError

MANIFEST = "gtgen_manifest"
MANIFEST_VERSION = 2  # 2: CRC32C of every chunk and shard file and of each shard's index
# files at most this large are read and checked whole even where a read needs part of them:
# small arrays' shards (meta/t_ns, ...) hold inner chunks of one size, so their indexes are
# alike and only the whole file's CRC32C ties them to their place; reading 64 KiB costs
# about what the index read and a seek cost
SMALL_FILE = 1 << 16
METADATA = "zarr.json"

# what the first axis of an array counts, by its shape symbol (storage/schema.py)
AXIS_NOUNS = {"S": "samples", "M_r": "maps", "V": "voxel maps", "N": "poses", "G": "fixes", "C": "candidates",
              "R": "rejected samples", "P": "points", "S + 1": "sample offsets"}


def rows_text(noun: str, a: int, b: int) -> str:
    """Return 'samples 16-31' (or 'sample 3' for one row)."""
    return f"{noun} {a}-{b}" if b > a else f"{noun.removesuffix('s')} {a}"


class DamagedStoreError(StoreError):
    """A store's data is missing or changed since it was written; ``what`` says what, without
    the store's name and the command that rebuilds it."""

    def __init__(self, message: str, what: str = "") -> None:
        super().__init__(message)
        self.what = what or message


def crc32c(data: bytes | memoryview | np.ndarray) -> int:
    """Return the CRC32C of ``data`` (any contiguous buffer; not copied)."""
    import google_crc32c

    return int(google_crc32c.value(np.frombuffer(data, np.uint8)))


def shard_index_bytes(meta: dict) -> int | None:
    """Return the length of a shard's index (at the end of the file) of an array whose
    ``zarr.json`` is ``meta``, or None unless it is sharded with the index at the end,
    encoded as bytes + crc32c (as gtgen writes them)."""
    codecs = meta.get("codecs") or []
    if len(codecs) != 1 or codecs[0].get("name") != "sharding_indexed":
        return None
    conf = codecs[0].get("configuration", {})
    names = [c.get("name") for c in conf.get("index_codecs", [])]
    if conf.get("index_location", "end") != "end" or names != ["bytes", "crc32c"]:
        return None
    outer = meta["chunk_grid"]["configuration"]["chunk_shape"]
    return 16 * int(np.prod([o // i for o, i in zip(outer, conf["chunk_shape"])])) + 4


def _files(root: Path) -> dict[str, int]:
    """Return {key: size} of every file under ``root`` (keys relative, '/'-separated)."""
    out: dict[str, int] = {}
    for dirpath, _, names in os.walk(root):
        rel = os.path.relpath(dirpath, root)
        prefix = "" if rel == "." else rel.replace(os.sep, "/") + "/"
        for name in names:
            out[prefix + name] = os.stat(os.path.join(dirpath, name)).st_size
    return out


def _store_files(root: Path) -> dict[str, int]:
    """Return {key: size} of the store's files, the manifest's own left out."""
    return {k: n for k, n in _files(root).items() if not k.startswith(MANIFEST + "/")}


def _index_sizes(root: Path, meta_keys: list[str]) -> dict[str, int]:
    """Return {array path: its shards' index length} of the sharded arrays among the
    metadata files ``meta_keys``."""
    out = {}
    for key in meta_keys:
        try:
            meta = json.loads((root / key).read_text())
            n = shard_index_bytes(meta) if meta.get("node_type") == "array" else None
        except (OSError, ValueError, KeyError, TypeError, ZeroDivisionError):
            n = None
        if n is not None and "/" in key:
            out[key.rsplit("/", 1)[0]] = n
    return out


def write_manifest(root: Path) -> None:
    """Record every file of the store at ``root`` (call it last, once the store is complete):
    sizes and CRC32C of every file, and of each shard's index."""
    import zarr

    keys = sorted(_store_files(root))
    metadata = [k for k in keys if k.rsplit("/", 1)[-1] == METADATA]
    sharded = _index_sizes(root, metadata)
    files: dict[str, list[int]] = {}
    indexes: dict[str, int] = {}
    for key in keys:
        data = (root / key).read_bytes()
        if key in metadata:
            continue
        files[key] = [len(data), crc32c(data)]
        n = next((sharded[a] for a in _arrays_of(key) if a in sharded), None)
        if n is not None and len(data) >= n:
            indexes[key] = crc32c(memoryview(data)[-n:-4])  # the entries: a CRC over bytes ending in their own CRC is a constant
    doc = {"version": MANIFEST_VERSION, "metadata": {k: crc32c((root / k).read_bytes()) for k in metadata}, "files": files,
           "indexes": indexes}
    zarr.open_group(str(root), mode="r+").create_array(MANIFEST, shape=(0,), dtype="uint8", attributes={"gtgen_manifest": doc})


def _arrays_of(key: str) -> list[str]:
    """Return the array paths a chunk key may belong to ('a/b/c/0/1' -> ['a/b'], 'a/c.0.1' -> ['a'])."""
    if "/c/" in key:
        return [key.rsplit("/c/", 1)[0]]
    head, _, leaf = key.rpartition("/")
    return [head] if leaf.startswith("c.") or leaf == "c" else []


def identity(root: Path) -> str:
    """Return the identity of the complete store at ``root``: a hash of what its manifest
    records of its arrays (each chunk and shard file's size and CRC32C, each array's
    metadata), its root attributes (the build's timings among them) left out, so two builds
    of the same data have the same identity. Raises StoreError without a readable manifest."""
    try:
        doc = json.loads((root / MANIFEST / METADATA).read_text())["attributes"]["gtgen_manifest"]
        arrays = {"files": doc["files"], "metadata": {k: v for k, v in doc["metadata"].items() if k != METADATA}}
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise StoreError(f"'{root}' has no readable record of what was written (array '{MANIFEST}'); it is not a complete gtgen store") from err
    return hashlib.sha256(json.dumps(arrays, sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Where:
    """How to name a store in an error: its kind, path and the command that makes it."""

    name: str
    path: Path
    made_by: str

    def damaged(self, what: str) -> DamagedStoreError:
        """Return the error for damaged data ``what`` in this store."""
        return DamagedStoreError(f"{self.name} store '{self.path}' is damaged: {what}; rebuild it with '{self.made_by}' "
                                 f"(check it whole with 'gtgen verify {self.path}')", what)


class Manifest:
    """The record of a complete store's files, for checking reads (see the module docstring)."""

    def __init__(self, root: Path, where: Where) -> None:
        self.root, self.where = root, where
        try:
            doc = json.loads((root / MANIFEST / METADATA).read_text())["attributes"]["gtgen_manifest"]
            version = doc.get("version")
            if version == MANIFEST_VERSION:
                self.files: dict[str, list[int]] = doc["files"]
                self.indexes: dict[str, int] = doc["indexes"]
                self.metadata: dict[str, int] = doc["metadata"]
        except FileNotFoundError:
            raise where.damaged(f"its record of what was written (array '{MANIFEST}') is missing") from None
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
            raise where.damaged(f"its record of what was written (array '{MANIFEST}') cannot be read ({err})".splitlines()[0]) from err
        if version != MANIFEST_VERSION:
            raise StoreError(f"{where.name} store '{where.path}' was written by another gtgen (its record of what was written, "
                             f"'{MANIFEST}', is of version {version!r}; this gtgen reads version {MANIFEST_VERSION}): "
                             f"rebuild it with '{where.made_by}'")
        self._first_axis: dict[str, tuple[int, str]] = {}
        self._by_row: dict[str, dict[int, list[str]]] = {}

    def check_metadata(self) -> None:
        """Raise DamagedStoreError unless every metadata file is there, unchanged."""
        for key, crc in self.metadata.items():
            try:
                data = (self.root / key).read_bytes()
            except OSError:
                raise self.where.damaged(f"metadata '{key}' is missing") from None
            if crc32c(data) != crc:
                raise self.where.damaged(f"metadata '{key}' was changed after it was written")

    def check(self, key: str, data: bytes | memoryview | np.ndarray | None) -> None:
        """Check a chunk file ``key`` read whole as ``data`` (None: the file was not there);
        raise DamagedStoreError if the store should hold other bytes there."""
        want = self.files.get(key)
        if want is None:
            if data is not None and key.rsplit("/", 1)[-1] != METADATA and not key.startswith(MANIFEST + "/"):
                raise self.damaged_chunk(key, "was not written with the store (removing the file is enough)")
            return
        if data is None:
            raise self.damaged_chunk(key, "is missing")
        n = memoryview(data).nbytes
        if n != want[0]:
            raise self.damaged_chunk(key, f"has {n} bytes, {want[0]} were written")
        if crc32c(data) != want[1]:
            raise self.damaged_chunk(key, "holds other bytes than were written there (another chunk's, or an earlier write's)")

    def check_size(self, key: str) -> None:
        """Check the size of chunk file ``key`` on disk (for reads of part of a file)."""
        try:
            n: int | None = os.stat(self.root / key).st_size
        except FileNotFoundError:
            n = None
        want = self.files.get(key)
        if want is None or n is None:
            self.check(key, None if n is None else b"")  # missing, or a file not written with the store
        elif n != want[0]:
            raise self.damaged_chunk(key, f"has {n} bytes, {want[0]} were written")

    def check_part(self, key: str) -> None:
        """Check chunk file ``key`` before a read of part of it: whole (read here) when it is
        at most ``SMALL_FILE`` bytes, else its size."""
        want = self.files.get(key)
        if want is not None and want[0] <= SMALL_FILE:
            try:
                data: bytes | None = (self.root / key).read_bytes()
            except FileNotFoundError:
                data = None
            self.check(key, data)
        else:
            self.check_size(key)

    def check_index(self, key: str, index: bytes | memoryview | np.ndarray) -> None:
        """Check the index bytes ``index`` read from the end of shard file ``key`` (a shard's
        inner chunks are read in part: the index ties them to their place)."""
        want = self.indexes.get(key)
        if want is not None and crc32c(memoryview(index)[:-4]) != want:
            raise self.damaged_chunk(key, "has another shard index than was written there (another shard's, or an earlier write's)")

    def check_rows(self, array: str, first: range | list[int]) -> None:
        """Check, before reading them, the chunk files of ``array`` whose first chunk index
        (along axis 0) is in ``first``: each listed one must be there with its size."""
        by_row = self._by_row.get(array)
        if by_row is None:
            by_row = {}
            prefix = array + "/"
            for key in self.files:
                if key.startswith(prefix):
                    rest = key[len(prefix):]
                    head = rest[2:].replace(".", "/").split("/")[0] if rest[:2] in ("c/", "c.") else ""
                    if head.isdigit():
                        by_row.setdefault(int(head), []).append(key)
            self._by_row[array] = by_row
        for i in first:
            for key in by_row.get(int(i), ()):
                self.check_size(key)

    def damaged_chunk(self, key: str, what: str) -> DamagedStoreError:
        """Return the error for chunk file ``key`` of this store, naming its array and rows."""
        array, rows = self.locate(key)
        return self.where.damaged(f"array '{array}'{rows}: chunk file '{key}' {what}")

    def locate(self, key: str) -> tuple[str, str]:
        """Return (array path, ' <noun> a-b' of the rows its chunk file ``key`` holds)."""
        array, _, chunk = key.partition("/c/") if "/c/" in key else key.rpartition("/")
        if "/c/" not in key:
            chunk = chunk[2:] if chunk.startswith("c.") else ""
        first = chunk.replace(".", "/").split("/")[0]
        if not first.isdigit():
            return array, ""
        n, noun = self.axis(array)
        a = int(first) * n
        return array, " " + rows_text(noun, a, a + n - 1)

    def axis(self, array: str) -> tuple[int, str]:
        """Return (rows per chunk file along axis 0, what the rows are) of ``array``."""
        if array not in self._first_axis:
            from gtgen.storage.schema import FORMATS

            noun = "rows"
            for fmt in FORMATS.values():
                spec = next((s for s in fmt.arrays if s.path == array), None)
                if spec is not None:
                    noun = AXIS_NOUNS.get(spec.axes()[0], "rows")
            try:
                meta = json.loads((self.root / array / METADATA).read_text())
                n = int(meta["chunk_grid"]["configuration"]["chunk_shape"][0])
            except (OSError, ValueError, KeyError, IndexError, TypeError):
                n = 1
            self._first_axis[array] = (n, noun)
        return self._first_axis[array]


@dataclass
class Verdict:
    """What ``verify`` found: ``problems`` (damage: the data is not as written), ``extra``
    (files the store was not written with that zarr never reads: removing them is enough),
    the files checked, and ``strays`` (files the store was not written with, named as a
    chunk of one of its arrays: zarr would read them as data, gtgen refuses them; removing
    them is enough too)."""

    problems: list[str]
    extra: list[str]
    checked: int
    strays: list[str] = field(default_factory=list)


def verify(root: Path, where: Where) -> Verdict:
    """Check the store at ``root`` whole: files missing, of another size or other bytes
    (CRC32C), not written with it, metadata changed, chunks that do not decode."""
    problems: list[str] = []
    m = Manifest(root, where)
    on_disk = _store_files(root)
    for key, crc in m.metadata.items():
        if key not in on_disk:
            problems.append(f"metadata '{key}' is missing")
        elif crc32c((root / key).read_bytes()) != crc:
            problems.append(f"metadata '{key}' was changed after it was written")
    for key in m.files:
        try:
            m.check(key, (root / key).read_bytes() if key in on_disk else None)
        except DamagedStoreError as err:
            problems.append(err.what)
    extra, strays = [], []
    for key in sorted(set(on_disk) - set(m.files) - set(m.metadata)):
        if _arrays_of(key) and f"{_arrays_of(key)[0]}/{METADATA}" in m.metadata:  # in an array's chunk keys: zarr reads it as data
            strays.append(key)
        else:
            extra.append(key)
    if not problems and not strays:  # zarr would decode the strays too: first they go
        problems += _decode_all(root, m)
    return Verdict(problems, extra, len(m.files) + len(m.metadata), strays)


def _decode_all(root: Path, m: Manifest) -> list[str]:
    """Return the rows of each array whose chunks do not decode (zstd checksums, shard
    index CRCs), read through zarr a chunk row at a time (memory bounded by one shard)."""
    import zarr

    problems = []
    arrays = sorted({m.locate(key)[0] for key in m.files} | {k.rsplit("/", 1)[0] for k in m.metadata if "/" in k})
    group = zarr.open_group(str(root), mode="r")
    for path in arrays:
        try:
            arr = group[path]
        except KeyError:
            continue
        if not isinstance(arr, zarr.Array) or arr.ndim == 0:
            continue
        n = int(arr.shards[0] if arr.shards else arr.chunks[0])
        for a in range(0, int(arr.shape[0]), max(n, 1)):
            try:
                arr[a : a + n]
            except Exception as err:  # noqa: BLE001 - zstd and the index check raise several kinds
                _, noun = m.axis(path)
                problems.append(f"array '{path}' {rows_text(noun, a, min(a + n, int(arr.shape[0])) - 1)}: does not decode ({err})".splitlines()[0])
    return problems
