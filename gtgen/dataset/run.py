"""``gtgen dem-align``: place the DEM, refine per sample by ICP, reject misfits, inpaint,
write the dataset.

``run_dem_align`` reads like its steps: open the drive and fused stores, index the DEM
tiles, place the drive (GNSS fit, coverage, vertical offset), then the ICP chain over the
samples here while the kept ones are assembled and written a shard at a time on the
pool, and last the dataset's attributes.
"""

from __future__ import annotations

import contextlib
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gtgen import __version__, codes
from gtgen.config import GtgenConfig
from gtgen.dataset.assemble import Context, Kept, build_block
from gtgen.dataset.split import split_counts
from gtgen.dataset.writer import ShardWriter
from gtgen.dem.fit import PlanarFit, gnss_lonlat
from gtgen.dem.place import DrivePlacement, Placement
from gtgen.dem.tiles import DemMosaic, TileIndex
from gtgen.errors import DemError
from gtgen.geometry import quat_to_yaw
from gtgen.runtime.output import stage_output
from gtgen.runtime.pool import Pool
from gtgen.runtime.progress import track
from gtgen.storage.chunks import ChunkFiles
from gtgen.storage.schema import SAMPLES_PER_SHARD, BagRef, DatasetAttrs, DriveEntry
from gtgen.storage.stores import open_drive, open_fused


@dataclass
class AlignResult:
    """What a dem-align run did."""

    store: Path
    n_in: int
    n_kept: int
    rejected: dict[str, int]
    fit: PlanarFit
    dz_dem_m: float
    geoid_offset_m: float
    crs: str = ""  # the working CRS the drive was placed in
    fitness: list[float] = field(default_factory=list)
    split_counts: dict[str, int] = field(default_factory=dict)


def default_dem_dir(cfg: GtgenConfig, drive: Any) -> Path:
    """Return the DEM folder: ``dem.dir`` if set, else ``dem/`` beside the drive's first bag."""
    if cfg.dem.dir:
        return Path(cfg.dem.dir)
    bags = drive.attrs.get("bags") or []
    if not bags:
        raise DemError("no DEM folder: set dem.dir or pass --dem DIR")
    return Path(bags[0]["path"]).parent / "dem"


def run_dem_align(drive_path: Path, fused_path: Path, dem_dir: Path | None, out: Path, cfg: GtgenConfig,
                  workers: int = 2) -> AlignResult:
    """Align the DEM to every fused sample of a drive and write the dataset ``out`` (atomically).

    The ICP chain is sequential; building and writing the kept samples runs on
    ``workers`` processes alongside it. The dataset does not depend on ``workers``.
    """
    with stage_output(out, reads=[drive_path, fused_path]) as tmp:
        drive, fused = open_drive(drive_path), open_fused(fused_path)
        dem_dir = dem_dir or default_dem_dir(cfg, drive)
        cache = out.parent / "dem-index.json"
        index = TileIndex.build(dem_dir, cache=cache)
        crs = index.working_crs(*gnss_lonlat(cfg, drive))
        with contextlib.ExitStack() as stack:
            placement = DrivePlacement.of_drive(cfg, drive, fused, stack.enter_context(DemMosaic(index, crs)), dem_dir)
            stack.callback(lambda: placement.dem.close())
            W, H = drive.attrs["image_size"]
            writer = ShardWriter(tmp, int(drive["samples/t_ns"].shape[0]), cfg.grids.micro.size, cfg.grids.short.size, (H, W))
            rows, fitness = _icp_chain(drive, fused, placement)
            suspect = placement.suspect_tiles()
            if suspect:  # place the drive again without the tiles its observations contradict
                placement = placement.without(suspect)
                rows, fitness = _icp_chain(drive, fused, placement)
            kept = _record(rows, writer, suspect, placement)
            ctx = Context(str(drive_path), str(fused_path), str(dem_dir), str(cache), crs, tuple(sorted(suspect)), str(tmp),
                          cfg.model_dump(mode="json"))
            with Pool(workers) as pool:
                blocks = _Blocks(ctx, pool, writer)
                for item in kept:
                    blocks.add(item)
                blocks.finish()
        entry = drive_entry(drive_path, drive, crs, placement, suspect_tiles=[index.tiles[i].path for i in sorted(suspect)])
        n = writer.close(dataset_attrs(cfg, [entry], drive.attrs))
        splits = split_counts(writer.root["meta/split"][:]) if n else {}
    return AlignResult(out, int(drive["samples/t_ns"].shape[0]), n, writer.rejected_counts(), placement.fit,
                       placement.dz_dem, placement.geoid_offset_m, crs, fitness, splits)


