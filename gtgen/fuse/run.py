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
from gtgen.format import compressors
from gtgen.fuse.fusion import FuseParams, MapSource, SampleGrid, fuse_range
from gtgen.fuse.lattice import to_lattice
from gtgen.geometry import quat_to_yaw
from gtgen.progress import track

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
    arrs = (g["elevation_m"], g["risk"], g["confidence"])

    def load(i: int):
        return to_lattice(int(t[i]), tuple(a[i] for a in arrs), centers[i], float(yaws[i]), map_res, res)

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


def _fuse_one_range(drive_path: str, out_path: str, rng: str, cfg_json: dict) -> tuple[str, np.ndarray, dict[str, float], int]:
    import zarr

    cfg = GtgenConfig.model_validate(cfg_json)
    drive = zarr.open_group(drive_path, mode="r")
    out = zarr.open_group(out_path, mode="r+")
    grid = cfg.grids.get(rng)
    maps = zarr_map_source(drive, rng, grid.resolution_m)
    samples = sample_grids(drive, rng, grid.size, grid.resolution_m)
    arrays = {name: out[f"{grp}/{rng}/{name}"] for grp, names in (("fused", ("elevation_m", "confidence", "risk", "count", "last_dt_s", "region")), ("xracer", ())) for name in names}
    xr = {name: out[f"xracer/{rng}/{name}"] for name in ("elevation_m", "risk", "confidence")}
    empty = np.zeros(len(samples), bool)
    regions = np.zeros(4, np.int64)
    for k, f in track(fuse_range(maps, samples, params(cfg)), f"fuse: {rng}", total=len(samples)):
        arrays["elevation_m"][k] = f.elevation
        arrays["confidence"][k] = f.confidence
        arrays["risk"][k] = f.risk
        arrays["count"][k] = f.count
        arrays["last_dt_s"][k] = f.last_dt_s
        arrays["region"][k] = f.region
        xr["elevation_m"][k] = f.xr_elevation
        xr["risk"][k] = f.xr_risk
        xr["confidence"][k] = f.xr_confidence
        empty[k] = not f.count.any()
        regions += np.bincount(f.region.ravel(), minlength=4)
    total = max(int(regions.sum()), 1)
    cov = {"obs_pc": regions[1] / total, "obs_f": regions[2] / total, "unobs": regions[3] / total}
    return rng, empty, {k: round(float(v), 4) for k, v in cov.items()}, maps.loads


def run_fuse(drive_path: Path, out: Path, cfg: GtgenConfig, workers: int = 2) -> FuseResult:
    """Fuse the maps of drive store ``drive_path`` into the fused store ``out`` (atomically)."""
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
        jobs = [(str(drive_path), str(tmp), r, cfg_json) for r in RANGES]
        if workers > 1:
            from concurrent.futures import ProcessPoolExecutor
            import multiprocessing as mp

            with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=mp.get_context("spawn")) as ex:
                results = list(ex.map(_fuse_one_range, *zip(*jobs)))
        else:
            results = [_fuse_one_range(*j) for j in jobs]
        reason = np.zeros(S, np.uint8)
        for _, empty, _, _ in results:
            reason[empty] = reasons.NO_FUSED_MAPS
        root.create_array("samples/reason", shape=(S,), dtype="uint8", chunks=(S,), fill_value=0)[:] = reason
        coverage = {r: cov for r, _, cov, _ in results}
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
    return FuseResult(out, S, int((reason == 0).sum()), rejected, coverage, {r: n for r, _, _, n in results})


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
