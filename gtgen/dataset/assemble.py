"""Assembling dataset samples: a kept sample's labels (fused, DEM-filled where
unobserved), the X-Racer baseline and the aligned DEM, and its paired inputs (images,
calibration, voxel points in the target frame, the raw min-z grid), a shard at a time.

``build_block`` runs in pool workers beside dem-align's ICP chain; each worker opens the
stores itself from a picklable ``Context``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.config import RANGES, GtgenConfig
from gtgen.dataset.split import split_of
from gtgen.dataset.writer import write_block
from gtgen.dem.place import dem_patch
from gtgen.dem.tiles import DemMosaic, TileIndex
from gtgen.geometry import (
    grid_xy,
    make_transform,
    quat_to_matrix,
    quat_to_yaw,
    yaw_transform,
)
from gtgen.storage.chunks import ChunkFiles, Encoded
from gtgen.storage.schema import FUSED

# the fused arrays a dataset sample is built from; those not decoded here go into the
# dataset unchanged, as encoded bytes
FUSED_READ = tuple(s.path for s in FUSED.arrays if not s.path.startswith("samples/"))
FUSED_DECODED = {f"fused/{r}/{name}" for r in RANGES for name in ("region", "elevation_m")}


@dataclass(frozen=True)
class Context:
    """What a block-building worker needs to open everything itself (picklable)."""

    drive_path: str
    fused_path: str
    dem_dir: str
    index_cache: str
    crs: str  # the drive's working CRS
    exclude_tiles: tuple[int, ...]  # DEM tiles judged wrong: not used for filling
    out_path: str
    cfg_json: dict


@dataclass(frozen=True)
class Kept:
    """A kept sample: its index in the drive store and its DEM placement after ICP."""

    k: int
    T_crs_target: NDArray
    fitness: float
    rmse_m: float
    T_correction: NDArray
    dem_disagreement: float
    gnss_offset_m: float
    vegetation_share: float


_OPEN: dict[tuple[str, str, str], tuple] = {}


def _open(ctx: Context) -> tuple:
    """Return (drive, fused chunk files, DEM mosaic, config) of ``ctx``, opened once per worker."""
    import zarr

    key = (ctx.drive_path, ctx.fused_path, ctx.out_path)
    if key not in _OPEN:
        for opened in _OPEN.values():
            opened[2].close()
        _OPEN.clear()
        fused = zarr.open_group(ctx.fused_path, mode="r")
        _OPEN[key] = (zarr.open_group(ctx.drive_path, mode="r"), {name: ChunkFiles(fused[name]) for name in FUSED_READ},
                      DemMosaic(TileIndex.build(Path(ctx.dem_dir), cache=Path(ctx.index_cache), update_cache=False), ctx.crs,
                                frozenset(ctx.exclude_tiles)),
                      GtgenConfig.model_validate(ctx.cfg_json))
    return _OPEN[key]


def raw_min_z(points: NDArray, size: int, res: float) -> NDArray[np.float32]:
    """Return the lowest point per cell of a (size, size) target grid of ``res`` (NaN where none)."""
    out = np.full(size * size, np.inf, np.float32)
    half = 0.5 * size * res
    i = np.floor((points[:, 0] + half) / res).astype(np.int64)
    j = np.floor((points[:, 1] + half) / res).astype(np.int64)
    ok = (i >= 0) & (i < size) & (j >= 0) & (j < size)
    np.minimum.at(out, i[ok] * size + j[ok], points[ok, 2])
    out[np.isinf(out)] = np.nan
    return out.reshape(size, size)


def build_block(ctx: Context, start: int, items: list[Kept]) -> list[NDArray[np.float32]]:
    """Build the kept samples ``items`` and write them from dataset index ``start``;
    return their voxel points in the target frame (appended in order by the caller)."""
    drive, fused, dem, cfg = _open(ctx)
    grids = {r: grid_xy(cfg.grids.get(r).size, cfg.grids.get(r).resolution_m) for r in RANGES}
    vox_index, vox_n = drive["samples/voxel_index"][:], drive["voxel_maps/n_points"][:]
    # the small per-sample arrays: one zarr read each for the block's samples (only theirs:
    # rejected ones between them are skipped), as zarr's cost per call dominates
    ks = np.array([it.k for it in items])
    rows = {name: drive[name].oindex[ks] for name in ("samples/pos_odom_m", "samples/quat_odom_xyzw", "samples/images", "samples/t_ns",
                                                      "samples/T_base_cam")}
    vs = np.unique(vox_index[ks])
    vox = drive["voxel_maps/points_odom_m"].oindex[vs]
    K = drive["calib/K"][:]
    samples, points = [], []
    for j, it in enumerate(items):
        pos, quat = rows["samples/pos_odom_m"][j], rows["samples/quat_odom_xyzw"][j]
        yaw = float(quat_to_yaw(quat))
        fused_k = {name: f.read(it.k) if name in FUSED_DECODED else f.encoded(it.k) for name, f in fused.items()}
        sample = sample_arrays(fused_k, dem, it.T_crs_target, grids)
        v = vox_index[it.k]
        pts = vox[np.searchsorted(vs, v), : vox_n[v]].astype(np.float64)
        pts_t = ((pts - pos) @ yaw_transform(0, 0, 0, yaw)[:3, :3]).astype(np.float32)
        sample.update({"inputs/K": K, "inputs/T_base_cam": rows["samples/T_base_cam"][j]})
        sample.update(_inputs_and_meta(cfg, it, rows["samples/images"][j], rows["samples/t_ns"][j], pos, quat, yaw, pts_t))
        samples.append(sample)
        points.append(pts_t)
    write_block(Path(ctx.out_path), start, samples)
    return points


def _inputs_and_meta(cfg: GtgenConfig, it: Kept, images: NDArray, t_ns: int, pos: NDArray, quat: NDArray, yaw: float,
                     pts_t: NDArray) -> dict[str, Any]:
    gs = cfg.grids.short
    T, C = it.T_crs_target, it.T_correction
    return {
        "inputs/images": images,
        "inputs/T_target_base": make_transform(yaw_transform(0, 0, 0, -yaw)[:3, :3] @ quat_to_matrix(quat), np.zeros(3)),
        "inputs/raw_elevation_m": raw_min_z(pts_t, gs.size, gs.resolution_m),
        "meta/t_ns": np.int64(t_ns),
        "meta/drive": np.uint16(0),
        "meta/pos_odom_m": pos,
        "meta/yaw_odom_rad": np.float64(yaw),
        "meta/crs_en_m": T[:2, 3],
        "meta/T_crs_target": T,
        "meta/icp_fitness": np.float32(it.fitness),
        "meta/icp_rmse_m": np.float32(it.rmse_m),
        "meta/icp_correction": np.array([C[0, 3], C[1, 3], C[2, 3], np.arctan2(C[1, 0], C[0, 0])], np.float32),
        "meta/dem_disagreement": np.float32(it.dem_disagreement),
        "meta/gnss_offset_m": np.float32(it.gnss_offset_m),
        "meta/vegetation_share": np.float32(it.vegetation_share),
        "meta/split": np.uint8(split_of(*T[:2, 3], cfg.shards)),
    }


def sample_arrays(fused: dict[str, NDArray | Encoded], dem_mosaic: DemMosaic, T_crs_target: NDArray, grids: dict) -> dict[str, NDArray | Encoded]:
    """Return one sample's label, X-Racer and DEM arrays from its fused arrays (by path;
    region and elevation as values, the rest as values or encoded chunks, which stay as
    they come: the dataset holds them unchanged)."""
    out: dict[str, NDArray | Encoded] = {}
    for r in RANGES:
        X, Y = grids[r]
        dem = dem_patch(dem_mosaic, T_crs_target, X, Y)
        region = fused[f"fused/{r}/region"]
        elev = fused[f"fused/{r}/elevation_m"]
        unobs = region == codes.UNOBS
        elev = np.where(unobs, dem, elev).astype(np.float32)
        region[unobs & ~np.isfinite(dem)] = codes.NO_LABEL
        out[f"labels/{r}/elevation_m"] = elev
        out[f"labels/{r}/region"] = region
        for name in ("risk", "confidence", "count", "last_dt_s"):
            out[f"labels/{r}/{name}"] = fused[f"fused/{r}/{name}"]
        for name in ("elevation_m", "risk", "confidence"):
            out[f"xracer/{r}/{name}"] = fused[f"xracer/{r}/{name}"]
        out[f"dem/{r}/elevation_m"] = dem
    return out
