"""What the two hand-written bag readers (``mcap``, ``rosbag1``) share: where a chunk of
messages lies, and the merge of chunks that overlap in time into one time-ordered stream."""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass


@dataclass(frozen=True)
class ChunkRef:
    """Where one chunk lies in its file, its record-time span and the channels it holds."""

    offset: int
    length: int
    t_start: int
    t_end: int
    channels: frozenset[int]


def in_time_order(refs: Iterable[ChunkRef], channels: set[int], start: int | None, stop: int | None,
                  messages: Callable[[ChunkRef], Iterable[tuple]]) -> Iterator[tuple]:
    """Yield the items ``messages(ref)`` gives for the chunks that overlap [start, stop) and
    hold one of ``channels``, in record-time order (ties in file order). Each item starts
    with its record time; items outside [start, stop) are dropped.

    Chunks may overlap in time (recorders write in arrival order), so they are taken in
    order of their first record time and their items merged on a heap, released once no
    later chunk can hold an earlier one.
    """
    lo = -1 if start is None else start
    hi = 1 << 64 if stop is None else stop
    todo = sorted((c for c in refs if c.t_end >= lo and c.t_start < hi and not channels.isdisjoint(c.channels)),
                  key=lambda c: (c.t_start, c.offset))
    heap: list = []
    seq = 0
    for ref in todo:
        while heap and heap[0][0] < ref.t_start:
            yield heapq.heappop(heap)[2]
        for item in messages(ref):
            if lo <= item[0] < hi:
                heapq.heappush(heap, (item[0], seq, item))
                seq += 1
    while heap:
        yield heapq.heappop(heap)[2]
