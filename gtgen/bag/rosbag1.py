"""ROS 1 bags cut short, read the way ``rosbag reindex`` reads them: chunk by chunk from
the start of the file, up to the cut.

Contract (the ROS bag format 2.0): after the line ``#ROSBAG V2.0`` come records of a
header (u32 LE length, then fields: u32 LE length and ``name=value``, ``op`` a byte) and
data (u32 LE length). The bag header (op 0x03) comes first; each chunk (op 0x05; fields
``compression``: none, bz2 or lz4 and ``size``) holds connection records (op 0x07: field
``conn``; data: fields ``topic``, ``type``, ``message_definition``) and message data
records (op 0x02: fields ``conn`` and ``time``, u32 sec and nsec; data: the serialized
message). The index at the end, which a bag cut short lacks, is not needed.

Why by hand: rosbags reads a bag through its index, so it refuses a bag whose recording
stopped without writing one (a power loss in the field). Complete bags are read by
rosbags; this reader is for the others. Oracle: ``tests/test_bag_reader.py`` compares every
message of a cut bag with rosbags' reading of the complete bag.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from gtgen.bag.chunked import ChunkRef, in_time_order
from gtgen.bag.msgdefs import normalize_msgtype
from gtgen.errors import BagError

MAGIC = b"#ROSBAG V2.0\n"
OP_MSG, OP_BAG_HEADER, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 0x02, 0x03, 0x05, 0x06, 0x07
_U32 = struct.Struct("<I")
_TIME = struct.Struct("<II")


@dataclass(frozen=True)
class Connection:
    """A connection: its topic, message type and definition (the schema of its messages)."""

    topic: str
    name: str  # message type, as rosbags names it ('pkg/msg/Type')
    data: bytes  # message_definition
    encoding: str = "ros1msg"


def _fields(buf: memoryview) -> dict[str, memoryview]:
    out, p = {}, 0
    while p < len(buf):
        (n,) = _U32.unpack_from(buf, p)
        name, sep, _ = bytes(buf[p + 4 : p + 4 + min(n, 64)]).partition(b"=")
        if not sep or p + 4 + n > len(buf):
            raise BagError("a record header field is damaged")
        out[name.decode()] = buf[p + 5 + len(name) : p + 4 + n]
        p += 4 + n
    return out


def _records(buf: memoryview) -> Iterator[tuple[dict[str, memoryview], memoryview]]:
    """Yield (header fields, data) of the records in ``buf``; BagError where one is cut."""
    p = 0
    while p < len(buf):
        if p + 4 > len(buf):
            raise BagError("a record is cut short")
        (hl,) = _U32.unpack_from(buf, p)
        if p + 8 + hl > len(buf):
            raise BagError("a record is cut short")
        head = _fields(buf[p + 4 : p + 4 + hl])
        (dl,) = _U32.unpack_from(buf, p + 4 + hl)
        start = p + 8 + hl
        if start + dl > len(buf):
            raise BagError("a record is cut short")
        yield head, buf[start : start + dl]
        p = start + dl


def _decompress(kind: str, data: memoryview, size: int) -> memoryview:
    if kind == "none":
        return data
    if kind == "bz2":
        import bz2

        return memoryview(bz2.decompress(data))
    if kind == "lz4":
        import lz4.frame

        return memoryview(lz4.frame.decompress(data))
    raise BagError(f"ROS 1 chunk compression {kind!r} unsupported; expected none, bz2 or lz4")


@dataclass
class Ros1File:
    """The connections (id -> Connection), per-connection message counts and complete
    chunks of a ROS 1 bag, found by walking it; ``lost_bytes`` after the cut."""

    path: Path
    connections: dict[int, Connection] = field(default_factory=dict)
    counts: dict[int, int] = field(default_factory=dict)
    chunks: list[ChunkRef] = field(default_factory=list)
    lost_bytes: int = 0

    @classmethod
    def open(cls, path: Path) -> Ros1File:
        """Return the index of ``path`` by walking its records up to the first one cut short."""
        rf = cls(Path(path))
        size = rf.path.stat().st_size
        with open(path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise BagError(f"bag '{path}' is not a ROS 1 bag (no '#ROSBAG V2.0' line)")
            pos = rf._walk(f, len(MAGIC), size)
        rf.lost_bytes = size - pos
        if not rf.chunks:
            raise BagError(f"bag '{path}' has no complete chunk of messages: truncated inside its header or first chunk "
                           f"({rf.lost_bytes} bytes after the cut)")
        return rf

    def _walk(self, f, pos: int, size: int) -> int:
        """Index the records from ``pos``; return where the complete ones end (the file's
        size where they run into the index section, which holds no messages)."""
        while pos + 4 <= size:
            f.seek(pos)
            (hl,) = _U32.unpack(f.read(4))
            if pos + 8 + hl > size:
                break
            try:
                head = _fields(memoryview(f.read(hl)))
            except (BagError, struct.error):
                break
            (dl,) = _U32.unpack(f.read(4))
            end = pos + 8 + hl + dl
            op = head.get("op", b"\x00")[0]
            if end > size:
                break
            if op in (OP_CHUNK_INFO, OP_CONNECTION) and self.chunks:
                return size  # the index section: every chunk is in
            if op == OP_CHUNK:
                try:
                    self._index_chunk(pos, end - pos, head, memoryview(f.read(dl)))
                except (BagError, struct.error, ValueError, OSError, EOFError):
                    break  # a damaged chunk: treat it as the cut
            pos = end
        return pos

    def _index_chunk(self, offset: int, length: int, head: dict, data: memoryview) -> None:
        body = _decompress(bytes(head["compression"]).decode(), data, _U32.unpack(head["size"])[0])
        t_min, t_max, seen = 1 << 63, -1, set()
        for h, d in _records(body):
            op = h["op"][0]
            if op == OP_CONNECTION:
                conn = _U32.unpack(h["conn"])[0]
                fields = _fields(d)
                self.connections[conn] = Connection(bytes(h["topic"]).decode(), normalize_msgtype(bytes(fields["type"]).decode()),
                                                    bytes(fields.get("message_definition", b"")))
            elif op == OP_MSG:
                conn = _U32.unpack(h["conn"])[0]
                sec, nsec = _TIME.unpack(h["time"])
                t = sec * 1_000_000_000 + nsec
                t_min, t_max = min(t_min, t), max(t_max, t)
                seen.add(conn)
                self.counts[conn] = self.counts.get(conn, 0) + 1
        if seen:
            self.chunks.append(ChunkRef(offset, length, t_min, t_max, frozenset(seen)))

    def time_range(self) -> tuple[int, int]:
        """Return [start, stop) of the record times of the complete chunks."""
        return min(c.t_start for c in self.chunks), max(c.t_end for c in self.chunks) + 1

    def messages(self, topics: set[str], start: int | None, stop: int | None) -> Iterator[tuple[int, str, str, memoryview]]:
        """Yield (record time, topic, message type, data) of ``topics`` with record time in
        [start, stop), in record-time order."""
        chans = {cid: (c.topic, c.name) for cid, c in self.connections.items() if c.topic in topics}
        with open(self.path, "rb") as f:
            yield from in_time_order(self.chunks, set(chans), start, stop, lambda ref: self._chunk_messages(f, ref, chans))

    def _chunk_messages(self, f, ref: ChunkRef, chans: dict[int, tuple[str, str]]) -> Iterator[tuple[int, str, str, memoryview]]:
        f.seek(ref.offset)
        raw = memoryview(f.read(ref.length))
        (head, data), = _records(raw)
        body = _decompress(bytes(head["compression"]).decode(), data, _U32.unpack(head["size"])[0])
        for h, d in _records(body):
            if h["op"][0] == OP_MSG:
                conn = _U32.unpack(h["conn"])[0]
                if conn in chans:
                    sec, nsec = _TIME.unpack(h["time"])
                    yield (sec * 1_000_000_000 + nsec, *chans[conn], d)
