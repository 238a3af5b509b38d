"""The hand-written MCAP reader against the mcap library (the oracle): every message, in
the same order, from indexed files and from files walked record by record."""

from __future__ import annotations

import numpy as np
import pytest

from gtgen.bag.mcap import McapFile


def _lib_messages(path, topics, start, stop):
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(m.log_time, ch.topic, bytes(m.data)) for _, ch, m in make_reader(f).iter_messages(
            topics=sorted(topics), starting_at=start, ending_before=stop, log_time_order=True)]


def _direct_messages(path, topics, start, stop):
    return [(t, topic, bytes(d)) for t, topic, _, d in McapFile.open(path).messages(set(topics), start, stop)]


def _write(path, compression, index=True):
    from mcap.writer import CompressionType, IndexType, Writer

    rng = np.random.default_rng(3)
    with path.open("wb") as f:
        w = Writer(f, chunk_size=300, compression=CompressionType[compression.upper()],
                   index_types=IndexType.ALL if index else IndexType.NONE, use_summary_offsets=index)
        w.start()
        sid = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        chans = [w.register_channel(f"/t{i}", "cdr", sid) for i in range(3)]
        t = np.sort(rng.integers(0, 2000, 400)) + rng.integers(-30, 30, 400)  # jittered: chunks overlap
        for k, tk in enumerate(t):
            w.add_message(chans[k % 3], log_time=int(tk) + 1000, data=rng.bytes(int(rng.integers(1, 90))), publish_time=0)
        w.finish()
    return path


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_direct_mcap_reader_matches_mcap_library(tmp_path, compression):
    """Chunks that overlap in record time, messages out of order inside a chunk, ties,
    time ranges and topic subsets: the same messages in the same order as the library,
    whether the chunks come from the summary's index or from walking the file."""
    indexed = _write(tmp_path / f"x_{compression}.mcap", compression)
    walked = _write(tmp_path / f"y_{compression}.mcap", compression, index=False)
    assert not McapFile.open(walked).lost_bytes
    for topics, start, stop in [({"/t0", "/t1", "/t2"}, None, None), ({"/t1"}, None, None), ({"/t0", "/t2"}, 1500, 2500)]:
        ref = _lib_messages(indexed, topics, start, stop)
        assert ref and _direct_messages(indexed, topics, start, stop) == ref
        assert _direct_messages(walked, topics, start, stop) == ref


def test_direct_mcap_reader_on_a_synth_bag(drive_dir):
    topics = {"/xracer/odometry", "/xracer/map/micro", "/cam_front/image/compressed"}
    assert _direct_messages(drive_dir / "drive.mcap", topics, None, None) == _lib_messages(drive_dir / "drive.mcap", topics, None, None)


def _rosbags_messages(path, ros1=True):
    from rosbags.highlevel import AnyReader

    from gtgen.bag.msgdefs import typestore

    with AnyReader([path], default_typestore=typestore(ros1)) as r:
        return [(t, c.topic, bytes(raw)) for c, t, raw in r.messages()]


