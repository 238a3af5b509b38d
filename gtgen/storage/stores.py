"""The one way to open and to write each kind of store, and the checks every read passes.

A complete store is opened read-only as its typed accessor (``DriveStore``,
``FusedStore``, ``DatasetStore``: ``storage/drive.py``, ``fused.py``, ``dataset.py``),
which validates its kind, version and completeness and reads its manifest
(``storage/integrity.py``). Every read goes through :class:`Store`: zarr reads through a
:class:`CheckedStore`, the fast chunk and shard readers with the manifest's check, and
any failure to read or decode becomes one :class:`~gtgen.storage.integrity.DamagedStoreError`
line naming the array, its rows and the command that rebuilds the store (zarr decodes the
checked store's chunks through a pipeline that says so, so users' xarray and zarr views of
it meet the same line). Stages ask the
accessors for poses, maps, samples and labels by name; no stage outside ``storage/``
opens a zarr group or spells an array path.

A store is written under its stage's partial output (``runtime/output.py``) through a
:class:`StoreWriter`, whose ``complete`` writes the attributes and then the manifest.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from gtgen.errors import GtgenError, StoreError
from gtgen.runtime.output import partials
from gtgen.storage.checked import checked_store
from gtgen.storage.chunks import ChunkFiles, RangeReader
from gtgen.storage.codecs import compressors
from gtgen.storage.integrity import (
    MANIFEST,
    METADATA,
    SMALL_FILE,
    DamagedStoreError,
    Manifest,
    Verdict,
    Where,
    rows_text,
    write_manifest,
)
from gtgen.storage.packing import Packing, packing_of
from gtgen.storage.schema import StoreFormat
from gtgen.storage.shards import SampleReader
from gtgen.storage.specs import ArraySpec, dimension_names


def jsonable(obj: Any) -> Any:
    """Return ``obj`` with numpy scalars and paths turned into JSON types."""
    return json.loads(json.dumps(obj, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def store_attrs(fmt: StoreFormat, **attrs: Any) -> dict[str, Any]:
    """Return the attributes of a complete store of ``fmt`` with ``attrs`` (as JSON types)."""
    return jsonable({"store": fmt.kind, "version": fmt.version, "complete": True, **attrs})


def _name(fmt: StoreFormat) -> str:
    return fmt.kind.removeprefix("gtgen-")


def complete_attrs(path: Path, fmt: StoreFormat) -> dict[str, Any]:
    """Return the attributes of the complete store of ``fmt`` at ``path``, or raise
    StoreError saying why it is not one and which command makes one."""
    import zarr

    name = _name(fmt)
    if not path.exists():
        left = partials(path)
        hint = f" (a run that did not finish left only '{left[0].name}')" if left else ""
        raise StoreError(f"{name} store '{path}' does not exist{hint}; run '{fmt.made_by}' first")
    try:
        attrs = zarr.open_group(str(path), mode="r").attrs.asdict()
    except Exception as err:  # noqa: BLE001 - zarr raises several types for non-stores
        if (path / MANIFEST).is_dir():  # a store gtgen completed, whose root metadata went missing
            raise Where(name, path, fmt.made_by).damaged(f"its root metadata '{METADATA}' is missing or unreadable") from err
        raise StoreError(f"'{path}' is not a zarr store: {err}".splitlines()[0]) from err
    if attrs.get("store") != fmt.kind:
        raise StoreError(f"'{path}' is not a gtgen {name} store (store={attrs.get('store')!r}, expected {fmt.kind!r})")
    if attrs.get("version") != fmt.version:
        raise StoreError(f"{name} store '{path}' has version {attrs.get('version')}; this gtgen reads version "
                         f"{fmt.version}: {fmt.rebuild or f're-run {fmt.made_by!r}'}")
    if not attrs.get("complete"):
        raise StoreError(f"{name} store '{path}' is incomplete; re-run '{fmt.made_by}'")
    return attrs


class Store:
    """A complete store of one format, opened read-only, every read checked.

    Subclasses set ``fmt`` and add the typed reads of their kind; ``group`` is the zarr
    group over the checked store, for tools that read arrays by path (xarray, tests).
    """

    fmt: ClassVar[StoreFormat]

    def __init__(self, path: Path) -> None:
        import zarr

        self.path = Path(path)
        self.name, self.where = _name(self.fmt), Where(_name(self.fmt), self.path, self.fmt.made_by)
        self.attrs: dict[str, Any] = complete_attrs(self.path, self.fmt)
        self.manifest = Manifest(self.path, self.where)
        self.manifest.check_metadata()
        self.group = zarr.open_group(checked_store(self.path, self.manifest), mode="r")
        self._arrays: dict[str, Any] = {}

    def __reduce__(self) -> tuple:
        return (_reopen, (type(self), str(self.path)))

    @cached_property
    def identity(self) -> str:
        """The store's identity (``integrity.identity``): results computed from it record it."""
        from gtgen.storage.integrity import identity

        return identity(self.path)

    def array(self, path: str) -> Any:
        """Return the zarr array ``path`` (checked reads)."""
        if path not in self._arrays:
            try:
                self._arrays[path] = self.group[path]
            except KeyError:
                raise self.where.damaged(f"array '{path}' is missing") from None
            except GtgenError:
                raise
            except Exception as err:  # noqa: BLE001 - zarr raises several types for bad metadata
                raise self.where.damaged(f"array '{path}' cannot be opened ({err})".splitlines()[0]) from err
        return self._arrays[path]

    def packing(self, path: str) -> Packing | None:
        """Return how array ``path`` is packed (its CF attributes; None: stored as it is)."""
        cache = self.__dict__.setdefault("_packings", {})
        if path not in cache:
            arr = self.array(path)
            cache[path] = packing_of(arr.attrs, arr.dtype)
        return cache[path]

    def shape(self, path: str) -> tuple[int, ...]:
        """Return the shape of array ``path``."""
        return tuple(int(n) for n in self.array(path).shape)

    def read(self, path: str, rows: Any = None) -> NDArray:
        """Return array ``path`` whole, or its ``rows`` (a slice, or sorted indices: one
        zarr call for all of them, a slice when consecutive), as floats where it is packed.
        The chunk files the read needs are checked against the manifest first."""
        out = self._read(path, rows)
        pk = self.packing(path)
        return out if pk is None else pk.unpack(out)

    def _read(self, path: str, rows: Any) -> NDArray:
        arr = self.array(path)
        n0 = int(arr.shape[0]) if arr.ndim else 0
        per = int((getattr(arr, "shards", None) or arr.chunks)[0]) if arr.ndim else 1
        if rows is None:
            sel: Any = ...
            first: Any = range((n0 + per - 1) // per)
        elif isinstance(rows, slice):
            sel = rows
            a, b, _ = rows.indices(n0)
            first = range(a // per, (b - 1) // per + 1) if b > a else range(0)
        else:
            sel = np.asarray(rows)
            first = np.unique(sel // per).tolist()
        self.manifest.check_rows(path, first)
        try:
            if not isinstance(sel, np.ndarray):
                return arr[sel]
            if len(sel) and np.all(np.diff(sel) == 1):
                return arr[int(sel[0]) : int(sel[-1]) + 1]
            return arr.get_orthogonal_selection((sel,))
        except GtgenError:
            raise
        except Exception as err:  # noqa: BLE001 - zstd, zarr and numpy raise several kinds
            raise self.damaged(path, rows, err) from err

    def rows(self, path: str) -> Rows:
        """Return a reader of array ``path`` one row (axis-0 index) at a time."""
        return Rows(self, path)

    def ranges(self, path: str) -> Callable[[int, int], NDArray]:
        """Return ``f(a, b)`` -> rows a to b of array ``path`` (chunked along axis 0 only),
        as floats where it is packed."""
        reader = RangeReader(self.array(path), check=self.manifest.check)
        pk = self.packing(path)

        def get(a: int, b: int) -> NDArray:
            try:
                rows = reader(a, b)
                return rows if pk is None else pk.unpack(rows)
            except GtgenError:
                raise
            except Exception as err:  # noqa: BLE001 - zstd raises several kinds
                raise self.damaged(path, slice(a, b), err) from err

        return get

    def damaged(self, path: str, rows: Any, err: BaseException) -> DamagedStoreError:
        """Return the error for a read of ``rows`` of array ``path`` that failed with ``err``."""
        where = ""
        if isinstance(rows, slice) and rows.start is not None:
            where = " " + rows_text(self.manifest.axis(path)[1], int(rows.start), int(rows.stop or rows.start + 1) - 1)
        elif rows is not None and not isinstance(rows, slice) and len(np.atleast_1d(rows)):
            r = np.atleast_1d(rows)
            where = " " + rows_text(self.manifest.axis(path)[1], int(r.min()), int(r.max()))
        return self.where.damaged(f"array '{path}'{where} cannot be read ({type(err).__name__}: {err})".splitlines()[0])


_OPENED: dict[tuple[type, str], tuple[tuple[int, int], Store]] = {}


def _reopen(cls: type, path: str) -> Store:
    """Return the store ``cls`` at ``path`` for a process that received it pickled: opened
    once per process (and again if the store was written anew since)."""
    try:
        st = (Path(path) / MANIFEST / "zarr.json").stat()
        stamp = (st.st_mtime_ns, st.st_size)
    except OSError:
        stamp = (0, 0)
    hit = _OPENED.get((cls, path))
    if hit is None or hit[0] != stamp:
        if len(_OPENED) > 8:
            _OPENED.clear()
        hit = (stamp, cls(Path(path)))
        _OPENED[(cls, path)] = hit
    return hit[1]


class Rows:
    """Rows (axis-0 indices) of one array of a store, each read from its chunk or shard
    file where the layout allows (no zarr call; ``storage/chunks.py``, ``shards.py``),
    else through zarr; checked against the store's manifest; as floats where packed."""

    def __init__(self, store: Store, path: str) -> None:
        arr = store.array(path)
        self.store, self.path = store, path
        self.packing = store.packing(path)
        check = store.manifest.check
        if getattr(arr, "shards", None):
            self._shard: SampleReader | None = SampleReader(arr, check=check, check_size=store.manifest.check_size,
                                                            check_index=store.manifest.check_index, whole_below=SMALL_FILE)
            self._files: ChunkFiles | None = None
        else:
            self._shard, self._files = None, ChunkFiles(arr, check=check)

    def __getitem__(self, k: int) -> NDArray:
        try:
            row = self._shard[int(k)] if self._shard is not None else self._files.read(int(k))  # type: ignore[union-attr]
            return row if self.packing is None else self.packing.unpack(row)
        except GtgenError:
            raise
        except Exception as err:  # noqa: BLE001 - zstd and numpy raise several kinds
            raise self.store.damaged(self.path, [int(k)], err) from err

    def encoded(self, k: int) -> Any:
        """Return row ``k`` as stored (``chunks.Encoded``) where it is a chunk file of an
        array stored as it is, else its values."""
        if self._files is not None and self._files.direct and self.packing is None:
            return self._files.encoded(int(k))
        return self[k]


class StoreWriter:
    """A store of one format being written at ``path`` (a stage's partial output).

    ``create`` makes arrays from the format's specs; ``complete`` writes the attributes
    (marking the store complete) and then the manifest of what the store holds.
    """

    fmt: ClassVar[StoreFormat]

    def __init__(self, path: Path, new: bool = True) -> None:
        import zarr

        self.path = Path(path)
        self.root = zarr.open_group(str(self.path), mode="w" if new else "r+")

    def spec(self, path: str) -> ArraySpec:
        """Return the spec of array ``path`` of this format."""
        return self.fmt.spec(path)

    def create(self, path: str, shape: tuple[int, ...], chunks: tuple[int, ...] | None = None,
               shards: tuple[int, ...] | None = None, flat: bool = False, packing: Packing | None = None, **kw: Any) -> Any:
        """Create array ``path`` with its spec's dtype, fill and dimension names and gtgen's
        codec; ``flat`` keys its chunks 'c.i.j...' (one folder); ``packing`` (of a packed
        spec) goes into its CF attributes."""
        sp = self.spec(path)
        if packing is not None:
            kw["attributes"] = {**kw.get("attributes", {}), **packing.attrs()}
        chunks = chunks or tuple(max(1, int(s)) for s in shape)
        keys = {"name": "default", "separator": "." if flat else "/"}
        return self.root.create_array(path, shape=shape, dtype=sp.dtype, chunks=chunks, shards=shards,
                                      fill_value=sp.fill_value(), compressors=compressors("blosc" if packing else sp.codec), chunk_key_encoding=keys,
                                      dimension_names=dimension_names(sp), **kw)

    def write(self, path: str, value: Any, chunks: tuple[int, ...] | None = None) -> Any:
        """Create array ``path`` holding ``value`` whole."""
        value = np.asarray(value)
        arr = self.create(path, value.shape, chunks)
        if value.size:
            arr[...] = value
        return arr

    def complete(self, **attrs: Any) -> None:
        """Write the attributes (the store is complete from here on) and the manifest."""
        self.root.attrs.update(store_attrs(self.fmt, **attrs))
        write_manifest(self.path)


def _kind_by_manifest(path: Path) -> str | None:
    """Return the kind of the store whose manifest at ``path`` lists the most arrays of that
    kind's format (None without a readable manifest)."""
    from gtgen.storage.schema import FORMATS

    try:
        doc = json.loads((path / MANIFEST / METADATA).read_text())["attributes"]["gtgen_manifest"]
        arrays = {k.rsplit("/", 1)[0] for k in doc["metadata"]}
    except (OSError, ValueError, KeyError, TypeError):
        return None
    overlap = {kind: len(arrays & {s.path for s in fmt.arrays}) for kind, fmt in FORMATS.items()}
    best = max(overlap, key=overlap.__getitem__)
    return best if overlap[best] else None


def verify_store(path: Path) -> tuple[StoreFormat, Verdict]:
    """Check the store at ``path`` whole (any gtgen kind): every file the manifest lists,
    every metadata checksum, every chunk decoded. Return (its format, what was found);
    raise StoreError if it is not a complete gtgen store at all."""
    from gtgen.storage.integrity import verify
    from gtgen.storage.schema import FORMATS

    try:
        kind = json.loads((Path(path) / METADATA).read_text()).get("attributes", {}).get("store")
    except (OSError, ValueError, AttributeError) as err:
        kind = _kind_by_manifest(Path(path))  # a completed store whose root metadata went missing: verify says so
        if kind is None:
            raise StoreError(f"'{path}' is not a gtgen store (no readable zarr.json)") from err
    fmt = FORMATS.get(kind)
    if fmt is None:
        raise StoreError(f"'{path}' is not a gtgen store (store={kind!r}; expected one of {sorted(FORMATS)})")
    if (Path(path) / METADATA).is_file():
        complete_attrs(Path(path), fmt)
    where = Where(_name(fmt), Path(path), fmt.made_by)
    try:
        return fmt, verify(Path(path), where)
    except DamagedStoreError as err:
        return fmt, Verdict([err.what], [], 0)
