"""``gtgen dem-align``: place the DEM, refine per sample by ICP, reject misfits, inpaint,
write the dataset.

``run_dem_align`` reads like its steps: open the drive and fused stores, align the DEM
to the drive (``gtgen.dem.run.align_drive``: GNSS fit, ICP chain, tiles set aside; without
a DEM, ``dem.enabled: false``, every fused sample is kept unplaced), record the rejected
samples and assemble and write the kept ones a shard at a time on the pool while the ICP
chain runs on (``_Build``), and last the dataset's attributes.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gtgen import __version__, codes
from gtgen.config import GtgenConfig
from gtgen.dataset.assemble import Context, Kept, build_block
from gtgen.dem.fit import PlanarFit
from gtgen.dem.index import default_dem_dir
from gtgen.dem.judge import TileJudgement
from gtgen.dem.place import Placement
from gtgen.dem.run import Alignment, ChainWatch, Outcome, align_drive, replay, unplaced
from gtgen.dem.tiles import DemRef
from gtgen.errors import ConfigError, StoreError
from gtgen.runtime.output import stage_output
from gtgen.runtime.pool import Pool
from gtgen.storage.dataset_writer import ShardWriter
from gtgen.storage.drive import DriveStore
from gtgen.storage.fused import FusedStore
from gtgen.storage.schema import SAMPLES_PER_SHARD, BagRef, DatasetAttrs, DriveEntry, TileEntry


@dataclass
class AlignResult:
    """What a dem-align run did."""

    store: Path
    n_in: int
    n_kept: int
    rejected: dict[str, int]
    fit: PlanarFit | None  # None: no DEM (dem.enabled: false), nothing placed
    dz_dem_m: float
    geoid_offset_m: float
    crs: str = ""  # the working CRS the drive was placed in ("": no DEM)
    fitness: list[float] = field(default_factory=list)
    split_counts: dict[str, int] = field(default_factory=dict)


def run_dem_align(drive_path: Path, fused_path: Path, dem_dir: Path | None, out: Path, cfg: GtgenConfig,
                  workers: int = 2, overwrite: bool = False, stream: bool = True) -> AlignResult:
    """Align the DEM to every fused sample of a drive and write the dataset ``out`` (atomically).

    The ICP chain is sequential; building and writing the kept samples runs on
    ``workers`` processes alongside it (``stream``: each shard as soon as the chain has
    placed its samples, the work of a pass the chain runs again thrown away; else once the
    chain is done, the oracle). The dataset depends on neither ``workers`` nor ``stream``.
    With ``dem.enabled`` false no DEM is read (``dem_dir`` must be None): every fused sample
    is kept with the fused labels alone.
    """
    drive, fused = DriveStore(drive_path), FusedStore(fused_path)
    _check_same_drive(drive, fused)
    _check_grids(fused, cfg)
    _check_qa(fused, cfg)
    dem_src = _dem_source(drive, dem_dir, cfg)
    reads = [drive_path, fused_path, *([dem_src] if dem_src is not None else [])]  # the default DEM folder too
    with stage_output(out, reads=reads, overwrite=overwrite) as tmp, Pool(workers) as pool:
        build = _Build(drive, fused, tmp, cfg, pool)
        with _aligned(drive, fused, dem_src, cfg, out.parent / "dem-index.json", build if stream else None) as al:
            if not stream:
                replay(build, al.dem, al.outcomes)
            writer = build.finish()
            entry = drive_entry(drive_path, drive, al)
        n = writer.close(dataset_attrs(cfg, [entry], drive.image_size, drive.cameras))
        splits = writer.split_counts()
    p = al.placement
    if p is None:
        return AlignResult(out, drive.n_samples, n, writer.rejected_counts(), None, float("nan"), float("nan"), "", [], splits)
    return AlignResult(out, drive.n_samples, n, writer.rejected_counts(), p.fit, p.dz_dem, p.geoid_offset_m, entry.crs, al.fitness,
                       splits)


def _dem_source(drive: DriveStore, dem_dir: Path | None, cfg: GtgenConfig) -> Path | None:
    """Return the DEM the drive is aligned to: ``dem_dir``, else the configured or default
    one; None when ``dem.enabled`` is false."""
    if not cfg.dem.enabled:
        if dem_dir is not None:
            raise ConfigError(f"--dem {dem_dir} given with --no-dem (dem.enabled: false); expected one of them")
        return None
    return dem_dir or default_dem_dir(cfg.dem.dir, [Path(b["path"]) for b in drive.bags])


@contextlib.contextmanager
def _aligned(drive: DriveStore, fused: FusedStore, dem_src: Path | None, cfg: GtgenConfig, cache: Path,
             watch: ChainWatch | None) -> Iterator[Alignment]:
    """Yield the drive's alignment to the DEM ``dem_src``, or its unplaced outcomes without
    one (``dem.enabled`` false); ``watch`` follows it."""
    if dem_src is None:
        yield unplaced(drive, fused, watch)
        return
    with align_drive(drive, fused, dem_src, cfg, cache, watch) as al:
        yield al


def _check_same_drive(drive: DriveStore, fused: FusedStore) -> None:
    """Refuse a fused store fused from another drive store than ``drive`` (its samples
    are another drive's): by the drive store's identity it recorded, or, in a fused store
    written before it recorded one, by the bags read and the samples."""
    recorded = fused.attrs.get("drive_identity")
    if recorded is not None:
        same = recorded == drive.identity
    else:
        bags = sorted(b.get("sha256", "") for b in fused.attrs.get("drive_bags") or [])
        same = bags == sorted(b.get("sha256", "") for b in drive.bags) and fused.n_samples == drive.n_samples
    if not same:
        raise StoreError(f"fused store '{fused.path}' was fused from another drive store than '{drive.path}' "
                         f"(it names '{fused.attrs.get('drive')}'); run 'gtgen fuse {drive.path}' again")


def _check_grids(fused: FusedStore, cfg: GtgenConfig) -> None:
    """Refuse a fused store whose grids are not the config's (the dataset would mix them)."""
    from gtgen.config import RANGES

    for r in RANGES:
        mine, theirs = cfg.grids.get(r), fused.config.grids.get(r)
        if (mine.size, mine.resolution_m) != (theirs.size, theirs.resolution_m) or fused.size(r) != mine.size:
            raise ConfigError(f"fused store '{fused.path}' has {r} grids of {theirs.size} cells at {theirs.resolution_m} m; "
                              f"the config asks for {mine.size} at {mine.resolution_m} m: run 'gtgen fuse' again with this config, "
                              "or pass the config it was fused with")


def _check_qa(fused: FusedStore, cfg: GtgenConfig) -> None:
    """Refuse a fused store without the QA grids the config's dataset stores."""
    missing = [r for r in cfg.shards.qa_ranges if r not in fused.qa_ranges]
    if missing:
        raise ConfigError(f"shards.qa_ranges {list(cfg.shards.qa_ranges)} asks for the QA grids of {missing}, but fused store "
                          f"'{fused.path}' was fused with shards.qa_ranges {fused.qa_ranges}: run 'gtgen fuse' again with this config")


def _qa(p: Placement) -> dict[str, Any]:
    """Return what the dataset records of a rejected sample's placement."""
    if p.icp is None:  # no ICP ran: the placement it would have started from
        return {} if p.T_crs_target is None else {"T_crs_target": p.T_crs_target}
    C, s = p.icp.T, p.signals
    return {"icp_fitness": p.icp.fitness, "icp_rmse_m": p.icp.rmse_m, "T_crs_target": p.T_crs_target,
            "icp_correction": [C[0, 3], C[1, 3], C[2, 3], np.arctan2(C[1, 0], C[0, 0])],
            "dem_disagreement": s["disagreement"], "gnss_offset_m": s["gnss_offset_m"], "vegetation_share": s["vegetation_share"]}


class _Build:
    """The dataset written while the ICP chain places the samples (a ``ChainWatch``): the
    rejected samples are recorded, the kept ones queued a shard at a time as the chain
    places them and built and written on the pool, on one worker fewer than it has while
    the chain holds a core, on all of them after; the shards are collected in order with
    a few in flight (so memory holds only those). A new pass of the chain voids the one
    before: its shards are waited for and the store starts anew."""

    IN_FLIGHT = 4  # shards built at once at most once the chain is done

    def __init__(self, drive: DriveStore, fused: FusedStore, tmp: Path, cfg: GtgenConfig, pool: Pool) -> None:
        self.drive, self.fused, self.tmp, self.cfg, self.pool = drive, fused, tmp, cfg, pool
        self.writer: ShardWriter | None = None
        self.futures: list[Future] = []

    def start(self, dem: DemRef | None) -> None:
        for f in self.futures:  # a pass before this one: its shards finish, then go with the store
            f.result()
        d, cfg = self.drive, self.cfg
        self.writer = ShardWriter(self.tmp, d.n_samples, cfg.grids.micro.size, cfg.grids.short.size, len(d.cameras), d.jpeg_capacity,
                                  scans=(cfg.shards.max_scan_points, cfg.shards.max_scans) if len(d.scans) else None,
                                  precision=cfg.shards.precision, qa_ranges=cfg.shards.qa_ranges)
        self.ctx = Context(d, self.fused, dem, self.tmp, cfg)
        self.items: list[Kept] = []
        self.queue: list[tuple[int, list[Kept]]] = []  # (dataset index of the first, samples) of shards not yet submitted
        self.futures = []
        self.next = 0  # dataset index of the first sample in ``items``

    def outcome(self, o: Outcome) -> None:
        p, w = o.placement, self.writer
        if not isinstance(p, Placement):
            w.reject(o.t_ns, 0, p, pos_odom_m=o.pos_odom_m, yaw_odom_rad=o.yaw_odom_rad)
        elif p.reason != codes.OK:
            w.reject(o.t_ns, 0, p.reason, pos_odom_m=o.pos_odom_m, yaw_odom_rad=o.yaw_odom_rad, **_qa(p))
        else:
            s = p.signals
            # no ICP: carried over set-aside tiles by odometry (dem.carry_over_m), or no DEM (no placement at all)
            fit, rmse, C = (p.icp.fitness, p.icp.rmse_m, p.icp.T) if p.icp else (np.nan, np.nan, np.eye(4))
            T = p.T_crs_target if p.T_crs_target is not None else np.full((4, 4), np.nan)
            self.items.append(Kept(o.k, T, fit, rmse, C, s["disagreement"], s["gnss_offset_m"], s["vegetation_share"]))
            if len(self.items) == SAMPLES_PER_SHARD:
                self._queue()
        self._pump(max(1, self.pool.workers - 1), wait=False)

    def _queue(self) -> None:
        if self.items:
            self.queue.append((self.next, self.items))
            self.next += len(self.items)
            self.items = []

    def _pump(self, in_flight: int, wait: bool) -> None:
        """Collect the finished shards in order and submit queued ones up to ``in_flight``
        (``wait``: until the queue is empty, waiting for the oldest shard when it is full)."""
        while True:
            while self.futures and self.futures[0].done():
                self.writer.add_block(self.futures.pop(0).result())
            while self.queue and len(self.futures) < in_flight:
                self.futures.append(self.pool.submit(build_block, self.ctx, *self.queue.pop(0)))
            if not (wait and self.queue):
                return
            self.writer.add_block(self.futures.pop(0).result())

    def finish(self) -> ShardWriter:
        """Write the last samples of the last pass; return its writer (to close)."""
        self._queue()
        self._pump(self.IN_FLIGHT, wait=True)
        while self.futures:
            self.writer.add_block(self.futures.pop(0).result())
        return self.writer


def drive_entry(drive_path: Path, drive: DriveStore, al: Alignment, name: str | None = None) -> DriveEntry:
    """Return the dataset's record of one drive (a drive without a DEM: no CRS, no alignment)."""
    bags = [BagRef(**b) for b in drive.bags]
    return DriveEntry(name=name or (Path(bags[0].path).stem if bags else drive_path.stem), drive_store=str(drive_path.resolve()),
                      bags=bags, crs=al.dem.crs if al.dem is not None else "",
                      alignment=al.placement.alignment() if al.placement is not None else {},
                      suspect_tiles=al.suspect_tiles, tiles=[_tile_entry(t) for t in al.tiles])


def _tile_entry(t: TileJudgement) -> TileEntry:
    """Return the dataset's record of a tile's judgement (NaN as null)."""
    def num(x: float) -> float | None:
        return round(float(x), 4) if np.isfinite(x) else None

    f = t.border
    border = {"border_pixels": f.pixels, "border_step_m": num(f.step_m), "border_step_put_back_m": num(f.best_step_m),
              "offset_m": [num(x) for x in f.offset], "sigma_m": [num(x) for x in f.sigma]} if f else {"offset_m": [None] * 3, "sigma_m": [None] * 3}
    return TileEntry(path=t.name, status=t.status, reason=t.reason, applied_m=[round(float(x), 4) for x in t.applied],
                     ground_cells=t.ground_cells, ground_disagreement=num(t.ground_disagreement), **border)


def dataset_attrs(cfg: GtgenConfig, drives: list[DriveEntry], image_size: tuple[int, int], cameras: list[str],
                  provenance: dict | None = None) -> DatasetAttrs:
    """Return the attributes of a dataset of ``drives`` built with ``cfg`` (images of
    ``image_size`` (width, height) [px] from ``cameras``)."""
    return DatasetAttrs(gtgen_version=__version__, config=cfg.model_dump(mode="json"), drives=drives,
                        image_size=tuple(image_size), cameras=list(cameras), provenance=provenance)
