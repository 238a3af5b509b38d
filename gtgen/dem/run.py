"""DEM alignment of one drive, the first half of ``gtgen dem-align`` (the dataset it
decides is written by ``gtgen.dataset.dem_align``).

``align_drive`` reads like its steps: index the DEM tiles, choose the working CRS, place
the drive (GNSS fit, coverage, vertical offset), run the ICP chain over the samples,
and when the drive's observations contradict some tiles, set them aside and run the
chain again without them.
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
from gtgen.dem.place import DrivePlacement, Placement
from gtgen.dem.tiles import DemMosaic, DemRef, TileIndex
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
    the tiles set aside), every sample's outcome, the tiles set aside, the ICP fitness of
    every sample ICP ran on, and how to open the same DEM elsewhere."""

    placement: DrivePlacement
    outcomes: list[Outcome]
    suspect: frozenset[int]
    fitness: list[float]
    dem: DemRef

    @property
    def suspect_tiles(self) -> list[str]:
        """The set-aside tiles' paths."""
        names = self.placement.dem.tile_names
        return [names[i] for i in sorted(self.suspect)]


@contextlib.contextmanager
def align_drive(drive: DriveStore, fused: FusedStore, dem_source: Path, cfg: GtgenConfig, cache: Path | None) -> Iterator[Alignment]:
    """Yield the DEM alignment of every fused sample of the drive (the DEM stays open
    while the block runs); ``cache`` keeps the tiles' headers."""
    index = TileIndex.build(dem_source, cache=cache)
    crs = index.working_crs(*gnss_lonlat(cfg, drive.gnss()))
    placement = DrivePlacement.of_drive(cfg, drive, fused, DemMosaic(index, crs), dem_source)
    try:
        outcomes, fitness = _icp_chain(drive, fused, placement)
        suspect = placement.suspect_tiles()
        if suspect:  # place the drive again without the tiles its observations contradict
            placement = placement.without(suspect)
            outcomes, fitness = _icp_chain(drive, fused, placement)
        yield Alignment(placement, outcomes, suspect, fitness, DemRef(str(dem_source), str(cache) if cache else None, crs, suspect))
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
