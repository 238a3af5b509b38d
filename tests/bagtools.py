"""Make tiny bags for tests: rewrite a drive's MCAP or ROS 1 bag with edits, through rosbags'
own writers."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterable
from pathlib import Path

from rosbags.rosbag1 import Reader as Reader1
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Reader, Writer
from rosbags.rosbag2.enums import StoragePlugin

from gtgen.bag.msgdefs import typestore

Edit = Callable[[str, int, object], Iterable[tuple[int, object]]]


def rewrite_mcap(src: Path, dst: Path, edit: Edit) -> Path:
    """Write ``dst`` (bare .mcap) with every message of ``src`` passed through ``edit``.

    ``edit(topic, record_time, msg)`` yields (record_time, msg) pairs: none drops the
    message, several duplicate it.
    """
    store = typestore(False)
    tmp = dst.parent / (dst.stem + "_rosbag2")
    shutil.rmtree(tmp, ignore_errors=True)
    with Reader(src) as r, Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for c in r.connections:
            conns[c.id] = w.add_connection(c.topic, c.msgtype, typestore=store)
        for c, t, raw in r.messages():
            msg = store.deserialize_cdr(raw, c.msgtype)
            for t2, m2 in edit(c.topic, t, msg):
                w.write(conns[c.id], t2, store.serialize_cdr(m2, c.msgtype))
    mcap = next(tmp.glob("*.mcap"))
    mcap.rename(dst)
    shutil.rmtree(tmp)
    return dst


def rewrite_bag(src: Path, dst: Path, edit: Edit) -> Path:
    """Write the ROS 1 bag ``dst`` with every message of the ROS 1 bag ``src`` passed
    through ``edit`` (as ``rewrite_mcap``; messages carry ROS 1 field names)."""
    store = typestore(True)
    with Reader1(src) as r, Writer1(dst) as w:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, typestore=store) for c in r.connections}
        for c, t, raw in r.messages():
            msg = store.deserialize_ros1(raw, c.msgtype)
            for t2, m2 in edit(c.topic, t, msg):
                w.write(conns[c.id], t2, store.serialize_ros1(m2, c.msgtype))
    return dst


def rewrite(src: Path, dst: Path, edit: Edit) -> Path:
    """Rewrite ``src`` into ``dst`` of the same flavour (.mcap or ROS 1 .bag) through ``edit``."""
    return (rewrite_bag if src.suffix == ".bag" else rewrite_mcap)(src, dst, edit)


def split_mcap(src: Path, first: Path, second: Path, after_s: float) -> tuple[Path, Path]:
    """Split a drive into two bare .mcap files at ``after_s`` seconds (tf_static in both)."""
    t0: list[int] = []

    def head(topic, t, msg):
        t0.append(t) if not t0 else None
        if t < t0[0] + after_s * 1e9:
            yield t, msg

    def tail(topic, t, msg):
        if t >= t0[0] + after_s * 1e9 or topic == "/tf_static":
            yield t, msg

    return rewrite_mcap(src, first, head), rewrite_mcap(src, second, tail)
