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
from dataclasses import dataclass
from pathlib import Path

from gtgen.bag.mcap import McapFile, profile
from gtgen.bag.msgdefs import typestore, typestore_of
from gtgen.errors import BagError, InputNotFoundError

log = logging.getLogger(__name__)

SUFFIXES = (".bag", ".mcap", ".db3")

Message = tuple[str, str, int, object | None, str | None]  # topic, msgtype, record time [ns], message, error


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


class BagSet:
    """One drive's bags, opened together and streamed as one time-ordered sequence.

    Use as a context manager. ``ros1`` tells which wire format the messages use;
    ``warnings`` lists what was recovered from bags cut short.
    """

    def __init__(self, paths: list[Path]) -> None:
        if not paths:
            raise BagError("no bag given; expected one or more .bag, .mcap, .db3 files or rosbag2 folders")
        self.paths = [Path(p) for p in paths]
        for p in self.paths:
            _check_path(p)
        if len({p.suffix == ".bag" for p in self.paths}) > 1:
            raise BagError("cannot mix ROS 1 .bag files with ROS 2 bags in one drive: " + ", ".join(map(str, self.paths)))
        self._bare_mcap = all(p.suffix == ".mcap" and p.is_file() for p in self.paths)
        if not self._bare_mcap and any(p.suffix == ".mcap" and p.is_file() for p in self.paths):
            raise BagError("cannot mix bare .mcap files with other bags in one drive: " + ", ".join(map(str, self.paths)))
        ros1 = {profile(p) == "ros1msg" for p in self.paths} if self._bare_mcap else {self.paths[0].suffix == ".bag"}
        if len(ros1) > 1:
            raise BagError("cannot mix ros1msg and ros2msg .mcap files in one drive")
        self.ros1 = ros1.pop()
        self.warnings: list[str] = []
        self._reader = None
        self._mcaps: list[McapFile] = []
        self._store = None

    def __enter__(self) -> BagSet:
        if self._bare_mcap:
            self._mcaps = [McapFile.open(p) for p in self.paths]
            self._store = typestore_of([s for m in self._mcaps for s in m.schemas.values()], self.ros1)
            self.warnings = [f"bag '{m.path}' is cut short: read every complete chunk, {m.lost_bytes} bytes after the cut lost"
                             for m in self._mcaps if m.lost_bytes]
            return self
        from rosbags.highlevel import AnyReader

        try:
            self._reader = AnyReader(self.paths, default_typestore=typestore(self.ros1))
            self._reader.open()
        except Exception as err:  # noqa: BLE001 - rosbags raises many types on bad input
            self._reader = None
            raise BagError(f"cannot open {self._names()}: {_first_line(err)}") from err
        return self

    def __exit__(self, *exc: object) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        self._mcaps = []

    def _names(self) -> str:
        return ", ".join(f"'{p}'" for p in self.paths)

    def topics(self) -> dict[str, TopicInfo]:
        """Return every topic of the bags with its type and count."""
        out: dict[str, TopicInfo] = {}

        def add(topic: str, msgtype: str, n: int) -> None:
            old = out.get(topic)
            out[topic] = TopicInfo(msgtype, (old.count if old else 0) + n)

        for m in self._mcaps:
            for cid, (topic, sid) in m.channels.items():
                add(topic, m.schemas[sid].name if sid in m.schemas else "", m.counts.get(cid, 0))
        if self._reader is not None:
            for c in self._reader.connections:
                add(c.topic, c.msgtype, c.msgcount)
        return out

    def time_range(self) -> tuple[int, int]:
        """Return [start, stop) of the record times [ns] of all messages."""
        if self._mcaps:
            spans = [m.time_range() for m in self._mcaps]
            return min(s[0] for s in spans), max(s[1] for s in spans)
        assert self._reader is not None, "BagSet is not open"
        if not any(c.msgcount for c in self._reader.connections):
            return 0, 0
        return int(self._reader.start_time), int(self._reader.end_time)

    def messages(self, topics: list[str], start: int | None = None, stop: int | None = None) -> Iterator[Message]:
        """Yield (topic, msgtype, record time [ns], message, error) in record-time order.

        Only messages with ``start <= record time < stop`` are read when given. A message
        that fails to decode yields ``None`` and the error text, so callers can count
        decode failures instead of stopping.
        """
        if self._mcaps:
            yield from self._mcap_messages(set(topics), start, stop)
            return
        assert self._reader is not None, "BagSet is not open"
        conns = [c for c in self._reader.connections if c.topic in set(topics)]
        if not conns:
            return
        it = self._reader.messages(connections=conns, start=start, stop=stop)
        while True:
            try:
                conn, t, raw = next(it)
            except StopIteration:
                return
            except Exception as err:  # noqa: BLE001 - truncated chunks raise various errors
                raise BagError(f"{self._names()} is truncated or corrupt: {_first_line(err)}") from err
            try:
                msg = self._reader.deserialize(raw, conn.msgtype)
            except Exception as err:  # noqa: BLE001 - a bad message is counted, not fatal
                yield conn.topic, conn.msgtype, t, None, _first_line(err)
                continue
            yield conn.topic, conn.msgtype, t, msg, None

    def _mcap_messages(self, wanted: set[str], start: int | None, stop: int | None) -> Iterator[Message]:
        assert self._store is not None, "BagSet is not open"
        decode = self._store.deserialize_ros1 if self.ros1 else self._store.deserialize_cdr
        streams = [m.messages(wanted, start, stop) for m in self._mcaps]
        try:
            for t, topic, name, data in heapq.merge(*streams, key=lambda x: x[0]):
                try:
                    msg = decode(data, name)
                except Exception as err:  # noqa: BLE001 - a bad message is counted, not fatal
                    yield topic, name, t, None, _first_line(err)
                    continue
                yield topic, name, t, msg, None
        except BagError:
            raise
        except Exception as err:  # noqa: BLE001 - damaged chunks raise various errors
            raise BagError(f"{self._names()} is truncated or corrupt: {_first_line(err)}") from err


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
