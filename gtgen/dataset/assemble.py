"""Assembling dataset samples: a kept sample's labels (fused, DEM-filled where
unobserved), the X-Racer baseline and the aligned DEM, and its paired inputs (images,
calibration, voxel points in the target frame, the raw min-z grid, the N-scan input when
the drive has raw scans), a shard at a time.

``build_block`` runs in pool workers beside dem-align's ICP chain; each worker opens the
stores itself from a picklable ``Context``.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.config import RANGES, GtgenConfig
from gtgen.dataset.scans import ScanInput
from gtgen.dataset.split import split_of
from gtgen.dem.place import dem_patch
from gtgen.dem.tiles import DemRef, DemSource
from gtgen.geometry import (
    make_transform,
    quat_to_matrix,
    quat_to_yaw,
    yaw_transform,
)
from gtgen.grids import grid_xy, raw_min_z
from gtgen.storage.dataset import DatasetSample
from gtgen.storage.dataset_writer import write_block
from gtgen.storage.drive import DriveStore
from gtgen.storage.fused import FusedSample, FusedStore

# the fused layers a dataset sample is built from as values; the others go into the
# dataset unchanged, as encoded bytes
DECODED = {(r, layer) for r in RANGES for layer in ("region", "elevation_m")}


@dataclass(frozen=True)
class Context:
    """What a block-building worker needs (picklable: the stores reopen themselves)."""

    drive: DriveStore
    fused: FusedStore
    dem: DemRef | None  # the drive's DEM in its working CRS, without the tiles set aside (None: no DEM)
    out_path: Path
    cfg: GtgenConfig


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


_OPEN: dict[tuple[Path, DemRef], DemSource] = {}


def _dem(ctx: Context) -> DemSource | None:
    """Return the DEM of ``ctx``, opened once per worker, dataset and DEM (a pass of the
    ICP chain that sets tiles aside or puts them back reads another; None: no DEM)."""
    if ctx.dem is None:
        return None
    key = (ctx.out_path, ctx.dem)
    if key not in _OPEN:
        for dem in _OPEN.values():
            dem.close()
        _OPEN.clear()
        _OPEN[key] = ctx.dem.open()
    return _OPEN[key]


def build_block(ctx: Context, start: int, items: list[Kept]) -> list[NDArray[np.float32]]:
    """Build the kept samples ``items`` and write them from dataset index ``start``;
    return their voxel points in the target frame (appended in order by the caller)."""
    drive, fused, dem, cfg = ctx.drive, ctx.fused, _dem(ctx), ctx.cfg
    grids = {r: grid_xy(cfg.grids.get(r).size, cfg.grids.get(r).resolution_m) for r in RANGES}
    s = drive.samples
    # the block's JPEG files and voxel maps in one read each (only theirs: rejected samples
    # between them are skipped), as zarr's cost per call dominates
    ks = np.array([it.k for it in items])
    cameras = bool(drive.cameras)
    jpeg, jpeg_n = drive.jpeg(ks) if cameras else (None, None)
    vs = np.unique(s.voxel_index[ks])
    vox, vox_n = drive.voxel_points(vs), drive.voxel_counts()
    K = drive.K()
    scans = ScanInput(drive, cfg, ks) if len(drive.scans) else None
    samples, points = [], []
    for j, it in enumerate(items):
        pos, quat = s.pos_odom_m[it.k], s.quat_odom_xyzw[it.k]
        yaw = float(quat_to_yaw(quat))
        sample = sample_arrays(fused.sample(it.k, DECODED), dem, it.T_crs_target, grids, cfg.shards.qa_ranges)
        v = s.voxel_index[it.k]
        pts = vox[np.searchsorted(vs, v), : vox_n[v]].astype(np.float64)
        pts_t = ((pts - pos) @ yaw_transform(0, 0, 0, yaw)[:3, :3]).astype(np.float32)
        if cameras:
            sample.inputs.update({"K": K, "T_base_cam": s.T_base_cam[it.k], "jpeg": jpeg[j], "jpeg_nbytes": jpeg_n[j].astype(np.int32)})
        _inputs_and_meta(sample, cfg, it, int(s.t_ns[it.k]), pos, quat, yaw, pts_t)
        if scans is not None:
            sample.inputs["scan_points_m"], sample.inputs["scan_counts"] = scans.sample(j, pos, yaw)
        samples.append(sample)
        points.append(pts_t)
    write_block(Path(ctx.out_path), start, samples)
    return points


def _inputs_and_meta(sample: DatasetSample, cfg: GtgenConfig, it: Kept, t_ns: int, pos: NDArray, quat: NDArray,
                     yaw: float, pts_t: NDArray) -> None:
    gs = cfg.grids.short
    T, C = it.T_crs_target, it.T_correction
    sample.inputs.update({
        "T_target_base": make_transform(yaw_transform(0, 0, 0, -yaw)[:3, :3] @ quat_to_matrix(quat), np.zeros(3)),
        "raw_elevation_m": raw_min_z(pts_t, gs.size, gs.resolution_m),
    })
    sample.meta.update({
        "t_ns": np.int64(t_ns),
        "drive": np.uint16(0),
        "pos_odom_m": pos,
        "yaw_odom_rad": np.float64(yaw),
        "crs_en_m": T[:2, 3],
        "T_crs_target": T,
        "icp_fitness": np.float32(it.fitness),
        "icp_rmse_m": np.float32(it.rmse_m),
        "icp_correction": np.array([C[0, 3], C[1, 3], C[2, 3], np.arctan2(C[1, 0], C[0, 0])], np.float32),
        "dem_disagreement": np.float32(it.dem_disagreement),
        "gnss_offset_m": np.float32(it.gnss_offset_m),
        "vegetation_share": np.float32(it.vegetation_share),
        # without a DEM the geography blocks are the drive's own odom frame's
        "split": np.uint8(split_of(*(T[:2, 3] if np.isfinite(T).all() else pos[:2]), cfg.shards)),
    })


def sample_arrays(fused: FusedSample, dem_source: DemSource | None, T_crs_target: NDArray, grids: dict,
                  whole_dem: Collection[str] = RANGES) -> DatasetSample:
    """Return one sample's label, X-Racer and DEM grids from its fused grids (region and
    elevation as values, the rest as values or encoded chunks, which stay as they come:
    the dataset holds them unchanged). The DEM grid of a range in ``whole_dem`` (the
    ranges whose DEM the dataset stores, ``shards.qa_ranges``) is sampled at every cell,
    of the others only at the unobserved cells the labels take it for (NaN elsewhere).
    Without a DEM (``dem_source`` None) its grids are NaN and the unobserved cells are
    left unlabelled."""
    out = DatasetSample({}, {}, {})
    for r in RANGES:
        X, Y = grids[r]
        labels = dict(fused.labels[r])
        region, elev = labels["region"], labels["elevation_m"]
        unobs = region == codes.UNOBS
        if dem_source is not None and r in whole_dem:
            dem = dem_patch(dem_source, T_crs_target, X, Y)
        else:
            dem = np.full(X.shape, np.nan, np.float32)
            if dem_source is not None:
                dem[unobs] = dem_patch(dem_source, T_crs_target, X, Y, at=unobs)
        labels["elevation_m"] = np.where(unobs, dem, elev).astype(np.float32)
        region[unobs & ~np.isfinite(dem)] = codes.NO_LABEL
        out.labels[r] = labels
        out.xracer[r] = dict(fused.xracer[r])
        out.dem[r] = dem
    return out
