"""DEM alignment of one drive, the first half of ``gtgen dem-align`` (the dataset it
decides is written by ``gtgen.dataset.dem_align``).

``align_drive`` reads like its steps: index the DEM tiles, choose the working CRS, place
the drive (GNSS fit, coverage, vertical offset), judge the tiles near it by their borders
(``gtgen.dem.judge``: put back the shifted ones, set aside those of another place), run the
ICP chain over the samples, and when the drive's observed ground disagrees with a tile, set
it aside and run the chain again; when the placements over a tile stand off those over the
others beyond odometry's drift (``gtgen.dem.track``), put it back and run the chain again.

A ``ChainWatch`` follows the chain sample by sample (dem-align builds the kept samples
while the chain runs on): each pass begins with ``start`` and voids the passes before it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.config import GtgenConfig
from gtgen.dem.fit import gnss_lonlat
from gtgen.dem.index import TileIndex
from gtgen.dem.judge import TileJudgement, judge_borders, judge_ground, tiles_near
from gtgen.dem.place import DrivePlacement, Placement
from gtgen.dem.tiles import DemMosaic, DemRef
from gtgen.dem.track import TileTrack, judge_track, tile_tracks
from gtgen.geometry import yaw_transform
from gtgen.runtime.progress import track
from gtgen.storage.drive import DriveStore
from gtgen.storage.fused import FusedStore

TRACK_PASSES = 3  # at most this many placements of the drive again with tiles its track puts back
TRACK_REACH_M = 40.0  # a sample's placement speaks for the tile under it when TRACK_SHARE of its ground
TRACK_SHARE = 0.75  # this far around (a square of that half-edge) lies on it [m]


@dataclass(frozen=True)
class Outcome:
    """One sample's outcome: its index and pose at t in odom, and its Placement (or the
    reason fusion left it without one)."""

    k: int
    t_ns: int
    pos_odom_m: NDArray[np.float64]
    yaw_odom_rad: float
    placement: Placement | int


class ChainWatch(Protocol):
    """What follows the ICP chain as it places the samples."""

    def start(self, dem: DemRef | None) -> None:
        """A pass over every sample begins, reading ``dem`` (None: no DEM); what the passes
        before it gave is void."""

    def outcome(self, o: Outcome) -> None:
        """Sample ``o.k``'s outcome in this pass (the samples come in order)."""


@dataclass
class Alignment:
    """A drive's DEM alignment: the placement (its fit, vertical offset and DEM, without
    the tiles set aside, with the shifted ones put back), every sample's outcome, the tiles
    set aside, the ICP fitness of every sample ICP ran on, how to open the same DEM
    elsewhere, and the judgement of every tile near the drive."""

    placement: DrivePlacement | None  # None: no DEM (``unplaced``)
    outcomes: list[Outcome]
    suspect: frozenset[int]
    fitness: list[float]
    dem: DemRef | None
    tiles: list[TileJudgement]

    @property
    def suspect_tiles(self) -> list[str]:
        """The set-aside tiles' paths."""
        if self.placement is None:
            return []
        names = self.placement.dem.tile_names
        return [names[i] for i in sorted(self.suspect)]


@contextlib.contextmanager
def align_drive(drive: DriveStore, fused: FusedStore, dem_source: Path, cfg: GtgenConfig, cache: Path | None,
                watch: ChainWatch | None = None) -> Iterator[Alignment]:
    """Yield the DEM alignment of every fused sample of the drive (the DEM stays open
    while the block runs); ``cache`` keeps the tiles' headers; ``watch`` follows every pass
    of the chain (the last it starts is the alignment's)."""
    index = TileIndex.build(dem_source, cache=cache)
    crs = index.working_crs(*gnss_lonlat(cfg, drive.gnss()))

    def ref(placement: DrivePlacement) -> DemRef:  # how to open the DEM a placement reads elsewhere
        dem = placement.dem
        return DemRef(str(dem_source), str(cache) if cache else None, crs, dem.exclude, tuple(sorted(dem.offsets.items())))

    def chain(placement: DrivePlacement) -> tuple[list[Outcome], list[float]]:
        if watch is not None:
            watch.start(ref(placement))
        return _icp_chain(drive, fused, placement, watch)

    placement = DrivePlacement.of_drive(cfg, drive, fused, DemMosaic(index, crs), dem_source)
    try:
        tiles = judge_borders(placement.dem, _near(placement, drive, cfg), cfg.dem)
        aside = frozenset(i for i, t in tiles.items() if t.status == "set_aside")
        placement = placement.adjusted(aside, {i: t.put_back for i, t in tiles.items() if t.put_back is not None})
        outcomes, fitness = chain(placement)
        tiles, more = judge_ground(tiles, placement.dem.tile_names, placement.tile_cells, placement.tile_bad, cfg.dem)
        if more:  # the drive's ground disagrees with tiles the borders kept: place it again without them
            placement = placement.without(more)
            outcomes, fitness = chain(placement)
        for _ in range(TRACK_PASSES):  # ICP follows a shifted tile part of the way: what is left shows on the next pass
            tiles, back = judge_track(tiles, placement.dem.tile_names, _tracks(placement, outcomes, drive), placement.gnss_sd_m, cfg.dem)
            if not back:
                break
            # the placements over a tile stand off the others' beyond odometry's drift: place the drive again, the tile put back
            placement = placement.adjusted(frozenset(), {**placement.dem.offsets, **back})
            outcomes, fitness = chain(placement)
        yield Alignment(placement, outcomes, placement.dem.exclude, fitness, ref(placement), [tiles[i] for i in sorted(tiles)])
    finally:
        placement.dem.close()


