"""The read-only zarr store every read of a gtgen store goes through, and the codec
pipeline that names a chunk that does not decode.

:class:`CheckedStore` checks each chunk file zarr reads against the store's manifest
(``storage/integrity.py``); ``CheckedPipeline`` turns a chunk of it that fails to decode
into the :class:`~gtgen.storage.integrity.DamagedStoreError` naming its array and rows,
so users' xarray and zarr views of a gtgen store meet the same one line as gtgen's own
readers (``storage/stores.py``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gtgen.errors import GtgenError
from gtgen.storage.integrity import Manifest, Where


def _checked_store_class() -> type:
    import zarr
    from zarr.abc.store import SuffixByteRequest
    from zarr.core.codec_pipeline import BatchedCodecPipeline
    from zarr.registry import fully_qualified_name, register_pipeline
    from zarr.storage import LocalStore

    class CheckedStore(LocalStore):
        """A read-only local zarr store whose every chunk read is checked against the
        store's manifest: a listed chunk that is missing, of another size or (read whole)
        of other bytes, or a shard index that is another, raises DamagedStoreError instead
        of reading as fill or as another chunk's data."""

        def __init__(self, root: Path, manifest: Manifest) -> None:
            super().__init__(str(root), read_only=True)
            self.manifest = manifest

        async def get(self, key: str, prototype: Any, byte_range: Any = None) -> Any:
            if byte_range is not None and key in self.manifest.files:
                self.manifest.check_part(key)
            buf = await super().get(key, prototype, byte_range)
            if byte_range is None:
                self.manifest.check(key, None if buf is None else buf.as_numpy_array())
            elif buf is not None and isinstance(byte_range, SuffixByteRequest) and key in self.manifest.indexes:
                self.manifest.check_index(key, buf.as_numpy_array())  # a shard's index, read before its inner chunks
            return buf

        def __reduce__(self) -> tuple:
            return (_reopen_checked, (str(self.root), self.manifest.where))

    class CheckedPipeline(BatchedCodecPipeline):
        """zarr's own codec pipeline, except that a chunk of a CheckedStore that does not
        decode (its zstd checksum, its shard index's CRC32C) is the DamagedStoreError naming
        its array and rows, for every zarr read of the store: xarray's, the group's."""

        async def read(self, batch_info: Any, out: Any, drop_axes: tuple[int, ...] = ()) -> None:
            batch_info = list(batch_info)
            try:
                await super().read(batch_info, out, drop_axes)
            except GtgenError:
                raise
            except Exception:  # noqa: BLE001 - zstd and the index check raise several kinds
                store = getattr(batch_info[0][0], "store", None) if batch_info else None  # a shard's inner chunks have none
                if not isinstance(store, CheckedStore):
                    raise
                for item in batch_info:  # which chunk file it was
                    try:
                        await super().read([item], out, drop_axes)
                    except Exception as one:  # noqa: BLE001 - zstd and the index check raise several kinds
                        raise store.manifest.damaged_chunk(item[0].path, f"does not decode ({type(one).__name__}: {one})".splitlines()[0]) from one
                raise

    # the default pipeline's place, unless the user chose another one (zarrs, say)
    if zarr.config.get("codec_pipeline.path") == fully_qualified_name(BatchedCodecPipeline):
        register_pipeline(CheckedPipeline)
        zarr.config.set({"codec_pipeline.path": fully_qualified_name(CheckedPipeline)})
    return CheckedStore


_CHECKED: type | None = None


def checked_store(root: Path, manifest: Manifest) -> Any:
    """Return a read-only zarr store of ``root`` whose chunk reads ``manifest`` checks."""
    global _CHECKED
    if _CHECKED is None:
        _CHECKED = _checked_store_class()
    return _CHECKED(root, manifest)


def _reopen_checked(root: str, where: Where) -> Any:
    return checked_store(Path(root), Manifest(Path(root), where))
