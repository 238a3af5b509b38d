"""Open any flavour of bag and stream decoded messages in time order.

Flavours: ROS 1 ``.bag`` (any chunk compression), rosbag2 folders (mcap or sqlite3),
bare ``.mcap`` (ros2msg via rosbags, ros1msg via the mcap library) and bare ``.db3``.
Messages are decoded from the definitions stored in the bag; bags without definitions
fall back to the standard ROS types plus gtgen's grid_map_msgs.
"""

from __future__ import annotations

import logging
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
        self._reader = None
        self._mcap_files: list = []

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
        return self

    def __exit__(self, *exc: object) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        for f in self._mcap_files:
            f.close()
        self._mcap_files = []

    def _names(self) -> str:
        return ", ".join(f"'{p}'" for p in self.paths)

    # -- ros1msg-encoded bare MCAP: rosbags' rosbag2 reader only knows ROS 2 schemas --
    def _open_ros1_mcap(self) -> None:
        from mcap.reader import make_reader
        from rosbags.typesys import get_types_from_msg

        self._store = typestore(True)
        self._topics: dict[str, TopicInfo] = {}
        for p in self.paths:
            f = p.open("rb")
            self._mcap_files.append(f)
            summary = make_reader(f).get_summary()
            if summary is None:
                raise BagError(f"bag '{p}' has no summary section (truncated?)")
            for sch in summary.schemas.values():
                if sch.name not in self._store.types:
                    self._store.register(get_types_from_msg(sch.data.decode(), sch.name))
            stats = summary.statistics.channel_message_counts if summary.statistics else {}
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

    def messages(self, topics: list[str]) -> Iterator[tuple[str, str, int, object | None, str | None]]:
        """Yield (topic, msgtype, record time [ns], message, error) in record-time order.

        A message that fails to decode yields ``None`` and the error text, so callers
        can count decode failures instead of stopping.
        """
        wanted = set(topics)
        if self._ros1_mcap:
            yield from self._ros1_mcap_messages(wanted)
            return
        assert self._reader is not None, "BagSet is not open"
        conns = [c for c in self._reader.connections if c.topic in wanted]
        if not conns:
            return
        it = self._reader.messages(connections=conns)
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

    def _ros1_mcap_messages(self, wanted: set[str]) -> Iterator:
        import heapq

        from mcap.reader import make_reader

        def one(f) -> Iterator:
            f.seek(0)
            for sch, ch, m in make_reader(f).iter_messages(topics=list(wanted), log_time_order=True):
                yield m.log_time, ch.topic, sch.name, m.data

        try:
            for t, topic, name, data in heapq.merge(*(one(f) for f in self._mcap_files), key=lambda x: x[0]):
                try:
                    msg = self._store.deserialize_ros1(data, name)
                except Exception as err:  # noqa: BLE001
                    yield topic, name, t, None, str(err).splitlines()[0]
                    continue
                yield topic, name, t, msg, None
        except Exception as err:  # noqa: BLE001
            raise BagError(f"{self._names()} is truncated or corrupt: {err}".splitlines()[0]) from err


def stamp_ns(header: object) -> int:
    """Return the header stamp [ns] of a std_msgs/Header."""
    st = header.stamp  # type: ignore[attr-defined]
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)
