"""``gtgen fuse``: the stage entry point over a drive store."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gtgen import __version__, codes
from gtgen.config import RANGES, GtgenConfig
from gtgen.errors import StoreError
from gtgen.fuse.fusion import FuseParams, MapSource, SampleGrid, fuse_range
from gtgen.fuse.lattice import to_lattice
from gtgen.geometry import quat_to_yaw
from gtgen.runtime.output import stage_output
from gtgen.runtime.pool import Pool
from gtgen.runtime.progress import track
from gtgen.storage.chunks import ChunkFiles, compressors
from gtgen.storage.schema import FUSED, MAP_LAYERS
from gtgen.storage.stores import create_group, open_drive, store_attrs

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


def zarr_map_source(drive, rng: str, res: float) -> MapSource:
    """Return the maps of range ``rng`` of an open drive store as a MapSource on ``res``."""
    g = drive[f"maps/{rng}"]
    t = g["t_ns"][:]
    centers = g["center_odom_m"][:]
    yaws = g["yaw_odom_rad"][:]
    z0 = g["z_offset_m"][:]
    map_res = float(g.attrs["resolution_m"])
    arrs = tuple(ChunkFiles(g[name]) for name in MAP_LAYERS)

    def load(i: int):
        elev, risk, conf = (a.read(i) for a in arrs)
        if z0[i]:
            elev += np.float32(z0[i])
        return to_lattice(int(t[i]), (elev, risk, conf), centers[i], float(yaws[i]), map_res, res)

    return MapSource(t, load)


def sample_grids(drive, rng: str, size: int, res: float) -> list[SampleGrid]:
    """Return the target grids of every sample of an open drive store for range ``rng``."""
    t = drive["samples/t_ns"][:]
    pos = drive["samples/pos_odom_m"][:]
    yaw = quat_to_yaw(drive["samples/quat_odom_xyzw"][:])
    cur = drive[f"samples/map_index_{rng}"][:]
    return [SampleGrid(int(t[k]), pos[k], float(yaw[k]), int(cur[k]), size, res) for k in range(len(t))]


def params(cfg: GtgenConfig) -> FuseParams:
    """Return the fusion parameters of ``cfg``."""
    f = cfg.fuse
    return FuseParams(int(round(f.window_s * 1e9)), int(round(f.past_s * 1e9)), f.min_conf, f.risk_min_conf, f.tile_cells)


def fused_fields(rng: str) -> dict[str, str]:
    """Return {fused-store array of range ``rng``: the ``Fused`` field it holds}."""
    out = {f"fused/{rng}/{n}": n for n in ("confidence", "risk", "count", "last_dt_s", "region")}
    out[f"fused/{rng}/elevation_m"] = "elevation"
    out.update({f"xracer/{rng}/{n}": f"xr_{n}" for n in ("risk", "confidence")})
    out[f"xracer/{rng}/elevation_m"] = "xr_elevation"
    return out


def _fuse_part(drive_path: str, out_path: str, rng: str, lo: int, hi: int, cfg_json: dict) -> tuple[str, int, np.ndarray, np.ndarray, int]:
    """Fuse samples [lo, hi) of range ``rng`` into the open store; a job for any worker.

    Chunks are exact: a chunk reads every map its windows need, and the integer sums
    make the labels independent of where a chunk starts.
    """
    import zarr

    cfg = GtgenConfig.model_validate(cfg_json)
    drive = zarr.open_group(drive_path, mode="r")
    out = zarr.open_group(out_path, mode="r+")
    grid = cfg.grids.get(rng)
    maps = zarr_map_source(drive, rng, grid.resolution_m)
    samples = sample_grids(drive, rng, grid.size, grid.resolution_m)[lo:hi]
    target = {ChunkFiles(out[path]): name for path, name in fused_fields(rng).items()}
    empty = np.zeros(len(samples), bool)
    regions = np.zeros(len(codes.REGIONS), np.int64)
    for k, f in track(fuse_range(maps, samples, params(cfg)), f"fuse: {rng} {lo}..{hi}", total=len(samples)):
        for arr, name in target.items():
            arr.write(lo + k, getattr(f, name))
        empty[k] = not f.count.any()
        regions += np.bincount(f.region.ravel(), minlength=len(codes.REGIONS))
    return rng, lo, empty, regions, maps.loads


def run_fuse(drive_path: Path, out: Path, cfg: GtgenConfig, workers: int = 2) -> FuseResult:
    """Fuse the maps of drive store ``drive_path`` into the fused store ``out`` (atomically).

    The work is split into jobs per range and per ``fuse.chunk_samples`` samples, run on
    ``workers`` processes; the result does not depend on the split.
    """
    with stage_output(out, reads=[drive_path]) as tmp:
        drive = open_drive(drive_path)
        S = int(drive["samples/t_ns"].shape[0])
        if S == 0:
            raise StoreError(f"drive store '{drive_path}' has no samples")
        root = _create(tmp, cfg, S)
        results = _fuse_all(drive_path, tmp, cfg, S, workers)
        result = _summarise(out, S, results)
        root.create_array("samples/reason", shape=(S,), dtype="uint8", chunks=(S,), fill_value=0)[:] = result.reason
        root.attrs.update(store_attrs(
            FUSED, gtgen_version=__version__, drive=str(drive_path.resolve()), drive_bags=drive.attrs.get("bags", []),
            config=cfg.model_dump(mode="json"), coverage=result.coverage, rejected=result.rejected,
        ))
    return result


def _create(tmp: Path, cfg: GtgenConfig, S: int):
    """Create the fused store's per-sample grids, one sample per chunk."""
    root = create_group(tmp)
    for sp in FUSED.arrays:
        if sp.path.startswith("samples/"):
            continue
        n = cfg.grids.get(sp.path.split("/")[1]).size
        root.create_array(sp.path, shape=(S, n, n), chunks=(1, n, n), dtype=sp.dtype, fill_value=sp.fill_value(), compressors=compressors())
    return root


def _fuse_all(drive_path: Path, tmp: Path, cfg: GtgenConfig, S: int, workers: int) -> list[tuple]:
    """Fuse every range in jobs of ``fuse.chunk_samples`` samples (the long micro ones first)."""
    cfg_json = cfg.model_dump(mode="json")
    step = cfg.fuse.chunk_samples
    jobs = [(str(drive_path), str(tmp), r, lo, min(lo + step, S), cfg_json) for r in RANGES for lo in range(0, S, step)]
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