def unplaced(drive: DriveStore, fused: FusedStore, watch: ChainWatch | None = None) -> Alignment:
    """Return the outcomes of a drive without a DEM (``dem.enabled: false``): every sample
    fusion kept is kept, none is placed (no placement, no ICP, no signals); ``watch`` sees
    them as one pass."""
    s = drive.samples
    reason_f = fused.reason()
    none = {"disagreement": np.nan, "gnss_offset_m": np.nan, "vegetation_share": np.nan}
    out = [Outcome(k, int(s.t_ns[k]), s.pos_odom_m[k], float(s.yaw_odom_rad[k]),
                   Placement(codes.OK, signals=none) if reason_f[k] == codes.OK else int(reason_f[k])) for k in range(len(s))]
    if watch is not None:
        replay(watch, None, out)
    return Alignment(None, out, frozenset(), [], None, [])


def replay(watch: ChainWatch, dem: DemRef | None, outcomes: list[Outcome]) -> None:
    """Hand ``watch`` a whole pass of ``outcomes`` (reading ``dem``), as a chain run with it would."""
    watch.start(dem)
    for o in outcomes:
        watch.outcome(o)


def _near(placement: DrivePlacement, drive: DriveStore, cfg: GtgenConfig) -> list[int]:
    """Return the tiles the drive's short grids can reach, as the GNSS fit places it."""
    en = placement.fit.apply_xy(drive.samples.pos_odom_m[:, :2])
    half = cfg.grids.short.size * cfg.grids.short.resolution_m / 2
    return tiles_near(placement.dem, en, half * np.sqrt(2) + cfg.dem.max_correction_m)


def _tracks(placement: DrivePlacement, outcomes: list[Outcome], drive: DriveStore) -> list[TileTrack]:
    """Return the kept ICP placements grouped by the tile under the base (``gtgen.dem.track``),
    of the samples whose ground within TRACK_REACH_M lies on that tile (ICP of a sample over
    two tiles is a compromise between them)."""
    kept = [o for o in outcomes if isinstance(o.placement, Placement) and o.placement.reason == codes.OK and o.placement.icp is not None]
    if not kept:
        return []
    T = np.stack([o.placement.T_crs_target for o in kept])
    off = [placement.track_offsets(Tk, yaw_transform(*o.pos_odom_m, o.yaw_odom_rad), o.t_ns) for Tk, o in zip(T, kept)]
    tile = placement.dem.tile_of(T[:, 0, 3], T[:, 1, 3])
    ring = np.linspace(-TRACK_REACH_M, TRACK_REACH_M, 9)
    rx, ry = (a.ravel() for a in np.meshgrid(ring, ring))
    around = placement.dem.tile_of((T[:, 0, 0, None] * rx + T[:, 0, 1, None] * ry + T[:, 0, 3, None]).ravel(),
                                   (T[:, 1, 0, None] * rx + T[:, 1, 1, None] * ry + T[:, 1, 3, None]).ravel()).reshape(len(T), -1)
    tile = np.where((around == tile[:, None]).mean(axis=1) >= TRACK_SHARE, tile, -1)
    dist = drive.samples.distance_m[[o.k for o in kept]]
    return tile_tracks(tile, dist, np.stack([d for d, _ in off]), np.stack([g for _, g in off]), placement.cfg.dem.tile_track_samples)


def _icp_chain(drive: DriveStore, fused: FusedStore, placement: DrivePlacement,
               watch: ChainWatch | None = None) -> tuple[list[Outcome], list[float]]:
    """Place every fused sample in turn (each starts from the previous kept placement),
    handing each outcome to ``watch`` as it comes; return each sample's outcome and the ICP
    fitness of every sample ICP ran on."""
    s = drive.samples
    reason_f = fused.reason()
    region, elev = fused.grid("short", "region"), fused.grid("short", "elevation_m")
    fitness: list[float] = []
    out: list[Outcome] = []
    for k in track(range(len(s)), "dem-align: samples"):
        t, pos, yaw = int(s.t_ns[k]), s.pos_odom_m[k], float(s.yaw_odom_rad[k])
        if reason_f[k] != codes.OK:
            o = Outcome(k, t, pos, yaw, int(reason_f[k]))
        else:
            p = placement.place(k, t, pos, yaw, region[k], elev[k], float(s.distance_m[k]))
            if p.icp is not None:
                fitness.append(p.icp.fitness)
            o = Outcome(k, t, pos, yaw, p)
        out.append(o)
        if watch is not None:
            watch.outcome(o)
    return out, fitness
