"""DEM alignment of one drive, the first half of ``gtgen dem-align`` (the dataset it
decides is written by ``gtgen.dataset.dem_align``).

``align_drive`` reads like its steps: index the DEM tiles, choose the working CRS, place
the drive (GNSS fit, coverage, vertical offset), run the ICP chain over the samples
(measuring each tile's offset on the way), and when the drive's observations put some
tiles elsewhere, run the chain again with those tiles put back (a consistent offset) or
set aside (none: a tile of another place).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.config import GtgenConfig
from gtgen.dem.fit import gnss_lonlat
from gtgen.dem.place import DrivePlacement, Placement, TileJudgement
from gtgen.dem.tiles import DemMosaic, DemRef, TileIndex, TileOffset
from gtgen.runtime.progress import track
from gtgen.storage.drive import DriveStore
from gtgen.storage.fused import FusedStore


@dataclass(frozen=True)
class Outcome:
    """One sample's outcome: its index and pose at t in odom, and its Placement (or the
    reason fusion left it without one)."""

    k: int
    t_ns: int
    pos_odom_m: NDArray[np.float64]
    yaw_odom_rad: float
    placement: Placement | int


@dataclass
class Alignment:
    """A drive's DEM alignment: the placement (its fit, vertical offset and DEM, without
    the tiles set aside, with the shifted ones put back), every sample's outcome, the tiles
    set aside, the ICP fitness of every sample ICP ran on, how to open the same DEM
    elsewhere, and what the first chain measured of each tile."""

    placement: DrivePlacement
    outcomes: list[Outcome]
    suspect: frozenset[int]
    fitness: list[float]
    dem: DemRef
    tiles: list[TileJudgement]

    @property
    def suspect_tiles(self) -> list[str]:
        """The set-aside tiles' paths."""
        names = self.placement.dem.tile_names
        return [names[i] for i in sorted(self.suspect)]


MAX_REPLACEMENTS = 5  # chains run again at most this many times while the tiles' offsets settle
SETTLED_M = (0.1, 0.03)  # put-back offsets that moved less than this (horizontal, vertical) [m] have settled


def _same(a: dict[int, TileOffset], b: dict[int, TileOffset]) -> bool:
    """Whether two sets of put-back offsets are the same tiles, settled to SETTLED_M."""
    return a.keys() == b.keys() and all(np.hypot(a[i].dx - b[i].dx, a[i].dy - b[i].dy) < SETTLED_M[0]
                                        and abs(a[i].dz - b[i].dz) < SETTLED_M[1] for i in a)


@contextlib.contextmanager
def align_drive(drive: DriveStore, fused: FusedStore, dem_source: Path, cfg: GtgenConfig, cache: Path | None) -> Iterator[Alignment]:
    """Yield the DEM alignment of every fused sample of the drive (the DEM stays open
    while the block runs); ``cache`` keeps the tiles' headers."""
    index = TileIndex.build(dem_source, cache=cache)
    crs = index.working_crs(*gnss_lonlat(cfg, drive.gnss()))
    placement = DrivePlacement.of_drive(cfg, drive, fused, DemMosaic(index, crs), dem_source)
    try:
        outcomes, fitness = _icp_chain(drive, fused, placement)
        record: dict[int, TileJudgement] = {}
        for _ in range(MAX_REPLACEMENTS):
            tiles = placement.judge_tiles()
            record.update({t.index: t for t in tiles if t.index not in placement.dem.exclude})
            suspect = frozenset(t.index for t in tiles if t.status == "set_aside")
            offsets = {t.index: t.put_back for t in tiles if t.put_back is not None}
            if suspect == placement.dem.exclude and _same(offsets, placement.dem.offsets):
                break
            # place the drive again with the tiles its observations put elsewhere
            placement = placement.adjusted(suspect, offsets)
            outcomes, fitness = _icp_chain(drive, fused, placement)
        dem = placement.dem
        ref = DemRef(str(dem_source), str(cache) if cache else None, crs, dem.exclude, tuple(sorted(dem.offsets.items())))
        yield Alignment(placement, outcomes, dem.exclude, fitness, ref, [record[i] for i in sorted(record)])
    finally:
        placement.dem.close()


def _icp_chain(drive: DriveStore, fused: FusedStore, placement: DrivePlacement) -> tuple[list[Outcome], list[float]]:
    """Place every fused sample in turn (each starts from the previous kept placement);
    return each sample's outcome and the ICP fitness of every sample ICP ran on."""
    s = drive.samples
    reason_f = fused.reason()
    region, elev = fused.grid("short", "region"), fused.grid("short", "elevation_m")
    fitness: list[float] = []
    out: list[Outcome] = []
    for k in track(range(len(s)), "dem-align: samples"):
        t, pos, yaw = int(s.t_ns[k]), s.pos_odom_m[k], float(s.yaw_odom_rad[k])
        if reason_f[k] != codes.OK:
            out.append(Outcome(k, t, pos, yaw, int(reason_f[k])))
            continue
        p = placement.place(k, t, pos, yaw, region[k], elev[k], float(s.distance_m[k]))
        if p.icp is not None:
            fitness.append(p.icp.fitness)
        out.append(Outcome(k, t, pos, yaw, p))
    return out, fitness
