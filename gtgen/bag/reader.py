"""Open any flavour of bag and stream decoded messages in time order.

Flavours: ROS 1 ``.bag`` (any chunk compression), rosbag2 folders (mcap or sqlite3),
bare ``.mcap`` (ros2msg or ros1msg) and bare ``.db3``. Messages are decoded from the
definitions stored in the bag; bags without definitions fall back to the standard ROS
types plus gtgen's grid_map_msgs.

Bare ``.mcap`` files are read chunk by chunk from their summary's chunk index (see
``_chunk_messages``; the mcap library's reader where a file has no index), so a time
range decompresses only the chunks that overlap it; everything else goes through
rosbags' AnyReader.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from gtgen.bag.msgdefs import typestore
from gtgen.errors import BagError, InputNotFoundError

log = logging.getLogger(__name__)

SUFFIXES = (".bag", ".mcap", ".db3")


@dataclass(frozen=True)
class TopicInfo:
    """A topic in a set of bags: its message type and message count."""

    msgtype: str
    count: int


def _check_path(path: Path) -> None:
    if not path.exists():
        raise InputNotFoundError(f"bag '{path}' does not exist")
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise BagError(f"folder '{path}' is not a rosbag2 recording (no metadata.yaml)")
        return
    if path.suffix not in SUFFIXES:
        raise BagError(f"bag '{path}' has suffix {path.suffix!r}; expected one of {list(SUFFIXES)} or a rosbag2 folder")
    if path.stat().st_size == 0:
        raise BagError(f"bag '{path}' is empty (0 bytes)")


def _mcap_profile(path: Path) -> str:
    """Return the schema encoding of a bare .mcap ('ros1msg', 'ros2msg', ...)."""
    from mcap.reader import make_reader

    try:
        with path.open("rb") as f:
            summary = make_reader(f).get_summary()
    except Exception as err:  # noqa: BLE001 - mcap raises several types for bad files
        raise BagError(f"bag '{path}' is truncated or corrupt: {err}".splitlines()[0]) from err
    if summary is None or not summary.schemas:
        return "ros2msg"
    return next(iter(summary.schemas.values())).encoding


class BagSet:
    """One drive's bags, opened together and streamed as one time-ordered sequence.

    Use as a context manager. ``ros1`` tells which wire format the messages use.
    """

    def __init__(self, paths: list[Path]) -> None:
        if not paths:
            raise BagError("no bag given; expected one or more .bag, .mcap, .db3 files or rosbag2 folders")
        self.paths = [Path(p) for p in paths]
        for p in self.paths:
            _check_path(p)
        kinds = {p.suffix == ".bag" for p in self.paths}
        if len(kinds) > 1:
            raise BagError("cannot mix ROS 1 .bag files with ROS 2 bags in one drive: " + ", ".join(map(str, self.paths)))
        mcaps = [p for p in self.paths if p.suffix == ".mcap" and p.is_file()]
        self._ros1_mcap = bool(mcaps) and all(_mcap_profile(p) == "ros1msg" for p in mcaps)
        if mcaps and not self._ros1_mcap and any(_mcap_profile(p) == "ros1msg" for p in mcaps):
            raise BagError("cannot mix ros1msg and ros2msg .mcap files in one drive")
        self.ros1 = self.paths[0].suffix == ".bag" or self._ros1_mcap
        self._bare_mcap = bool(mcaps) and len(mcaps) == len(self.paths)
        self._reader = None
        self._mcap_files: list = []
        self._mcap_readers: list = []

    def __enter__(self) -> BagSet:
        if self._ros1_mcap:
            self._open_ros1_mcap()
            return self
        from rosbags.highlevel import AnyReader

        try:
            self._reader = AnyReader(self.paths, default_typestore=typestore(self.ros1))
            self._reader.open()
        except Exception as err:  # noqa: BLE001 - rosbags raises many types on bad input
            self._reader = None
            raise BagError(f"cannot open {self._names()}: {err}".splitlines()[0]) from err
        if self._bare_mcap:
            self._open_mcap_readers()
        return self

    def _open_mcap_readers(self) -> None:
        from mcap.reader import make_reader

        for p in self.paths:
            f = p.open("rb")
            self._mcap_files.append(f)
            try:
                self._mcap_readers.append(make_reader(f))
            except Exception as err:  # noqa: BLE001 - mcap raises several types for bad files
                raise BagError(f"bag '{p}' is truncated or corrupt: {err}".splitlines()[0]) from err

    def __exit__(self, *exc: object) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        for f in self._mcap_files:
            f.close()
        self._mcap_files = []
        self._mcap_readers = []

    def _names(self) -> str:
        return ", ".join(f"'{p}'" for p in self.paths)

    # -- ros1msg-encoded bare MCAP: rosbags' rosbag2 reader only knows ROS 2 schemas --
    def _open_ros1_mcap(self) -> None:
        from rosbags.typesys import get_types_from_msg

        self._store = typestore(True)
        self._topics: dict[str, TopicInfo] = {}
        self._span = [None, None]
        self._open_mcap_readers()
        for p, reader in zip(self.paths, self._mcap_readers):
            summary = reader.get_summary()
            if summary is None:
                raise BagError(f"bag '{p}' has no summary section (truncated?)")
            for sch in summary.schemas.values():
                if sch.name not in self._store.types:
                    self._store.register(get_types_from_msg(sch.data.decode(), sch.name))
            stats = summary.statistics.channel_message_counts if summary.statistics else {}
            if summary.statistics and summary.statistics.message_count:
                lo, hi = summary.statistics.message_start_time, summary.statistics.message_end_time + 1
                self._span = [lo if self._span[0] is None else min(self._span[0], lo), hi if self._span[1] is None else max(self._span[1], hi)]
            for cid, ch in summary.channels.items():
                name = summary.schemas[ch.schema_id].name
                old = self._topics.get(ch.topic)
                self._topics[ch.topic] = TopicInfo(name, (old.count if old else 0) + stats.get(cid, 0))

    def topics(self) -> dict[str, TopicInfo]:
        """Return every topic of the bags with its type and count."""
        if self._ros1_mcap:
            return dict(self._topics)
        assert self._reader is not None, "BagSet is not open"
        out: dict[str, TopicInfo] = {}
        for c in self._reader.connections:
            old = out.get(c.topic)
            out[c.topic] = TopicInfo(c.msgtype, (old.count if old else 0) + c.msgcount)
        return out

    def time_range(self) -> tuple[int, int]:
        """Return [start, stop) of the record times [ns] of all messages."""
        if self._ros1_mcap:
            if self._span[0] is None:
                return 0, 0
            return int(self._span[0]), int(self._span[1])
        assert self._reader is not None, "BagSet is not open"
        if not any(c.msgcount for c in self._reader.connections):
            return 0, 0
        return int(self._reader.start_time), int(self._reader.end_time)

    def messages(self, topics: list[str], start: int | None = None, stop: int | None = None
                 ) -> Iterator[tuple[str, str, int, object | None, str | None]]:
        """Yield (topic, msgtype, record time [ns], message, error) in record-time order.

        Only messages with ``start <= record time < stop`` are read when given. A message
        that fails to decode yields ``None`` and the error text, so callers can count
        decode failures instead of stopping.
        """
        wanted = set(topics)
        if self._mcap_readers:
            yield from self._mcap_messages(wanted, start, stop)
            return
        assert self._reader is not None, "BagSet is not open"
        conns = [c for c in self._reader.connections if c.topic in wanted]
        if not conns:
            return
        it = self._reader.messages(connections=conns, start=start, stop=stop)
        while True:
            try:
                conn, t, raw = next(it)
            except StopIteration:
                return
            except Exception as err:  # noqa: BLE001 - truncated chunks raise various errors
                raise BagError(f"{self._names()} is truncated or corrupt: {err}".splitlines()[0]) from err
            try:
                msg = self._reader.deserialize(raw, conn.msgtype)
            except Exception as err:  # noqa: BLE001 - a bad message is counted, not fatal
                yield conn.topic, conn.msgtype, t, None, str(err).splitlines()[0] if str(err) else type(err).__name__
                continue
            yield conn.topic, conn.msgtype, t, msg, None

    def _mcap_messages(self, wanted: set[str], start: int | None, stop: int | None) -> Iterator:
        import heapq

        if self._ros1_mcap:
            decode = self._store.deserialize_ros1
        else:
            assert self._reader is not None
            decode = self._reader.deserialize

        def one(f, reader) -> Iterator:
            summary = reader.get_summary()
            if summary is not None and summary.chunk_indexes:
                yield from _chunk_messages(f, summary, wanted, start, stop)
                return
            for sch, ch, m in reader.iter_messages(topics=list(wanted), starting_at=start, ending_before=stop, log_time_order=True):
                yield m.log_time, ch.topic, sch.name, m.data

        try:
            for t, topic, name, data in heapq.merge(*(one(f, r) for f, r in zip(self._mcap_files, self._mcap_readers)), key=lambda x: x[0]):
                try:
                    msg = decode(data, name)
                except Exception as err:  # noqa: BLE001 - a bad message is counted, not fatal
                    yield topic, name, t, None, str(err).splitlines()[0] if str(err) else type(err).__name__
                    continue
                yield topic, name, t, msg, None
        except Exception as err:  # noqa: BLE001 - truncated chunks raise various errors
            raise BagError(f"{self._names()} is truncated or corrupt: {err}".splitlines()[0]) from err


# -- MCAP chunks, read directly --------------------------------------------------------
# The mcap library parses every record through a small-read stream wrapper: about a
# quarter of the time of a pass over a bag. Here each chunk the summary indexes is read
# with one read and one decompression, its records split with struct on a memoryview (no
# copies). Chunks may overlap in record time (recorders write in arrival order), so they
# are taken in order of their first record time and their messages merged on a heap,
# released once no later chunk can hold an earlier message (as the mcap library does).
_OP_MESSAGE = 0x05
_REC = struct.Struct("<BQ")
_MSG = struct.Struct("<HIQQ")
_CHUNK = struct.Struct("<QQQI")


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


def _read_chunk(f, ci) -> memoryview:
    """Return the uncompressed records of the chunk that ``ci`` (a ChunkIndex) points to."""
    f.seek(ci.chunk_start_offset)
    raw = memoryview(f.read(ci.chunk_length))
    if len(raw) != ci.chunk_length or raw[0] != 0x06:
        raise BagError(f"MCAP chunk at byte {ci.chunk_start_offset} is cut short or not a chunk")
    pos = 9 + _CHUNK.size
    n = int.from_bytes(raw[pos : pos + 4], "little")
    kind = str(raw[pos + 4 : pos + 4 + n], "utf-8")
    pos += 4 + n
    m = int.from_bytes(raw[pos : pos + 8], "little")
    return memoryview(_decompress(kind, raw[pos + 8 : pos + 8 + m], ci.uncompressed_size))


def _chunk_messages(f, summary, topics: set[str], start: int | None, stop: int | None) -> Iterator:
    """Yield (record time, topic, schema name, data) of ``topics`` with record time in
    [start, stop), in record-time order (ties in file order), from an indexed MCAP file."""
    import heapq

    chans = {cid: (ch.topic, summary.schemas[ch.schema_id].name if ch.schema_id else "")
             for cid, ch in summary.channels.items() if ch.topic in topics}
    lo = -1 if start is None else start
    hi = 1 << 64 if stop is None else stop
    cis = sorted((ci for ci in summary.chunk_indexes
                  if ci.message_end_time >= lo and ci.message_start_time < hi and any(c in chans for c in ci.message_index_offsets)),
                 key=lambda ci: (ci.message_start_time, ci.chunk_start_offset))
    heap: list = []
    seq = 0
    for ci in cis:
        while heap and heap[0][0] < ci.message_start_time:
            t, _, topic, name, data = heapq.heappop(heap)
            yield t, topic, name, data
        data = _read_chunk(f, ci)
        p, end = 0, len(data)
        while p < end:
            op, length = _REC.unpack_from(data, p)
            p += 9
            if op == _OP_MESSAGE:
                cid, _, t, _ = _MSG.unpack_from(data, p)
                if cid in chans and lo <= t < hi:
                    heapq.heappush(heap, (t, seq, *chans[cid], data[p + 22 : p + length]))
                    seq += 1
            p += length
        if p != end:
            raise BagError(f"MCAP chunk at byte {ci.chunk_start_offset} has a record running past its end")
    while heap:
        t, _, topic, name, data = heapq.heappop(heap)
        yield t, topic, name, data


def stamp_ns(header: object) -> int:
    """Return the header stamp [ns] of a std_msgs/Header."""
    st = header.stamp  # type: ignore[attr-defined]
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)
