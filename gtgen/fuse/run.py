"""``gtgen fuse``: the stage entry point over a drive store."""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gtgen import reasons
from gtgen.bag import store as drive_store
from gtgen.config import RANGES, GtgenConfig, save_config
from gtgen.errors import StoreError
from gtgen.fuse import store as fs
from gtgen.format import ChunkFiles, compressors
from gtgen.fuse.fusion import FuseParams, MapSource, SampleGrid, fuse_range
from gtgen.fuse.lattice import to_lattice
from gtgen.geometry import quat_to_yaw
from gtgen.progress import ProcessJobs, track

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


def zarr_map_source(drive, rng: str, res: float) -> MapSource:
    """Return the maps of range ``rng`` of an open drive store as a MapSource on ``res``."""
    g = drive[f"maps/{rng}"]
    t = g["t_ns"][:]
    centers = g["center_odom_m"][:]
    yaws = g["yaw_odom_rad"][:]
    map_res = float(g.attrs["resolution_m"])
    arrs = tuple(ChunkFiles(g[name]) for name in drive_store.MAP_LAYERS)

    def load(i: int):
        return to_lattice(int(t[i]), tuple(a.read(i) for a in arrs), centers[i], float(yaws[i]), map_res, res)

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
    arrays = {f"fused/{rng}/{n}": n for n in ("elevation", "confidence", "risk", "count", "last_dt_s", "region")}
    arrays.update({f"xracer/{rng}/{n}": f"xr_{n}" for n in ("elevation", "risk", "confidence")})
    target = {path: ChunkFiles(out[path.replace("elevation", "elevation_m")]) for path in arrays}
    empty = np.zeros(len(samples), bool)
    regions = np.zeros(4, np.int64)
    for k, f in track(fuse_range(maps, samples, params(cfg)), f"fuse: {rng} {lo}..{hi}", total=len(samples)):
        for path, attr in arrays.items():
            target[path].write(lo + k, getattr(f, attr))
        empty[k] = not f.count.any()
        regions += np.bincount(f.region.ravel(), minlength=4)
    return rng, lo, empty, regions, maps.loads


def run_fuse(drive_path: Path, out: Path, cfg: GtgenConfig, workers: int = 2) -> FuseResult:
    """Fuse the maps of drive store ``drive_path`` into the fused store ``out`` (atomically).

    The work is split into jobs per range and per ``fuse.chunk_samples`` samples, run on
    ``workers`` processes; the result does not depend on the split.
    """
    import zarr

    drive = drive_store.open_drive(drive_path)
    S = int(drive["samples/t_ns"].shape[0])
    if S == 0:
        raise StoreError(f"drive store '{drive_path}' has no samples")
    tmp = drive_store.partial_path(out)
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        root = zarr.open_group(str(tmp), mode="w")
        for sp in fs.FUSED_ARRAYS:
            if sp.path.startswith("samples/"):
                continue
            n = cfg.grids.get(sp.path.split("/")[1]).size
            root.create_array(sp.path, shape=(S, n, n), chunks=(1, n, n), dtype=sp.dtype, fill_value=sp.fill_value(), compressors=compressors())
        cfg_json = cfg.model_dump(mode="json")
        step = cfg.fuse.chunk_samples
        # the micro jobs first: they are the long ones
        jobs = [(str(drive_path), str(tmp), r, lo, min(lo + step, S), cfg_json) for r in RANGES for lo in range(0, S, step)]
        with ProcessJobs(min(workers, len(jobs))) as pool:
            results = list(pool.map(_fuse_part, jobs))
        reason = np.zeros(S, np.uint8)
        counts = {r: np.zeros(4, np.int64) for r in RANGES}
        loads = {r: 0 for r in RANGES}
        for r, lo, empty, regions, n_loads in results:
            reason[lo : lo + len(empty)][empty] = reasons.NO_FUSED_MAPS
            counts[r] += regions
            loads[r] += n_loads
        root.create_array("samples/reason", shape=(S,), dtype="uint8", chunks=(S,), fill_value=0)[:] = reason
        coverage = {}
        for r, c in counts.items():
            tot = max(int(c.sum()), 1)
            coverage[r] = {k: round(float(c[i] / tot), 4) for i, k in ((1, "obs_pc"), (2, "obs_f"), (3, "unobs"))}
        rejected = {reasons.name(k): int(v) for k, v in zip(*np.unique(reason, return_counts=True)) if k}
        root.attrs.update(drive_store.jsonable({
            "store": fs.FUSED_STORE, "version": fs.FUSED_VERSION, "complete": True,
            "drive": str(drive_path.resolve()), "drive_bags": drive.attrs.get("bags", []),
            "config": cfg_json, "coverage": coverage, "rejected": rejected,
        }))
        save_config(cfg, tmp / "gtgen-config.yaml")
        drive_store.finalize(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return FuseResult(out, S, int((reason == 0).sum()), rejected, coverage, loads)


def open_fused(path: Path):
    """Return the zarr group of a complete fused store, or raise StoreError saying why not."""
    import zarr

    if not path.exists():
        raise StoreError(f"fused store '{path}' does not exist; run 'gtgen fuse' first")
    g = zarr.open_group(str(path), mode="r")
    a = g.attrs.asdict()
    if a.get("store") != fs.FUSED_STORE or a.get("version") != fs.FUSED_VERSION or not a.get("complete"):
        raise StoreError(f"'{path}' is not a complete gtgen fused store of version {fs.FUSED_VERSION}; re-run 'gtgen fuse'")
    return g
