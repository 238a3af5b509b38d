"""Open any flavour of bag and stream decoded messages in record-time order.

Flavours: ROS 1 ``.bag`` (any chunk compression), rosbag2 folders (mcap or sqlite3) and
bare ``.db3`` through rosbags' AnyReader; bare ``.mcap`` (ros2msg or ros1msg) through
``gtgen.bag.mcap``, which reads a time range by decompressing only the chunks that
overlap it. Messages are decoded from the definitions stored in the bag; bags without
definitions fall back to the standard ROS types plus gtgen's grid_map_msgs.
"""

from __future__ import annotations

import hashlib
import heapq
import logging
from collections.abc import Iterator
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from types import SimpleNamespace

import google_crc32c

from gtgen.bag.mcap import McapFile, profile
from gtgen.bag.msgdefs import typestore, typestore_of
from gtgen.errors import BagError, InputNotFoundError

log = logging.getLogger(__name__)

SUFFIXES = (".bag", ".mcap", ".db3")

Message = tuple[str, str, int, object | None, str | None]  # topic, msgtype, record time [ns], message, error
Digest = tuple[int, int]  # (crc32c, length) of a message's serialized bytes
Record = tuple[str, str, int, object | None, str | None, Digest | None]  # a Message and its digest


def detached(msg: object) -> object:
    """Return a decoded message as nested ``SimpleNamespace`` objects with the same
    attributes (arrays and plain values as they are), to keep or hand to another process.
    rosbags generates a message's class into one module, ``rosbags.usertypes``, which every
    new typestore replaces: a message object pickled in a worker unpickles in the parent
    only while the parent's module holds that class."""
    if is_dataclass(msg) and not isinstance(msg, type):
        return SimpleNamespace(**{f.name: detached(getattr(msg, f.name)) for f in fields(msg)})
    if isinstance(msg, list):
        return [detached(x) for x in msg]
    return msg


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


def _first_line(err: BaseException) -> str:
    return str(err).splitlines()[0] if str(err) else type(err).__name__


def digest(raw: bytes | memoryview) -> Digest:
    """Return the (crc32c, length) of serialized message bytes: with the header stamp, what
    tells a message recorded twice from another (crc32c: about 8 GB/s with the copy that
    google_crc32c needs of a memoryview)."""
    return google_crc32c.value(raw if isinstance(raw, bytes) else bytes(raw)), len(raw)


class _Rosbags:
    """Bags read through rosbags' AnyReader (with their index)."""

    def __init__(self, paths: list[Path], ros1: bool) -> None:
        from rosbags.highlevel import AnyReader

        self.paths = paths
        self.reader = AnyReader(paths, default_typestore=typestore(ros1))
        self.reader.open()

    def close(self) -> None:
        self.reader.close()

    def topics(self) -> Iterator[tuple[str, str, int]]:
        for c in self.reader.connections:
            yield c.topic, c.msgtype, c.msgcount

    def time_range(self) -> tuple[int, int] | None:
        if not any(c.msgcount for c in self.reader.connections):
            return None
        return int(self.reader.start_time), int(self.reader.end_time)

    def messages(self, topics: set[str], start: int | None, stop: int | None, digests: bool) -> Iterator[Record]:
        conns = [c for c in self.reader.connections if c.topic in topics]
        if not conns:
            return
        it = self.reader.messages(connections=conns, start=start, stop=stop)
        while True:
            try:
                conn, t, raw = next(it)
            except StopIteration:
                return
            except Exception as err:  # noqa: BLE001 - damaged chunks raise various errors
                raise BagError(f"{_names(self.paths)} is truncated or corrupt: {_first_line(err)}") from err
            d = digest(raw) if digests else None
            try:
                yield conn.topic, conn.msgtype, t, self.reader.deserialize(raw, conn.msgtype), None, d
            except Exception as err:  # noqa: BLE001 - a bad message is counted, not fatal
                yield conn.topic, conn.msgtype, t, None, _first_line(err), d


class _Chunked:
    """Bags read chunk by chunk by gtgen's own readers: bare MCAP files (``mcap``), and ROS 1
    bags that rosbags cannot open because they were cut short (``rosbag1``)."""

    def __init__(self, files: list, ros1: bool) -> None:
        self.files = files
        schemas = [s for f in files for s in (f.schemas.values() if isinstance(f, McapFile) else f.connections.values())]
        store = typestore_of(schemas, ros1)
        self.decode = store.deserialize_ros1 if ros1 else store.deserialize_cdr

    def close(self) -> None:
        self.files = []

    def topics(self) -> Iterator[tuple[str, str, int]]:
        for f in self.files:
            if isinstance(f, McapFile):
                for cid, (topic, sid) in f.channels.items():
                    yield topic, f.schemas[sid].name if sid in f.schemas else "", f.counts.get(cid, 0)
            else:
                for cid, c in f.connections.items():
                    yield c.topic, c.name, f.counts.get(cid, 0)

    def time_range(self) -> tuple[int, int] | None:
        spans = [f.time_range() for f in self.files]
        return (min(s[0] for s in spans), max(s[1] for s in spans)) if spans else None

    def messages(self, topics: set[str], start: int | None, stop: int | None, digests: bool) -> Iterator[Record]:
        streams = [f.messages(topics, start, stop) for f in self.files]
        try:
            for t, topic, name, data in heapq.merge(*streams, key=lambda x: x[0]):
                d = digest(data) if digests else None
                try:
                    msg = self.decode(data, name)
                except Exception as err:  # noqa: BLE001 - a bad message is counted, not fatal
                    yield topic, name, t, None, _first_line(err), d
                    continue
                yield topic, name, t, msg, None, d
        except BagError:
            raise
        except Exception as err:  # noqa: BLE001 - damaged chunks raise various errors
            raise BagError(f"{_names([f.path for f in self.files])} is truncated or corrupt: {_first_line(err)}") from err


