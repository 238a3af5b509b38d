"""Bare MCAP files, read chunk by chunk: the one hand-written MCAP reader of gtgen.

Contract (the MCAP specification, version 0): after the 8-byte magic come records of an
opcode (u8), a length (u64 LE) and content; strings are a u32 LE length and UTF-8
bytes. A Chunk (0x06) holds message_start_time, message_end_time, uncompressed size
(u64 each), a crc (u32), the compression ('', 'zstd' or 'lz4') and its records
(u64 length); inside, Message records (0x05) are channel id (u16), sequence (u32), log
time and publish time (u64) and the serialized message; Schema (0x03) and Channel
(0x04) records say what each channel carries. Messages must sit in chunks (as every ROS
recorder and rosbags write them).

Where to find the chunks: from the summary's chunk indexes (read with the mcap library)
when the file has them; otherwise, as ``mcap recover`` does, by walking the records from
the start of the file, which also reads a file cut short (a power loss in the field):
every complete chunk before the cut is used and the bytes after it are reported lost.

Why by hand: the mcap library parses every record through a small-read stream wrapper,
about a quarter of the time of a pass over a bag. Here each chunk is read with one read
and one decompression, and its records are split with struct on a memoryview (no copies);
chunks that overlap in log time are merged as the mcap library does
(``chunked.in_time_order``).

Oracle: ``tests/test_bag_reader.py`` compares every message with the mcap library's.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from gtgen.bag.chunked import ChunkRef, in_time_order
from gtgen.bag.msgdefs import normalize_msgtype
from gtgen.errors import BagError

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_DATA_END = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F
_REC = struct.Struct("<BQ")
_MSG = struct.Struct("<HIQQ")
_CHUNK = struct.Struct("<QQQI")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")


@dataclass(frozen=True)
class Schema:
    """A message schema: its type name, encoding ('ros1msg', 'ros2msg', ...) and definition."""

    name: str
    encoding: str
    data: bytes


@dataclass
class McapFile:
    """The schemas, channels (id -> (topic, schema id)), per-channel message counts and
    chunks of one bare MCAP file; ``lost_bytes`` > 0 when it was cut short."""

    path: Path
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, tuple[str, int]] = field(default_factory=dict)
    counts: dict[int, int] = field(default_factory=dict)
    chunks: list[ChunkRef] = field(default_factory=list)
    lost_bytes: int = 0
    size: int = 0

    @classmethod
    def open(cls, path: Path) -> McapFile:
        """Return the index of ``path``: from its summary, else by walking its records."""
        mf = cls(Path(path), size=Path(path).stat().st_size)
        with open(path, "rb") as f:
            if f.read(8) != MAGIC:
                raise BagError(f"bag '{path}' is not an MCAP file (bad magic bytes)")
            if not mf._from_summary(f):
                f.seek(8)
                mf._walk(f)
        if not mf.chunks:
            cut = f" ({mf.lost_bytes} bytes after the cut)" if mf.lost_bytes else ""
            raise BagError(f"bag '{path}' has no complete chunk of messages: truncated inside its header or first chunk{cut}")
        return mf

    def _from_summary(self, f) -> bool:
        from mcap.reader import make_reader

        try:
            f.seek(0)
            summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - a file cut short has no footer: walk it instead
            return False
        if summary is None or not summary.chunk_indexes:
            return False
        self.schemas = {i: Schema(normalize_msgtype(s.name), s.encoding, bytes(s.data)) for i, s in summary.schemas.items()}
        self.channels = {i: (c.topic, c.schema_id) for i, c in summary.channels.items()}
        stats = summary.statistics.channel_message_counts if summary.statistics else {}
        self.counts = {i: int(stats.get(i, 0)) for i in self.channels}
        self.chunks = [ChunkRef(ci.chunk_start_offset, ci.chunk_length, ci.message_start_time, ci.message_end_time,
                                frozenset(ci.message_index_offsets)) for ci in summary.chunk_indexes]
        return True

    def _walk(self, f) -> None:
        """Index the file record by record from its start, stopping at the first record that
        is cut short or damaged (everything after it is lost)."""
        pos = 8
        while pos < self.size:
            head = f.read(9)
            if len(head) < 9:
                break
            op, length = _REC.unpack(head)
            if op in (OP_FOOTER, OP_DATA_END) or length > self.size - pos - 9:
                break
            body = memoryview(f.read(length))
            if len(body) < length:
                break
            if op == OP_CHUNK:
                try:
                    self._index_chunk(pos, 9 + length, body)
                except (BagError, struct.error, ValueError):
                    break  # a damaged chunk: treat it as the cut
            elif op in (OP_SCHEMA, OP_CHANNEL):
                self._definition(op, body)
            elif op == OP_MESSAGE:
                raise BagError(f"bag '{self.path}' has messages outside chunks; gtgen reads chunked MCAP files (as ROS recorders write them)")
            pos += 9 + length
        if pos < self.size and not self._ended(f, pos):
            self.lost_bytes = self.size - pos

    def _ended(self, f, pos: int) -> bool:
        """Whether the walk stopped at the end of the data section, not at a cut."""
        f.seek(pos)
        head = f.read(9)
        return len(head) == 9 and head[0] in (OP_FOOTER, OP_DATA_END)

    def _definition(self, op: int, body: memoryview) -> None:
        if op == OP_SCHEMA:
            (sid,) = _U16.unpack_from(body, 0)
            name, p = _string(body, 2)
            enc, p = _string(body, p)
            (n,) = _U32.unpack_from(body, p)
            self.schemas[sid] = Schema(normalize_msgtype(name), enc, bytes(body[p + 4 : p + 4 + n]))
        else:
            cid, sid = struct.unpack_from("<HH", body, 0)
            topic, _ = _string(body, 4)
            self.channels[cid] = (topic, sid)
            self.counts.setdefault(cid, 0)

    def _index_chunk(self, offset: int, length: int, body: memoryview) -> None:
        t0, t1, _, _ = _CHUNK.unpack_from(body, 0)
        seen: set[int] = set()
        data = _records(body)
        p, end = 0, len(data)
        while p < end:
            op, n = _REC.unpack_from(data, p)
            p += 9
            if p + n > end:
                raise BagError("record runs past the end of its chunk")
            if op == OP_MESSAGE:
                (cid,) = _U16.unpack_from(data, p)
                seen.add(cid)
                self.counts[cid] = self.counts.get(cid, 0) + 1
            elif op in (OP_SCHEMA, OP_CHANNEL):
                self._definition(op, data[p : p + n])
            p += n
        self.chunks.append(ChunkRef(offset, length, t0, t1, frozenset(seen)))

    def time_range(self) -> tuple[int, int]:
        """Return [start, stop) of the log times of the file's chunks."""
        return min(c.t_start for c in self.chunks), max(c.t_end for c in self.chunks) + 1

    def messages(self, topics: set[str], start: int | None, stop: int | None) -> Iterator[tuple[int, str, str, memoryview]]:
        """Yield (log time, topic, schema name, data) of ``topics`` with log time in
        [start, stop), in log-time order (ties in file order)."""
        chans = {cid: (topic, self.schemas[sid].name if sid in self.schemas else "")
                 for cid, (topic, sid) in self.channels.items() if topic in topics}
        with open(self.path, "rb") as f:
            yield from in_time_order(self.chunks, set(chans), start, stop, lambda ref: self._chunk_messages(f, ref, chans))

    def _chunk_messages(self, f, ref: ChunkRef, chans: dict[int, tuple[str, str]]) -> Iterator[tuple[int, str, str, memoryview]]:
        data = self._read_chunk(f, ref)
        p, end = 0, len(data)
        while p < end:
            op, length = _REC.unpack_from(data, p)
            p += 9
            if op == OP_MESSAGE:
                cid, _, t, _ = _MSG.unpack_from(data, p)
                if cid in chans:
                    yield (t, *chans[cid], data[p + 22 : p + length])
            p += length
        if p != end:
            raise BagError(f"MCAP chunk at byte {ref.offset} of '{self.path}' has a record running past its end")

    def _read_chunk(self, f, ref: ChunkRef) -> memoryview:
        f.seek(ref.offset)
        raw = memoryview(f.read(ref.length))
        if len(raw) != ref.length or raw[0] != OP_CHUNK:
            raise BagError(f"MCAP chunk at byte {ref.offset} of '{self.path}' is cut short or not a chunk")
        return _records(raw[9:])