def test_ros1_bag_cut_short_is_read_up_to_the_cut(drive_dir, tmp_path):
    """The walker reads a whole bag as rosbags does, and a bag cut anywhere after its first
    chunk as rosbags reads the messages of the chunks before the cut."""
    from gtgen.bag.rosbag1 import Ros1File

    full = drive_dir / "drive.bag"
    ref = _rosbags_messages(full)
    whole = Ros1File.open(full)
    assert whole.lost_bytes == 0
    topics = {c.topic for c in whole.connections.values()}
    got = [(t, topic, bytes(d)) for t, topic, _, d in whole.messages(topics, None, None)]
    assert sorted(got) == sorted(ref) and [m[0] for m in got] == sorted(m[0] for m in got)
    data = full.read_bytes()
    first = whole.chunks[0].offset + whole.chunks[0].length
    for cut in np.random.default_rng(1).integers(first + 1, len(data), 4):
        bag = tmp_path / "cut.bag"
        bag.write_bytes(data[:cut])
        rf = Ros1File.open(bag)
        assert 0 < rf.lost_bytes < len(data) - first
        n = len(rf.chunks)
        assert rf.chunks == whole.chunks[:n] and all(c.offset + c.length <= cut for c in rf.chunks)
        assert n == len(whole.chunks) or whole.chunks[n].offset + whole.chunks[n].length > cut  # every complete chunk
        got = [(t, topic, bytes(d)) for t, topic, _, d in rf.messages(topics, None, None)]
        chans = {cid: (c.topic, c.name) for cid, c in whole.connections.items()}
        with open(full, "rb") as f:
            want = [(t, topic, bytes(d)) for ref_ in whole.chunks[:n] for t, topic, _, d in whole._chunk_messages(f, ref_, chans)]
        assert got and sorted(got) == sorted(want) and [m[0] for m in got] == sorted(m[0] for m in got)


@pytest.mark.parametrize("name", ["drive.mcap", "drive.bag"])
def test_a_detached_camera_info_survives_a_new_typestore_and_reads_alike(drive_dir, name, monkeypatch):
    """The scan a worker hands back holds each camera's CameraInfo: as rosbags' own object
    it unpickles only while the parent's rosbags.usertypes module (replaced by every new
    typestore) holds its class; detached, it needs no class and gives the same intrinsics,
    lens and frame."""
    import pickle
    import sys

    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from gtgen.bag.decode.image import intrinsics, lens
    from gtgen.bag.reader import BagSet, detached

    with BagSet([drive_dir / name]) as bags:
        msg = next(m for _, _, _, m, _ in bags.messages(["/cam_front/camera_info"]))
    monkeypatch.setitem(sys.modules, "rosbags.usertypes", sys.modules["rosbags.usertypes"])  # put back after the test
    get_typestore(Stores.EMPTY).register(get_types_from_msg("float64 x\n", "other_msgs/msg/Thing"))  # another store's module
    with pytest.raises((AttributeError, pickle.PicklingError)):  # rosbags' object: no longer dumped, or not loaded
        pickle.loads(pickle.dumps(msg))
    info = pickle.loads(pickle.dumps(detached(msg)))
    K, size = intrinsics(info)
    K0, size0 = intrinsics(msg)
    np.testing.assert_array_equal(K, K0)
    assert size == size0 and lens(info) == lens(msg) and info.header.frame_id == msg.header.frame_id


def test_bags_of_one_robot_share_one_typestore_and_other_definitions_get_theirs(monkeypatch):
    """A typestore (parsed definitions, generated deserializers: about 0.1 s a bag) is made
    once per process for the definitions the bags carry; other definitions of a type get
    a store of their own, and bytes or text of one definition are the same key. (Safe since
    no message object crosses a process: see the detached CameraInfo's test.)"""
    import sys
    from types import SimpleNamespace

    from gtgen.bag.msgdefs import typestore_of

    a = SimpleNamespace(name="pkg/msg/Thing", encoding="ros2msg", data=b"float64 x\n")
    b = SimpleNamespace(name="pkg/msg/Thing", encoding="ros2msg", data="float64 x\n")
    c = SimpleNamespace(name="pkg/msg/Thing", encoding="ros2msg", data=b"float64 x\nfloat64 y\n")
    if "rosbags.usertypes" in sys.modules:  # put back after the test (its stores register their own module)
        monkeypatch.setitem(sys.modules, "rosbags.usertypes", sys.modules["rosbags.usertypes"])
    one = typestore_of([a], ros1=False)
    assert typestore_of([b], ros1=False) is one and typestore_of([a, a], ros1=False) is one
    other = typestore_of([c], ros1=False)
    assert other is not one
    assert list(other.types["pkg/msg/Thing"].__dataclass_fields__)[:2] == ["x", "y"]
    assert "y" not in one.types["pkg/msg/Thing"].__dataclass_fields__