def _icp_chain(drive: Any, fused: Any, placement: DrivePlacement) -> tuple[list[tuple], list[float]]:
    """Place every fused sample in turn (each starts from the previous kept placement);
    return per sample (index, time, pose, Placement or fused reason) and the ICP fitness
    of every sample ICP ran on."""
    t_s = drive["samples/t_ns"][:]
    pos = drive["samples/pos_odom_m"][:]
    yaw = quat_to_yaw(drive["samples/quat_odom_xyzw"][:])
    dist = drive["samples/distance_m"][:]
    reason_f = fused["samples/reason"][:]
    region, elev = ChunkFiles(fused["fused/short/region"]), ChunkFiles(fused["fused/short/elevation_m"])
    fitness: list[float] = []
    rows: list[tuple] = []
    for k in track(range(len(t_s)), "dem-align: samples"):
        if reason_f[k] != codes.OK:
            rows.append((k, int(t_s[k]), pos[k], yaw[k], int(reason_f[k])))
            continue
        p = _place(placement, drive, fused, k, int(t_s[k]), pos[k], yaw[k], float(dist[k]), region, elev)
        if p.icp is not None:
            fitness.append(p.icp.fitness)
        rows.append((k, int(t_s[k]), pos[k], yaw[k], p))
    return rows, fitness


def _place(placement: DrivePlacement, drive: Any, fused: Any, k: int, t: int, pos: Any, yaw: float, dist: float,
           region: ChunkFiles | None = None, elev: ChunkFiles | None = None) -> Placement:
    region = region or ChunkFiles(fused["fused/short/region"])
    elev = elev or ChunkFiles(fused["fused/short/elevation_m"])
    return placement.place(k, t, pos, yaw, region.read(k), elev.read(k), dist)


def _record(rows: list[tuple], writer: ShardWriter, suspect: frozenset[int], placement: DrivePlacement) -> list[Kept]:
    """Record the rejected samples; return the kept ones."""
    kept = []
    for k, t, pos, yaw, p in rows:
        if not isinstance(p, Placement):
            writer.reject(t, 0, p, pos_odom_m=pos, yaw_odom_rad=yaw)
        elif p.reason != codes.OK:
            writer.reject(t, 0, p.reason, pos_odom_m=pos, yaw_odom_rad=yaw, **_qa(p))
        else:
            s = p.signals
            # no ICP: carried over set-aside tiles by odometry (dem.carry_over_m)
            fit, rmse, C = (p.icp.fitness, p.icp.rmse_m, p.icp.T) if p.icp else (np.nan, np.nan, np.eye(4))
            kept.append(Kept(k, p.T_crs_target, fit, rmse, C, s["disagreement"], s["gnss_offset_m"], s["vegetation_share"]))
    return kept


def _qa(p: Placement) -> dict[str, Any]:
    """Return what the dataset records of a rejected sample's placement."""
    if p.icp is None:  # no ICP ran: the placement it would have started from
        return {} if p.T_crs_target is None else {"T_crs_target": p.T_crs_target}
    C, s = p.icp.T, p.signals
    return {"icp_fitness": p.icp.fitness, "icp_rmse_m": p.icp.rmse_m, "T_crs_target": p.T_crs_target,
            "icp_correction": [C[0, 3], C[1, 3], C[2, 3], np.arctan2(C[1, 0], C[0, 0])],
            "dem_disagreement": s["disagreement"], "gnss_offset_m": s["gnss_offset_m"], "vegetation_share": s["vegetation_share"]}


class _Blocks:
    """Kept samples, built and written one shard at a time on the pool, collected in order
    (so memory holds only a few blocks)."""

    def __init__(self, ctx: Context, pool: Pool, writer: ShardWriter) -> None:
        self.ctx, self.pool, self.writer = ctx, pool, writer
        self.items: list[Kept] = []
        self.start = 0
        self.futures: list[Future] = []

    def add(self, item: Kept) -> None:
        self.items.append(item)
        if len(self.items) == SAMPLES_PER_SHARD:
            self._submit()

    def _submit(self) -> None:
        if not self.items:
            return
        self.futures.append(self.pool.submit(build_block, self.ctx, self.start, self.items))
        while self.futures and (self.futures[0].done() or len(self.futures) > 4):
            self.writer.add_block(self.futures.pop(0).result())
        self.start += len(self.items)
        self.items = []

    def finish(self) -> None:
        self._submit()
        while self.futures:
            self.writer.add_block(self.futures.pop(0).result())


def drive_entry(drive_path: Path, drive: Any, crs: str, placement: DrivePlacement, name: str | None = None,
                suspect_tiles: list[str] | None = None) -> DriveEntry:
    """Return the dataset's record of one drive."""
    bags = [BagRef(**b) for b in drive.attrs.get("bags", [])]
    return DriveEntry(name=name or (Path(bags[0].path).stem if bags else drive_path.stem), drive_store=str(drive_path.resolve()),
                      bags=bags, crs=crs, alignment=placement.alignment(), suspect_tiles=suspect_tiles or [])


def dataset_attrs(cfg: GtgenConfig, drives: list[DriveEntry], drive_attrs: Any, provenance: dict | None = None) -> DatasetAttrs:
    """Return the attributes of a dataset of ``drives`` built with ``cfg``."""
    return DatasetAttrs(gtgen_version=__version__, config=cfg.model_dump(mode="json"), drives=drives,
                        image_size=tuple(drive_attrs["image_size"]), cameras=list(drive_attrs.get("cameras") or []),
                        provenance=provenance)
