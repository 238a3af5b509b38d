"""A TF buffer over a whole drive: any frame pair at any stamp, through static and dynamic edges.

Edges come from ``tf_static`` (one transform each) and ``tf`` (a time series each,
interpolated linearly and by SLERP, never extrapolated beyond the pose tolerance: see
``PoseTrack``). A lookup chains the edges on the path between the two frames in the
frame graph and is vectorised over stamps; where a dynamic edge on the path does not
cover a stamp, that stamp is reported as missing instead of guessed.
"""

from __future__ import annotations

from collections import defaultdict, deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.poses import PoseTrack
from gtgen.errors import TopicError
from gtgen.geometry import invert, make_transform, quat_to_matrix

Edge = tuple[str, str]  # (parent, child): the edge's transform is T_parent_child


@dataclass
class EdgeSamples:
    """The stamped transforms of one dynamic edge as they are read: growing lists,
    packed into arrays by ``pack`` (memory per sample: 64 bytes)."""

    t: list[int] = field(default_factory=list)
    rows: list[tuple[float, ...]] = field(default_factory=list)  # tx, ty, tz, qx, qy, qz, qw
    packed: list[tuple[NDArray, NDArray]] = field(default_factory=list)

    def add(self, t: int, trans: NDArray, quat: NDArray) -> None:
        self.t.append(t)
        self.rows.append((*trans, *quat))

    def pack(self) -> None:
        """Move the lists into arrays."""
        if self.t:
            self.packed.append((np.asarray(self.t, np.int64), np.asarray(self.rows, np.float64).reshape(-1, 7)))
            self.t, self.rows = [], []

    def extend(self, other: EdgeSamples) -> None:
        other.pack()
        self.pack()
        self.packed += other.packed

    def arrays(self) -> tuple[NDArray, NDArray]:
        """Return (stamps, (n, 7) rows) of every sample."""
        self.pack()
        if not self.packed:
            return np.zeros(0, np.int64), np.zeros((0, 7))
        return np.concatenate([p[0] for p in self.packed]), np.concatenate([p[1] for p in self.packed])

    def __len__(self) -> int:
        return len(self.t) + sum(len(p[0]) for p in self.packed)


def relevant_edges(dynamic: list[Edge], static: list[Edge], frames: set[str]) -> set[Edge]:
    """Return the dynamic edges that can lie on a path between two of ``frames``: an edge
    is kept when both of its sides (the graph cut at it) reach one of ``frames``."""
    adj: dict[str, set[str]] = defaultdict(set)
    for p, c in [*dynamic, *static]:
        adj[p].add(c)
        adj[c].add(p)
    keep = set()
    for p, c in dynamic:
        if _reaches(adj, c, p, frames) and _reaches(adj, p, c, frames):
            keep.add((p, c))
    return keep


def _reaches(adj: dict[str, set[str]], start: str, blocked: str, frames: set[str]) -> bool:
    seen, todo = {start, blocked}, deque([start])
    while todo:
        node = todo.popleft()
        if node in frames:
            return True
        for nxt in adj[node] - seen:
            seen.add(nxt)
            todo.append(nxt)
    return False


class TfBuffer:
    """Static transforms ({(parent, child): T}) and dynamic ones ({(parent, child): PoseTrack})."""

    def __init__(self, static: dict[Edge, NDArray], dynamic: dict[Edge, PoseTrack]) -> None:
        self.static = dict(static)
        self.dynamic = dict(dynamic)
        self._adj: dict[str, list[tuple[str, Edge, bool]]] = defaultdict(list)
        for e in [*self.static, *self.dynamic]:
            self._link(e)

    def _link(self, e: Edge) -> None:
        p, c = e
        self._adj[p].append((c, e, True))
        self._adj[c].append((p, e, False))

    @classmethod
    def from_samples(cls, static: dict[Edge, NDArray], samples: dict[Edge, EdgeSamples], tolerance_ns: int) -> TfBuffer:
        """Return the buffer of ``static`` edges and the dynamic ``samples`` (sorted, duplicate
        stamps dropped)."""
        dynamic = {}
        for e, s in samples.items():
            t, rows = s.arrays()
            if len(t):
                dynamic[e] = PoseTrack.from_unsorted(t, rows[:, :3], rows[:, 3:], tolerance_ns)[0]
        return cls({e: T for e, T in static.items() if e not in dynamic}, dynamic)

    def add_dynamic(self, edge: Edge, track: PoseTrack) -> None:
        """Add a dynamic edge (for example the odometry's odom -> base)."""
        self.dynamic[edge] = track
        self._link(edge)

    def path(self, target: str, source: str) -> list[tuple[Edge, bool]] | None:
        """Return the edges from ``target`` to ``source`` (each with True where it is
        walked parent to child), or None if the frames are not connected."""
        if target == source:
            return []
        prev: dict[str, tuple[str, Edge, bool]] = {}
        todo, seen = deque([target]), {target}
        while todo:
            node = todo.popleft()
            for nxt, e, fwd in self._adj[node]:
                if nxt not in seen:
                    seen.add(nxt)
                    prev[nxt] = (node, e, fwd)
                    if nxt == source:
                        out = []
                        while nxt != target:
                            node, e, fwd = prev[nxt]
                            out.append((e, fwd))
                            nxt = node
                        return out[::-1]
                    todo.append(nxt)
        return None

    def lookup(self, target: str, source: str, t_ns: NDArray) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Return T_target_source (N, 4, 4) at stamps ``t_ns`` and where it is known (N,);
        nothing is known where the frames are not connected."""
        t = np.atleast_1d(np.asarray(t_ns, np.int64))
        T = np.broadcast_to(np.eye(4), (len(t), 4, 4)).copy()
        path = self.path(target, source)
        if path is None:
            return T, np.zeros(len(t), bool)
        ok = np.ones(len(t), bool)
        for e, fwd in path:
            if e in self.static:
                step = np.broadcast_to(self.static[e], (len(t), 4, 4))
            else:
                track = self.dynamic[e]
                pos, quat = track.interpolate(t, strict=False)
                good = track.covered(t)
                ok &= good
                pos[~good], quat[~good] = 0.0, (0.0, 0.0, 0.0, 1.0)
                step = make_transform(quat_to_matrix(quat), pos)
            T = T @ (step if fwd else invert(step))
        return T, ok

    def at(self, target: str, source: str, t_ns: int) -> NDArray[np.float64]:
        """Return T_target_source at one stamp (identity for one frame, or an empty
        ``source``: a message without a frame id); TopicError naming the edge if unknown."""
        if source in ("", target):
            return np.eye(4)
        T, ok = self.lookup(target, source, np.array([t_ns]))
        if not ok[0]:
            raise TopicError(f"no transform from '{target}' to '{source}' at {t_ns} ns: {self.why_not(target, source)}")
        return T[0]

    def why_not(self, target: str, source: str) -> str:
        """Return why a transform from ``source`` to ``target`` may be missing."""
        path = self.path(target, source)
        if path is None:
            return f"no TF path from '{target}' to '{source}' (frames known: {sorted(self._adj)})"
        dyn = [f"'{p}' -> '{c}'" for (p, c), _ in path if (p, c) in self.dynamic]
        return f"dynamic edge(s) {', '.join(dyn)} do not cover the stamp within the pose tolerance" if dyn else "ok"
