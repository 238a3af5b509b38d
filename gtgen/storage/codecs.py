"""The codecs of gtgen's arrays, and their chunks encoded and decoded by hand.

Contract (the Zarr v3 specification): an array's codecs are ``bytes`` (little endian)
then ``zstd`` with its content checksum (``compressors()``; codec "zstd"), or, for the
dataset's packed integer arrays (``storage/packing.py``), ``bytes``, ``blosc`` (zstd at
``BLOSC_LEVEL``, byte shuffle, the dtype's typesize) and ``crc32c`` (codec "blosc": the
CRC32C of the compressed bytes appended, little endian), or, for the float grids of the
drive and fused stores that the next stage reads once (codec "lz4"), the same with blosc's
lz4 at ``LZ4_LEVEL``. :func:`encode_chunk` makes the bytes zarr writes for one chunk of
any, :func:`decode_chunk` reads them back and fails on a changed byte (zstd's checksum,
or the CRC32C).

Why by hand: gtgen's chunk and shard files are read and written without zarr's per-call
cost (``storage/chunks.py``, ``shards.py``). Oracle: ``tests/test_format.py`` and
``tests/test_packing.py`` compare these bytes with zarr's.
"""

from __future__ import annotations

from typing import Any

import numpy as np

ZSTD_LEVEL = 1  # faster to write than zarr's default level, about the same size on elevation maps
CHECKSUM = True  # each chunk carries zstd's content checksum (4 bytes): a changed byte fails its decode
# packed integer grids: byte shuffle puts the steps' slowly varying high bytes together;
# measured on the default drive's dataset (bench/bytes.py), 23 % smaller than plain zstd
# level 1 on the packed grids and points, and faster to write; level 5 gains 7 % more at
# 4 times the encoding time
BLOSC_LEVEL = 2
# the intermediate stores' float grids (X-Racer maps, fused grids): written once and read
# once by the next stage, where zstd's encoding and decoding were 30-40 % of fuse's time.
# Measured on the default drive's micro maps, per 500 x 500 layer (zstd 1 -> blosc lz4 5
# with byte shuffle): encode 2.6-4.2 -> 1.0-2.2 ms, decode 1.3-1.6 -> 0.4-1.0 ms, the
# stores about 20 % larger (bench/pipeline.py)
LZ4_LEVEL = 5
CODECS = ("zstd", "blosc", "lz4")
_BLOSC = {"blosc": ("zstd", BLOSC_LEVEL), "lz4": ("lz4", LZ4_LEVEL)}  # codec -> blosc's cname, clevel


def compressors(codec: str = "zstd") -> list:
    """Return the compressors of a gtgen array of ``codec``: zstd at ``ZSTD_LEVEL`` with its
    checksum, or ("blosc", packed arrays; "lz4", intermediate float grids) blosc zstd or
    lz4 with byte shuffle then crc32c."""
    if codec in _BLOSC:
        from zarr.codecs import BloscCodec, Crc32cCodec

        cname, level = _BLOSC[codec]
        return [BloscCodec(cname=cname, clevel=level, shuffle="shuffle"), Crc32cCodec()]
    if codec != "zstd":
        raise ValueError(f"codec {codec!r}; expected one of {CODECS}")
    from zarr.codecs import ZstdCodec

    return [ZstdCodec(level=ZSTD_LEVEL, checksum=CHECKSUM)]


def _blosc(itemsize: int, codec: str = "blosc") -> Any:
    from numcodecs import Blosc

    cname, level = _BLOSC[codec]
    return Blosc.from_config({"cname": cname, "clevel": level, "shuffle": Blosc.SHUFFLE, "blocksize": 0, "typesize": itemsize})


def encode_chunk(value: np.ndarray, codec: str = "zstd") -> bytes:
    """Return the encoded bytes of one whole chunk holding ``value``, as zarr writes them
    for an array with ``compressors(codec)``."""
    v = np.ascontiguousarray(value)
    if v.dtype.byteorder == ">":
        v = v.astype(v.dtype.newbyteorder("<"))
    if codec in _BLOSC:
        import google_crc32c

        data = _blosc(v.dtype.itemsize, codec).encode(v.view(np.uint8).reshape(-1))
        return bytes(data) + int(google_crc32c.value(data)).to_bytes(4, "little")
    from numcodecs import Zstd

    return Zstd(level=ZSTD_LEVEL, checksum=CHECKSUM).encode(v)


def decode_chunk(data: bytes | memoryview, dtype: np.dtype, shape: tuple[int, ...], codec: str = "zstd") -> np.ndarray:
    """Return the values of one chunk's bytes of ``codec``; ValueError where its checksum
    (zstd's, or the crc32c of a blosc chunk) fails."""
    out = np.empty(shape, np.dtype(dtype).newbyteorder("<"))
    if codec in _BLOSC:
        import google_crc32c

        raw = np.frombuffer(data, np.uint8)
        body = raw[:-4]
        if len(raw) < 4 or int(google_crc32c.value(body)) != int.from_bytes(raw[-4:].tobytes(), "little"):
            raise ValueError("chunk crc32c checksum does not match")
        _blosc(out.dtype.itemsize, codec).decode(body, out=out.view(np.uint8).reshape(-1))
        return out.astype(dtype, copy=False)
    from numcodecs import Zstd

    return Zstd().decode(data, out=out).astype(dtype, copy=False)


def codec_of(codecs: list[dict], dtype: Any) -> str | None:
    """Return which of ``CODECS`` a zarr v3 codec list (as in ``zarr.json``) stores chunks
    as :func:`encode_chunk` makes them with, None for any other list."""
    head = {"name": "bytes", "configuration": {"endian": "little"}}
    got = [{"name": c.get("name"), "configuration": c.get("configuration", {})} for c in codecs]
    if np.dtype(dtype).itemsize == 1:  # single bytes have no endianness
        got = [c if c["name"] != "bytes" else head for c in got]
    if got == [head, {"name": "zstd", "configuration": {"level": ZSTD_LEVEL, "checksum": CHECKSUM}}]:
        return "zstd"
    for codec, (cname, level) in _BLOSC.items():
        blosc = {"typesize": np.dtype(dtype).itemsize, "cname": cname, "clevel": level, "shuffle": "shuffle", "blocksize": 0}
        if got == [head, {"name": "blosc", "configuration": blosc}, {"name": "crc32c", "configuration": {}}]:
            return codec
    return None


def encodes_like_gtgen(codecs: list[dict], dtype: Any) -> bool:
    """Whether a zarr v3 codec list (as in ``zarr.json``) stores chunks as :func:`encode_chunk`
    makes them (with one of ``CODECS``)."""
    return codec_of(codecs, dtype) is not None