def _string(buf: memoryview, p: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(buf, p)
    return str(buf[p + 4 : p + 4 + n], "utf-8"), p + 4 + n


def _records(body: memoryview) -> memoryview:
    """Return the uncompressed records of a chunk record's content."""
    _, _, size, _ = _CHUNK.unpack_from(body, 0)
    kind, p = _string(body, _CHUNK.size)
    (m,) = struct.unpack_from("<Q", body, p)
    return memoryview(_decompress(kind, body[p + 8 : p + 8 + m], size))


def _decompress(kind: str, data: memoryview, size: int) -> bytes | memoryview:
    if kind == "":
        return data
    if kind == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if kind == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise BagError(f"MCAP chunk compression {kind!r} unsupported; expected zstd, lz4 or none")


def profile(path: Path) -> str:
    """Return the schema encoding of a bare .mcap ('ros1msg', 'ros2msg', ...), without
    indexing it (the first schema record decides; 'ros2msg' if none is found early)."""
    with open(path, "rb") as f:
        if f.read(8) != MAGIC:
            raise BagError(f"bag '{path}' is not an MCAP file (bad magic bytes)")
        for _ in range(64):
            head = f.read(9)
            if len(head) < 9:
                break
            op, length = _REC.unpack(head)
            if op == OP_SCHEMA:
                body = memoryview(f.read(length))
                _, p = _string(body, 2)
                return _string(body, p)[0]
            if op == OP_CHUNK:
                try:
                    data = _records(memoryview(f.read(length)))
                except Exception:  # noqa: BLE001 - a damaged first chunk: decided elsewhere
                    break
                p = 0
                while p < len(data):
                    op2, n = _REC.unpack_from(data, p)
                    if op2 == OP_SCHEMA:
                        body = data[p + 9 : p + 9 + n]
                        _, q = _string(body, 2)
                        return _string(body, q)[0]
                    p += 9 + n
                break
            f.seek(length, 1)
    return "ros2msg"
