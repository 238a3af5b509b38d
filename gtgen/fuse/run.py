"""``gtgen fuse``: the stage entry point over a drive store."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gtgen import __version__, codes
from gtgen.config import RANGES, GtgenConfig
from gtgen.errors import StoreError
from gtgen.fuse.fusion import Fused, FuseParams, MapSource, SampleGrid, fuse_range
from gtgen.fuse.lattice import to_lattice
from gtgen.runtime.output import stage_output
from gtgen.runtime.pool import Pool
from gtgen.runtime.progress import track
from gtgen.storage.drive import DriveStore
from gtgen.storage.fused import FusedWriter, layers

log = logging.getLogger(__name__)


@dataclass
class FuseResult:
    """What a fuse run did."""

    store: Path
    n_samples: int
    n_fused: int
    rejected: dict[str, int]
    coverage: dict[str, dict[str, float]]
    map_loads: dict[str, int]
    reason: np.ndarray  # (S,) 0 = fused, else why not


def map_source(drive: DriveStore, rng: str, res: float) -> MapSource:
    """Return the maps of range ``rng`` of a drive store as a MapSource on ``res``."""
    maps = drive.maps(rng)

    def load(i: int):
        return to_lattice(int(maps.t_ns[i]), maps.layers(i), maps.center_odom_m[i], float(maps.yaw_odom_rad[i]),
                          maps.resolution_m, res)

    return MapSource(maps.t_ns, load)


def sample_grids(drive: DriveStore, rng: str, size: int, res: float) -> list[SampleGrid]:
    """Return the target grids of every sample of a drive store for range ``rng``."""
    s = drive.samples
    return [SampleGrid(int(s.t_ns[k]), s.pos_odom_m[k], float(s.yaw_odom_rad[k]), int(s.map_index[rng][k]), size, res)
            for k in range(len(s))]


def params(cfg: GtgenConfig, rng: str | None = None) -> FuseParams:
    """Return the fusion parameters of ``cfg`` for range ``rng``: its QA grids are computed
    only if the dataset stores them (``shards.qa_ranges``; every range when ``rng`` is None)."""
    f = cfg.fuse
    return FuseParams(int(round(f.window_s * 1e9)), int(round(f.past_s * 1e9)), f.min_conf, f.risk_min_conf, f.tile_cells,
                      f.elevation_rule, f.top_height_m, f.top_footprint_m, qa=rng is None or rng in cfg.shards.qa_ranges)


def _layers(f: Fused, rng: str, qa_ranges: list[str]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Return a fused sample's label layers and X-Racer layers of range ``rng`` by their
    store names: those the store holds (the QA grids only for ``qa_ranges``)."""
    labels = {"elevation_m": f.elevation, "confidence": f.confidence, "risk": f.risk, "count": f.count,
              "last_dt_s": f.last_dt_s, "region": f.region}
    xracer = {"elevation_m": f.xr_elevation, "risk": f.xr_risk, "confidence": f.xr_confidence}
    return ({k: labels[k] for k in layers("fused", rng, qa_ranges)}, {k: xracer[k] for k in layers("xracer", rng, qa_ranges)})


def _fuse_part(drive: DriveStore, out_path: str, rng: str, lo: int, hi: int, cfg: GtgenConfig) -> tuple[str, int, np.ndarray, np.ndarray, int]:
    """Fuse samples [lo, hi) of range ``rng`` into the fused store being written; a job for any worker.

    Chunks are exact: a chunk reads every map its windows need, and the integer sums
    make the labels independent of where a chunk starts.
    """
    out = FusedWriter.reopen(Path(out_path))
    grid = cfg.grids.get(rng)
    maps = map_source(drive, rng, grid.resolution_m)
    samples = sample_grids(drive, rng, grid.size, grid.resolution_m)[lo:hi]
    empty = np.zeros(len(samples), bool)
    regions = np.zeros(len(codes.REGIONS), np.int64)
    for k, f in track(fuse_range(maps, samples, params(cfg, rng)), f"fuse: {rng} {lo}..{hi}", total=len(samples)):
        out.write_sample(rng, lo + k, *_layers(f, rng, cfg.shards.qa_ranges))
        empty[k] = not f.count.any()
        regions += np.bincount(f.region.ravel(), minlength=len(codes.REGIONS))
    return rng, lo, empty, regions, maps.loads


def run_fuse(drive_path: Path, out: Path, cfg: GtgenConfig, workers: int = 2, overwrite: bool = False) -> FuseResult:
    """Fuse the maps of drive store ``drive_path`` into the fused store ``out`` (atomically).

    The work is split into jobs per range and per ``fuse.chunk_samples`` samples, run on
    ``workers`` processes; the result does not depend on the split.
    """
    with stage_output(out, reads=[drive_path], overwrite=overwrite) as tmp:
        drive = DriveStore(drive_path)
        S = drive.n_samples
        if S == 0:
            raise StoreError(f"drive store '{drive_path}' has no samples")
        writer = FusedWriter(tmp)
        writer.create_grids(S, {r: cfg.grids.get(r).size for r in RANGES}, cfg.shards.qa_ranges)
        result = _summarise(out, S, _fuse_all(drive, tmp, cfg, S, workers))
        writer.finish(result.reason, gtgen_version=__version__, drive=str(drive_path.resolve()), drive_bags=drive.bags,
                      drive_identity=drive.identity,
                      config=cfg.model_dump(mode="json"), coverage=result.coverage, rejected=result.rejected)
    return result


def _fuse_all(drive: DriveStore, tmp: Path, cfg: GtgenConfig, S: int, workers: int) -> list[tuple]:
    """Fuse every range in jobs of ``fuse.chunk_samples`` samples (the long micro ones first)."""
    step = cfg.fuse.chunk_samples
    jobs = [(drive, str(tmp), r, lo, min(lo + step, S), cfg) for r in RANGES for lo in range(0, S, step)]
    with Pool(min(workers, len(jobs))) as pool:
        return list(pool.map(_fuse_part, jobs))


def _summarise(out: Path, S: int, results: list[tuple]) -> FuseResult:
    reason = np.zeros(S, np.uint8)
    counts = {r: np.zeros(len(codes.REGIONS), np.int64) for r in RANGES}
    loads = {r: 0 for r in RANGES}
    for r, lo, empty, regions, n_loads in results:
        reason[lo : lo + len(empty)][empty] = codes.NO_FUSED_MAPS
        counts[r] += regions
        loads[r] += n_loads
    coverage = {}
    for r, c in counts.items():
        tot = max(int(c.sum()), 1)
        coverage[r] = {codes.REGIONS[i]: round(float(c[i] / tot), 4) for i in codes.LABELLED}
    return FuseResult(out, S, int((reason == codes.OK).sum()), codes.reason_counts(reason), coverage, loads, reason)
