"""Which DEM tiles a drive uses, and how: each tile near the drive is judged by its borders
with its neighbours before the ICP chain (``gtgen.dem.borders``), and by the drive's
observed ground over it after.

By its borders, a tile is
- put back (``corrected``) when it continues its neighbours markedly better read at an
  offset (``dem.tile_border_gain`` times, and beyond the steps' noise) and that offset is
  larger than ``dem.tile_offset_min_m`` (``_z_m``) and twice its uncertainty; a vertical
  offset alone is put back when it exceeds those;
- set aside when no offset within ``dem.max_tile_offset_m`` makes it continue them
  (its steps stay above ``dem.max_border_step_m``): a tile of another place;
- ``ok`` otherwise, and ``unjudged`` without a neighbour along a quarter of a side.
Tiles set aside are no neighbours: their neighbours are judged again without them.

By the observed ground, a tile whose observed ground disagrees with it where the drive was
placed (more than ``dem.max_tile_disagreement`` of ``dem.min_tile_cells`` cells or more)
is set aside too (a tile with no neighbour to judge it by, a stale survey).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from gtgen.config import DemConfig
from gtgen.dem.borders import BorderFit, border_fit
from gtgen.dem.tiles import DemSource, TileOffset


@dataclass(frozen=True)
class TileJudgement:
    """What dem-align decided of one DEM tile: ``status`` (ok: used as it is; corrected:
    read put back by ``applied``; set_aside: not used; unjudged: no neighbour to judge it
    by, used as it is), why (``reason``), what its borders say (``border``, None without
    a neighbour), and the drive's observed ground cells over it and the share of them that
    disagree with it."""

    index: int
    name: str
    status: str
    border: BorderFit | None
    applied: NDArray = field(default_factory=lambda: np.zeros(3))
    reason: str = ""
    ground_cells: int = 0
    ground_disagreement: float = float("nan")

    @property
    def put_back(self) -> TileOffset | None:
        """The offset the tile is read put back by, None if not corrected."""
        return TileOffset(*map(float, self.applied)) if self.status == "corrected" else None


def tiles_near(dem: DemSource, track_en: NDArray, reach_m: float) -> list[int]:
    """Return the tiles within ``reach_m`` of a track (points (n, 2) in the working CRS)."""
    out = []
    for i in range(len(dem.tile_names)):
        l, b, r, t = dem.tile_bounds(i)
        dx = np.maximum(np.maximum(l - track_en[:, 0], track_en[:, 0] - r), 0)
        dy = np.maximum(np.maximum(b - track_en[:, 1], track_en[:, 1] - t), 0)
        if np.hypot(dx, dy).min() <= reach_m:
            out.append(i)
    return out


def judge_borders(dem: DemSource, tiles: list[int], dc: DemConfig) -> dict[int, TileJudgement]:
    """Judge ``tiles`` by their borders with their neighbours (see the module). A wrong
    tile spoils its neighbours' borders too, so the decisions are taken one at a time: the
    tile whose borders step most against its neighbours as read, summed along them (their
    spread, or their median where larger: a tile read too high steps evenly, with little
    spread, and its neighbours step on the side they share with it only), is set aside or
    put back first (a tile wrong on all its sides before a neighbour wrong on the one it
    shares with it), and its neighbours are judged again with that decision in force, until
    every tile left is fine as it is."""
    aside: set[int] = set()
    back: dict[int, TileOffset] = {}

    def judge(i: int) -> TileJudgement:
        sides = dem.border_sides(i, dc.max_tile_offset_m, frozenset(aside), back)
        return _by_border(i, dem.tile_names[i], border_fit(sides, dc.max_tile_offset_m), dc)

    out = {i: judge(i) for i in tiles}
    decided: set[int] = set()
    while todo := [i for i, j in out.items() if j.status in ("set_aside", "corrected") and i not in decided]:
        worst = max(todo, key=lambda i: _wrongness(out[i].border))
        decided.add(worst)
        if out[worst].status == "set_aside":
            aside.add(worst)
        else:
            back[worst] = out[worst].put_back
        for i in set(tiles) - decided:
            if _touch(dem.tile_bounds(i), dem.tile_bounds(worst), dc.max_tile_offset_m):
                out[i] = judge(i)
    return out


def _wrongness(fit: BorderFit | None) -> float:
    """How wrong a tile reads against its neighbours, summed along its borders [m x pixels]."""
    return np.inf if fit is None else max(fit.step_m, abs(fit.dz_as_read_m)) * fit.pixels


def _touch(a: tuple[float, float, float, float], b: tuple[float, float, float, float], gap_m: float) -> bool:
    """Whether two tiles' bounds lie within ``gap_m`` of each other."""
    return a[0] - gap_m <= b[2] and b[0] - gap_m <= a[2] and a[1] - gap_m <= b[3] and b[1] - gap_m <= a[3]


def _by_border(i: int, name: str, fit: BorderFit | None, dc: DemConfig) -> TileJudgement:
    """Return the judgement of tile ``i`` by its border fit (see the module)."""
    if fit is None:
        return TileJudgement(i, name, "unjudged", None, reason="no neighbour")
    if fit.best_step_m > dc.max_border_step_m:
        return TileJudgement(i, name, "set_aside", fit, reason="no offset continues its neighbours")
    better = fit.step_m >= dc.tile_border_gain * fit.best_step_m and fit.step_m - fit.best_step_m > 4 * fit.step_noise_m
    h = better and np.hypot(*fit.offset[:2]) > max(dc.tile_offset_min_m, 2 * np.hypot(*fit.sigma[:2]))
    dz = fit.offset[2] if h else fit.dz_as_read_m
    v = abs(dz) > max(dc.tile_offset_min_z_m, 2 * fit.sigma[2])
    if not (h or v):
        return TileJudgement(i, name, "ok", fit)
    applied = np.array([fit.offset[0] if h else 0.0, fit.offset[1] if h else 0.0, dz if v else 0.0])
    return TileJudgement(i, name, "corrected", fit, applied, reason="continues its neighbours put back")


def judge_ground(tiles: dict[int, TileJudgement], names: list[str], cells: NDArray, disagree: NDArray,
                 dc: DemConfig) -> tuple[dict[int, TileJudgement], frozenset[int]]:
    """Add the drive's observed ground (per tile: ``cells`` observed, ``disagree`` of them
    disagreeing with it) to the judgements; return them and the tiles the ground newly sets aside."""
    out = dict(tiles)
    new = set()
    for i in np.flatnonzero(cells):
        i = int(i)
        share = float(disagree[i] / cells[i])
        j = out.get(i) or TileJudgement(i, names[i], "unjudged", None, reason="no neighbour")
        j = replace(j, ground_cells=int(cells[i]), ground_disagreement=share)
        if j.status != "set_aside" and cells[i] >= dc.min_tile_cells and share > dc.max_tile_disagreement:
            j = replace(j, status="set_aside", applied=np.zeros(3), reason="its observed ground disagrees")
            new.add(i)
        out[i] = j
    return out, frozenset(new)
