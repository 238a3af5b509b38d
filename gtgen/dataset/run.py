"""``gtgen dem-align``: place the DEM, refine per sample by ICP, reject misfits, inpaint,
write the dataset.

``run_dem_align`` reads like its steps: open the drive and fused stores, index the DEM
tiles, place the drive (GNSS fit, coverage, vertical offset), then the ICP chain over the
samples here while the kept ones are assembled and written a shard at a time on the
pool, and last the dataset's attributes.
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


from gtgen import __version__, codes
from gtgen.config import GtgenConfig, save_config
from gtgen.dataset.assemble import Context, Kept, build_block
from gtgen.dataset.split import split_counts
from gtgen.dataset.writer import ShardWriter
from gtgen.dem.fit import PlanarFit
from gtgen.dem.place import DrivePlacement
from gtgen.dem.fit import gnss_lonlat
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
        with DemMosaic(index, crs) as dem:
            placement = DrivePlacement.of_drive(cfg, drive, fused, dem, dem_dir)
            W, H = drive.attrs["image_size"]
            writer = ShardWriter(tmp, int(drive["samples/t_ns"].shape[0]), cfg.grids.micro.size, cfg.grids.short.size, (H, W))
            ctx = Context(str(drive_path), str(fused_path), str(dem_dir), str(cache), crs, str(tmp), cfg.model_dump(mode="json"))
            with Pool(workers) as pool:
                fitness = _icp_chain(drive, fused, placement, writer, _Blocks(ctx, pool, writer))
        n = writer.close(dataset_attrs(cfg, [drive_entry(drive_path, drive, crs, placement)], drive.attrs))
        save_config(cfg, tmp / "gtgen-config.yaml")
        splits = split_counts(writer.root["meta/split"][:]) if n else {}
    return AlignResult(out, int(drive["samples/t_ns"].shape[0]), n, writer.rejected_counts(), placement.fit,
                       placement.dz_dem, placement.geoid_offset_m, crs, fitness, splits)


def _icp_chain(drive: Any, fused: Any, placement: DrivePlacement, writer: ShardWriter, blocks: _Blocks) -> list[float]:
    """Place every fused sample in turn (each starts from the previous kept placement);
    reject or hand it to ``blocks``; return the ICP fitness of every sample ICP ran on."""
    t_s = drive["samples/t_ns"][:]
    pos = drive["samples/pos_odom_m"][:]
    yaw = quat_to_yaw(drive["samples/quat_odom_xyzw"][:])
    reason_f = fused["samples/reason"][:]
    region, elev = ChunkFiles(fused["fused/short/region"]), ChunkFiles(fused["fused/short/elevation_m"])
    fitness: list[float] = []
    for k in track(range(len(t_s)), "dem-align: samples"):
        if reason_f[k] != codes.OK:
            writer.reject(int(t_s[k]), 0, int(reason_f[k]))
            continue
        p = placement.place(k, pos[k], yaw[k], region.read(k), elev.read(k))
        if p.icp is not None:
            fitness.append(p.icp.fitness)
        if p.reason != codes.OK:
            icp = p.icp
            writer.reject(int(t_s[k]), 0, p.reason, *((icp.fitness, icp.rmse_m) if icp is not None else ()))
            continue
        blocks.add(Kept(k, p.T_crs_target, p.icp.fitness, p.icp.rmse_m, p.icp.T))
    blocks.finish()
    return fitness


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


def drive_entry(drive_path: Path, drive: Any, crs: str, placement: DrivePlacement, name: str | None = None) -> DriveEntry:
    """Return the dataset's record of one drive."""
    bags = [BagRef(**b) for b in drive.attrs.get("bags", [])]
    return DriveEntry(name=name or (Path(bags[0].path).stem if bags else drive_path.stem), drive_store=str(drive_path.resolve()),
                      bags=bags, crs=crs, alignment=placement.alignment())


def dataset_attrs(cfg: GtgenConfig, drives: list[DriveEntry], drive_attrs: Any, provenance: dict | None = None) -> DatasetAttrs:
    """Return the attributes of a dataset of ``drives`` built with ``cfg``."""
    return DatasetAttrs(gtgen_version=__version__, config=cfg.model_dump(mode="json"), drives=drives,
                        image_size=tuple(drive_attrs["image_size"]), cameras=list(drive_attrs.get("cameras") or []),
                        provenance=provenance)
