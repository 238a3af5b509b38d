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