def _names(paths: list[Path]) -> str:
    return ", ".join(f"'{p}'" for p in paths)


class BagSet:
    """One drive's bags, opened together and streamed as one time-ordered sequence.

    Use as a context manager. ``ros1`` tells which wire format the messages use;
    ``warnings`` names the bags that were cut short and what of them was lost.
    """

    def __init__(self, paths: list[Path]) -> None:
        if not paths:
            raise BagError("no bag given; expected one or more .bag, .mcap, .db3 files or rosbag2 folders")
        self.paths = [Path(p) for p in paths]
        for p in self.paths:
            _check_path(p)
        if len({p.suffix == ".bag" for p in self.paths}) > 1:
            raise BagError("cannot mix ROS 1 .bag files with ROS 2 bags in one drive: " + _names(self.paths))
        self._bare_mcap = all(p.suffix == ".mcap" and p.is_file() for p in self.paths)
        if not self._bare_mcap and any(p.suffix == ".mcap" and p.is_file() for p in self.paths):
            raise BagError("cannot mix bare .mcap files with other bags in one drive: " + _names(self.paths))
        ros1 = {profile(p) == "ros1msg" for p in self.paths} if self._bare_mcap else {self.paths[0].suffix == ".bag"}
        if len(ros1) > 1:
            raise BagError("cannot mix ros1msg and ros2msg .mcap files in one drive")
        self.ros1 = ros1.pop()
        self.warnings: list[str] = []
        self._sources: list = []

    def __enter__(self) -> BagSet:
        try:
            if self._bare_mcap:
                self._add_chunked([McapFile.open(p) for p in self.paths])
            else:
                self._open_rosbags()
        except BaseException:
            self.__exit__()
            raise
        return self

    def _open_rosbags(self) -> None:
        try:
            self._sources.append(_Rosbags(self.paths, self.ros1))
            return
        except Exception as err:  # noqa: BLE001 - rosbags raises many types on bad input
            first = err
        # ROS 1 bags cut short have no index: those rosbags refuses are walked instead
        healthy, cut = [], []
        for p in self.paths:
            try:
                _Rosbags([p], self.ros1).close()
                healthy.append(p)
            except Exception:  # noqa: BLE001 - any reason rosbags gives
                cut.append(p)
        if not cut or not all(p.suffix == ".bag" for p in cut):
            raise BagError(f"cannot open {_names(self.paths)}: {_first_line(first)}") from first
        from gtgen.bag.rosbag1 import Ros1File

        self._add_chunked([Ros1File.open(p) for p in cut])
        if healthy:
            self._sources.append(_Rosbags(healthy, self.ros1))

    def _add_chunked(self, files: list) -> None:
        self._sources.append(_Chunked(files, self.ros1))
        self.warnings += [f"bag '{f.path}' is cut short: read every complete chunk, {f.lost_bytes} bytes after the cut lost"
                          for f in files if f.lost_bytes]

    def __exit__(self, *exc: object) -> None:
        for s in self._sources:
            s.close()
        self._sources = []

    def topics(self) -> dict[str, TopicInfo]:
        """Return every topic of the bags with its type and count."""
        out: dict[str, TopicInfo] = {}
        for s in self._sources:
            for topic, msgtype, n in s.topics():
                old = out.get(topic)
                out[topic] = TopicInfo(msgtype, (old.count if old else 0) + n)
        return out

    def time_range(self) -> tuple[int, int]:
        """Return [start, stop) of the record times [ns] of all messages."""
        spans = [r for r in (s.time_range() for s in self._sources) if r is not None]
        return (min(s[0] for s in spans), max(s[1] for s in spans)) if spans else (0, 0)

    def messages(self, topics: list[str], start: int | None = None, stop: int | None = None) -> Iterator[Message]:
        """Yield (topic, msgtype, record time [ns], message, error) in record-time order.

        Only messages with ``start <= record time < stop`` are read when given. A message
        that fails to decode yields ``None`` and the error text, so callers can count
        decode failures instead of stopping.
        """
        for r in self._stream(topics, start, stop, False):
            yield r[:5]

    def records(self, topics: list[str], start: int | None = None, stop: int | None = None) -> Iterator[Record]:
        """Yield what ``messages`` yields and the ``digest`` of each message's bytes."""
        yield from self._stream(topics, start, stop, True)

    def _stream(self, topics: list[str], start: int | None, stop: int | None, digests: bool) -> Iterator[Record]:
        streams = [s.messages(set(topics), start, stop, digests) for s in self._sources]
        yield from streams[0] if len(streams) == 1 else heapq.merge(*streams, key=lambda m: m[2])


def stamp_ns(header: object) -> int:
    """Return the header stamp [ns] of a std_msgs/Header."""
    st = header.stamp  # type: ignore[attr-defined]
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def hash_bag(path: Path) -> str:
    """Return the sha256 of a bag file, or of a rosbag2 folder's files in name order."""
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    buf = bytearray(1 << 20)  # one reused buffer: fresh blocks cost page faults
    view = memoryview(buf)
    for f in files:
        with f.open("rb", buffering=0) as fh:
            while n := fh.readinto(buf):
                h.update(view[:n])
    return h.hexdigest()
