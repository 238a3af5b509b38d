"""What the drive's own track says of the DEM tiles: the placements ICP found over each tile,
against odometry and GNSS.

A tile whose file is off by a few metres on smooth ground passes its borders (they observe
the offset weakly there, ``gtgen.dem.borders``) and its ground (ICP follows the tile, so
the observed ground agrees with it), and the ICP chain walks onto it one small correction
at a time. What does not follow the tile is odometry: over each tile, the placements' offset
from the drive's GNSS fit carried by odometry (``TileTrack.delta``) is the fit's error plus
the odometry's slow drift, the same on every tile the drive crosses up to
``dem.drift_allowance`` per metre between them. A tile whose placements stand apart from the
others' by more than that and ``dem.tile_track_min_m`` is read put back by the difference,
both measured where the drive passes from one tile to the other (the samples of each nearest
the other's along the drive: odometry's drift between them is least there).

Which of two tiles that disagree is the one off is told by what else knows where the robot
is: the window's GNSS fixes (within their stated uncertainty) and the tiles' borders (within
theirs); with three or more tiles, first by how many agree with each other.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import combinations

import numpy as np
from numpy.typing import NDArray

from gtgen.config import DemConfig
from gtgen.dem.judge import TileJudgement
from gtgen.dem.tiles import TileOffset


@dataclass(frozen=True)
class TileTrack:
    """The kept ICP placements over one tile (the base's position on it), per sample: travel
    [m] (n,), horizontal offset from the drive's GNSS fit carried by odometry (``delta``, (n,
    2) [m]) and from the window's GNSS fixes (``gnss``, (n, 2) [m]; NaN without fixes)."""

    index: int
    distance_m: NDArray[np.float64]
    delta: NDArray[np.float64]
    gnss: NDArray[np.float64]

    @property
    def gnss_median(self) -> NDArray[np.float64]:
        """The median offset from the GNSS fixes (E, N) [m], NaN without any."""
        g = self.gnss[np.isfinite(self.gnss).all(axis=1)]
        return np.median(g, axis=0) if len(g) else np.full(2, np.nan)


def tile_tracks(tile: NDArray, distance_m: NDArray, delta: NDArray, gnss: NDArray, min_samples: int) -> list[TileTrack]:
    """Group the kept placements by ``tile`` (-1: none) into ``TileTrack``s of at least
    ``min_samples`` samples (``distance_m`` (n,), ``delta`` and ``gnss`` (n, 2) per sample)."""
    out = []
    for i in np.unique(tile[tile >= 0]):
        m = tile == i
        if m.sum() >= min_samples:
            out.append(TileTrack(int(i), distance_m[m], delta[m], gnss[m]))
    return out


def _facing(a: TileTrack, b: TileTrack, n: int) -> tuple[NDArray, float]:
    """Return how far ``b``'s placements stand from ``a``'s, (E, N) [m], on the ``n``
    samples of each nearest the other's along the drive (odometry's drift between them is
    least there), and the travel between those [m]."""
    ia = np.argsort(np.abs(a.distance_m[:, None] - b.distance_m[None, :]).min(axis=1), kind="stable")[:n]
    ib = np.argsort(np.abs(b.distance_m[:, None] - a.distance_m[None, :]).min(axis=1), kind="stable")[:n]
    d = np.median(b.delta[ib], axis=0) - np.median(a.delta[ia], axis=0)
    return d, float(abs(np.median(b.distance_m[ib]) - np.median(a.distance_m[ia])))


def _agree(a: TileTrack, b: TileTrack, dc: DemConfig) -> bool:
    """Whether two tiles' placements agree within odometry's drift between them."""
    d, gap = _facing(a, b, dc.tile_track_samples)
    return bool(np.hypot(*d) <= max(dc.tile_track_min_m, dc.drift_allowance * gap))


def _offsets(tracks: list[TileTrack], group: set[int], n: int) -> dict[int, NDArray]:
    """Each tile's offset when ``group`` (tile indices) is where the drive truly is: zero in
    the group, else how far its placements stand from those of the group's tile nearest
    along the drive (``_facing``)."""
    ref = [t for t in tracks if t.index in group]
    out = {}
    for t in tracks:
        if t.index in group:
            out[t.index] = np.zeros(2)
        else:
            near = min(ref, key=lambda r: np.abs(r.distance_m[:, None] - t.distance_m[None, :]).min())
            out[t.index] = _facing(near, t, n)[0]
    return out


def _evidence(tracks: list[TileTrack], off: dict[int, NDArray], tiles: dict[int, TileJudgement], sigma_gnss_m: float) -> float:
    """Log-likelihood (up to a constant) of the tiles' offsets ``off`` given the GNSS fixes
    (each tile's placements, put back, should meet them within their stated sigma) and the
    tiles' borders (their measured offset within its sigma)."""
    ll = 0.0
    for t in tracks:
        d = off[t.index]
        g = t.gnss_median
        if np.isfinite(g).all() and sigma_gnss_m > 0:
            ll -= 0.5 * float(np.sum((g - d) ** 2)) / sigma_gnss_m**2
        b = tiles[t.index].border if t.index in tiles else None
        if b is not None:
            ok = np.isfinite(b.offset[:2]) & np.isfinite(b.sigma[:2]) & (b.sigma[:2] > 0)
            ll -= 0.5 * float(np.sum(((b.offset[:2] - d)[ok] / b.sigma[:2][ok]) ** 2))
    return ll


def judge_track(tiles: dict[int, TileJudgement], names: list[str], tracks: list[TileTrack], sigma_gnss_m: float,
                dc: DemConfig) -> tuple[dict[int, TileJudgement], dict[int, TileOffset]]:
    """Return the judgements (``names``: every tile's, by index) with the tiles the track
    puts back, and those tiles' offsets (added to any they are read put back by already). The tiles where the drive truly is are
    the largest set of tiles that agree with each other (``_agree``), and of sets as large,
    the one the GNSS fixes and the borders make likeliest; every other tile is off by its
    placements' difference from that set's nearest tile."""
    if len(tracks) < 2 or all(_agree(a, b, dc) for a, b in combinations(tracks, 2)):
        return tiles, {}
    groups = {frozenset(t.index for t in tracks if _agree(s, t, dc)) for s in tracks}
    score = {g: (len(g), _evidence(tracks, _offsets(tracks, set(g), dc.tile_track_samples), tiles, sigma_gnss_m)) for g in groups}
    best = max(groups, key=score.get)
    if any(g != best and score[g][0] == score[best][0] and score[best][1] - score[g][1] < 1e-9 for g in groups):
        return tiles, {}  # nothing tells which is off (no GNSS sigma or fixes, no border): left as they are, not guessed
    out, back = dict(tiles), {}
    for i, d in _offsets(tracks, set(best), dc.tile_track_samples).items():
        if i in best:
            continue
        j = out.get(i) or TileJudgement(i, names[i], "unjudged", None, reason="no neighbour")
        applied = np.array([j.applied[0] + d[0], j.applied[1] + d[1], j.applied[2]]) if j.status == "corrected" else np.array([d[0], d[1], 0.0])
        out[i] = replace(j, status="corrected", applied=applied,
                         reason=f"its placements stand {np.hypot(*d):.1f} m off those over the drive's other tiles beyond odometry's drift: put back")
        back[i] = TileOffset(*map(float, applied))
    return out, back
