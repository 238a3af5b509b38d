"""What a store holds, recorded when it is completed, and checked on every read.

Zarr reads a missing chunk as its fill value, and gtgen does not store chunks that are
all fill, so a deleted file cannot be told from "no data" by zarr alone. Every gtgen
store therefore records, as its last write, a manifest of every file it holds: each chunk
or shard file's size, and each metadata file's (``zarr.json``) CRC32C. The manifest is the
attributes of an empty array ``MANIFEST`` at the store's root (a member of the hierarchy,
so zarr and xarray list the store without complaint), excluded from itself. The bytes inside a chunk are protected by the chunk itself: every
chunk (and every inner chunk of a shard) is a zstd frame with its content checksum, and
a shard's index carries its CRC32C (the Zarr v3 sharding codec's), so a changed byte
fails the decode.

Readers check through :class:`Manifest`: a chunk the manifest lists but the store lacks,
or whose size differs, is a :class:`DamagedStoreError` naming the array, the rows (samples)
it holds and the command that rebuilds the store; a chunk the manifest does not list is
all fill, as zarr says. ``verify`` checks a whole store: every listed file, every
metadata checksum, every chunk decoded.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from gtgen.errors import StoreError

MANIFEST = "gtgen_manifest"
MANIFEST_VERSION = 1
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


def crc32c(data: bytes) -> int:
    """Return the CRC32C of ``data``."""
    import google_crc32c

    return int(google_crc32c.value(data))


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


def write_manifest(root: Path) -> None:
    """Record every file of the store at ``root`` (call it last, once the store is complete)."""
    import zarr

    files = _store_files(root)
    meta = {k: crc32c((root / k).read_bytes()) for k in files if k.rsplit("/", 1)[-1] == METADATA}
    doc = {"version": MANIFEST_VERSION, "metadata": meta, "files": {k: n for k, n in sorted(files.items()) if k not in meta}}
    zarr.open_group(str(root), mode="r+").create_array(MANIFEST, shape=(0,), dtype="uint8", attributes={"gtgen_manifest": doc})


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
            self.files: dict[str, int] = doc["files"]
            self.metadata: dict[str, int] = doc["metadata"]
            ok = doc.get("version") == MANIFEST_VERSION
        except FileNotFoundError:
            raise where.damaged(f"its record of what was written (array '{MANIFEST}') is missing") from None
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise where.damaged(f"its record of what was written (array '{MANIFEST}') cannot be read ({err})".splitlines()[0]) from err
        if not ok:
            raise where.damaged(f"'{MANIFEST}' is of version {doc.get('version')!r}, expected {MANIFEST_VERSION}")
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

    def check(self, key: str, nbytes: int | None) -> None:
        """Check a chunk file ``key`` read with ``nbytes`` bytes (None: the file was not
        there); raise DamagedStoreError if the store should hold other bytes."""
        want = self.files.get(key)
        if want is None:
            if nbytes is not None and key.rsplit("/", 1)[-1] != METADATA and not key.startswith(MANIFEST + "/"):
                raise self.damaged_chunk(key, "holds a chunk file that was not written with the store")
            return
        if nbytes is None:
            raise self.damaged_chunk(key, "is missing")
        if nbytes != want:
            raise self.damaged_chunk(key, f"has {nbytes} bytes, {want} were written")

    def check_size(self, key: str) -> None:
        """Check the size of chunk file ``key`` on disk (for reads of part of a file)."""
        try:
            n: int | None = os.stat(self.root / key).st_size
        except FileNotFoundError:
            n = None
        self.check(key, n)

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


def verify(root: Path, where: Where) -> list[str]:
    """Return every problem of the store at ``root`` (empty if it is whole): files missing,
    of another size or not written with it, metadata changed, chunks that do not decode."""
    problems: list[str] = []
    m = Manifest(root, where)
    on_disk = _store_files(root)
    for key, crc in m.metadata.items():
        if key not in on_disk:
            problems.append(f"metadata '{key}' is missing")
        elif crc32c((root / key).read_bytes()) != crc:
            problems.append(f"metadata '{key}' was changed after it was written")
    for key, n in m.files.items():
        got = on_disk.get(key)
        if got != n:
            array, rows = m.locate(key)
            problems.append(f"array '{array}'{rows}: chunk file '{key}' " + ("is missing" if got is None else f"has {got} bytes, {n} were written"))
    for key in sorted(set(on_disk) - set(m.files) - set(m.metadata)):
        problems.append(f"file '{key}' was not written with the store")
    if problems:
        return problems
    problems += _decode_all(root, m)
    return problems


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
