"""``gtgen dem-align``: place the DEM, refine per sample by ICP, inpaint, write shards.

``run()`` reads like the steps: index the tiles, fit odom to the DEM CRS from GNSS,
estimate the vertical offset against the DEM, then per sample: prior placement (the
previous accepted sample's, else the drive fit), ICP, accept or reject, inpaint, write.
"""

from __future__ import annotations

import logging
import shutil
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen import __version__, reasons
from gtgen.bag import store as drive_store
from gtgen.bag.poses import PoseTrack
from gtgen.config import RANGES, GtgenConfig, save_config
from gtgen.dem.fit import PlanarFit, fit_planar
from gtgen.dem.icp import icp_4dof
from gtgen.dem.tiles import TileIndex, sample_bilinear
from gtgen.errors import AlignmentError, DemError
from gtgen.format import ChunkFiles, Encoded
from gtgen.fuse.run import open_fused
from gtgen.fuse.store import FUSED_ARRAYS
from gtgen.geometry import grid_xy, invert, make_transform, quat_to_matrix, quat_to_yaw, yaw_transform
from gtgen.progress import track
from gtgen.shards import schema as sc
from gtgen.shards.writer import ShardWriter

log = logging.getLogger(__name__)

MIN_ICP_POINTS = 100


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
    fitness: list[float] = field(default_factory=list)
    split_counts: dict[str, int] = field(default_factory=dict)


def default_dem_dir(cfg: GtgenConfig, drive) -> Path:
    """Return the DEM folder: ``dem.dir`` if set, else ``dem/`` beside the drive's first bag."""
    if cfg.dem.dir:
        return Path(cfg.dem.dir)
    bags = drive.attrs.get("bags") or []
    if not bags:
        raise DemError("no DEM folder: set dem.dir or pass --dem DIR")
    return Path(bags[0]["path"]).parent / "dem"


def _gnss_fit(cfg: GtgenConfig, drive, track_: PoseTrack, crs: str) -> PlanarFit:
    from pyproj import Transformer

    t = drive["gnss/t_ns"][:]
    if len(t) == 0:
        raise AlignmentError(f"GNSS absent for the whole drive (no fix on '{cfg.topics.gnss}'); dem-align needs GNSS to place the DEM")
    lat, lon, alt = drive["gnss/lat_deg"][:], drive["gnss/lon_deg"][:], drive["gnss/alt_m"][:]
    status = drive["gnss/status"][:]
    var = drive["gnss/var_enu_m2"][:]
    ok = (status >= 0) & np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt)
    E, N = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)
    pos, _ = track_.interpolate(t, strict=False)
    enu = np.column_stack([E, N, alt])
    enu[~ok] = np.nan
    return fit_planar(pos, enu, var[:, :2].mean(axis=1), cfg.dem.gnss_outlier_m, cfg.dem.min_gnss_fixes)


def _crs_odom(fit: PlanarFit, dz: float) -> NDArray:
    return yaw_transform(fit.tx, fit.ty, dz, fit.yaw)


def _dem_patch(index: TileIndex, T_crs_target: NDArray, X: NDArray, Y: NDArray, margin: float = 5.0) -> NDArray[np.float32]:
    """Return DEM heights in the target frame at target cells (X, Y) (NaN where no DEM)."""
    R, t = T_crs_target[:3, :3], T_crs_target[:3, 3]
    E = R[0, 0] * X + R[0, 1] * Y + t[0]
    N = R[1, 0] * X + R[1, 1] * Y + t[1]
    grid, origin = index.read(E.min() - margin, N.min() - margin, E.max() + margin, N.max() + margin)
    return sample_bilinear(grid, origin, E, N) - np.float32(t[2])


def _dz_against_dem(index: TileIndex, fused, track_: PoseTrack, drive, fit: PlanarFit, X: NDArray, Y: NDArray, n: int = 24) -> float:
    """Return the median DEM height minus odom height over observed short cells of a few samples."""
    S = fused["fused/short/region"].shape[0]
    pos = drive["samples/pos_odom_m"][:]
    yaw = quat_to_yaw(drive["samples/quat_odom_xyzw"][:])
    diffs = []
    for k in np.unique(np.linspace(0, S - 1, min(n, S)).astype(int)):
        reg = fused["fused/short/region"][k]
        el = fused["fused/short/elevation_m"][k]
        obs = (reg == 1) | (reg == 2)
        if not obs.any():
            continue
        T = _crs_odom(fit, 0.0) @ yaw_transform(*pos[k], yaw[k])
        dem = _dem_patch(index, T, X, Y)
        d = (dem - el)[obs]  # dem is relative to odom z 0 + base z; both relative to base z
        diffs.append(d[np.isfinite(d)])
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    if len(d) < 50:
        raise DemError("the DEM has no valid cells under the drive's observed terrain: wrong DEM folder, wrong area, or nodata")
    return float(np.median(d))


def _split(E: float, N: float, cfg: GtgenConfig) -> int:
    B = cfg.shards.split_block_m
    key = f"{int(np.floor(E / B))},{int(np.floor(N / B))}".encode()
    return 1 if (zlib.crc32(key) / 2**32) < cfg.shards.val_fraction else 0


def _normals(Z: NDArray, res: float) -> NDArray:
    gx, gy = np.gradient(Z, res)
    n = np.stack([-gx, -gy, np.ones_like(Z)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _raw_min_z(points: NDArray, size: int, res: float) -> NDArray[np.float32]:
    out = np.full(size * size, np.inf, np.float32)
    half = 0.5 * size * res
    i = np.floor((points[:, 0] + half) / res).astype(np.int64)
    j = np.floor((points[:, 1] + half) / res).astype(np.int64)
    ok = (i >= 0) & (i < size) & (j >= 0) & (j < size)
    np.minimum.at(out, i[ok] * size + j[ok], points[ok, 2])
    out[np.isinf(out)] = np.nan
    return out.reshape(size, size)


def run_dem_align(drive_path: Path, fused_path: Path, dem_dir: Path | None, out: Path, cfg: GtgenConfig, workers: int = 2) -> AlignResult:
    """Align the DEM to every fused sample of a drive and write the dataset ``out`` (atomically).

    The ICP chain is sequential; building and writing the accepted samples runs on
    ``workers`` processes alongside it. The dataset does not depend on ``workers``.
    """
    drive = drive_store.open_drive(drive_path)
    fused = open_fused(fused_path)
    dem_dir = dem_dir or default_dem_dir(cfg, drive)
    cache = out.parent / "dem-index.json"
    index = TileIndex.build(dem_dir, cache=cache)
    track_ = PoseTrack(drive["poses/t_ns"][:], drive["poses/pos_odom_m"][:], drive["poses/quat_odom_xyzw"][:],
                       int(cfg.extract.pose_tolerance_s * 1e9))
    fit = _gnss_fit(cfg, drive, track_, index.crs)
    _check_overlap(index, fit, track_, dem_dir)
    gs = cfg.grids.short
    Xs, Ys = grid_xy(gs.size, gs.resolution_m)
    dz_dem = _dz_against_dem(index, fused, track_, drive, fit, Xs, Ys)
    tmp = drive_store.partial_path(out)
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        ctx = _Context(str(drive_path), str(fused_path), str(dem_dir), str(cache), str(tmp), cfg.model_dump(mode="json"))
        result = _align_all(cfg, ctx, drive, fused, index, fit, dz_dem, tmp, workers)
        result.store = out
        drive_store.finalize(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        index.close()
    return result


def _check_overlap(index: TileIndex, fit: PlanarFit, track_: PoseTrack, dem_dir: Path) -> None:
    en = fit.apply_xy(track_.pos[:, :2])
    l, b, r, t = index.bounds()
    inside = (en[:, 0] > l) & (en[:, 0] < r) & (en[:, 1] > b) & (en[:, 1] < t)
    if not inside.any():
        raise DemError(
            f"DEM folder '{dem_dir}' does not cover the drive: drive spans E {en[:, 0].min():.0f}..{en[:, 0].max():.0f}, "
            f"N {en[:, 1].min():.0f}..{en[:, 1].max():.0f} in {index.crs}; tiles span E {l:.0f}..{r:.0f}, N {b:.0f}..{t:.0f}"
        )


def _align_all(cfg: GtgenConfig, ctx: _Context, drive, fused, index: TileIndex, fit: PlanarFit, dz_dem: float,
               tmp: Path, workers: int) -> AlignResult:
    """Run the ICP chain here (each sample starts from the previous accepted placement) and
    build and write the accepted samples shard by shard on ``workers`` processes meanwhile."""
    S = int(drive["samples/t_ns"].shape[0])
    t_s = drive["samples/t_ns"][:]
    pos = drive["samples/pos_odom_m"][:]
    yaw = quat_to_yaw(drive["samples/quat_odom_xyzw"][:])
    reason_f = fused["samples/reason"][:]
    W, H = drive.attrs["image_size"]
    gs = cfg.grids.short
    Xs, Ys = grid_xy(gs.size, gs.resolution_m)
    writer = ShardWriter(tmp, S, cfg.grids.micro.size, gs.size, (H, W))
    T_prior = _crs_odom(fit, dz_dem)
    fitness: list[float] = []
    dc = cfg.dem
    blocks = _Blocks(ctx, workers, writer)
    short_region, short_elev = ChunkFiles(fused["fused/short/region"]), ChunkFiles(fused["fused/short/elevation_m"])
    for k in track(range(S), "dem-align: samples"):
        if reason_f[k]:
            writer.reject(int(t_s[k]), 0, int(reason_f[k]))
            continue
        T_odom_target = yaw_transform(*pos[k], yaw[k])
        T_crs_target = T_prior @ T_odom_target
        dem_s = _dem_patch(index, T_crs_target, Xs, Ys)
        reg_s = short_region.read(k)
        el_s = short_elev.read(k)
        src_mask = ((reg_s == 1) | (reg_s == 2)) & np.isfinite(el_s)
        tgt_mask = np.isfinite(dem_s)
        if not tgt_mask.any():
            writer.reject(int(t_s[k]), 0, reasons.NO_DEM)
            continue
        if src_mask.sum() < MIN_ICP_POINTS:
            writer.reject(int(t_s[k]), 0, reasons.TOO_FEW_POINTS)
            continue
        src = np.column_stack([Xs[src_mask], Ys[src_mask], el_s[src_mask]])
        if len(src) > dc.icp_max_points:
            src = src[np.random.default_rng(k).choice(len(src), dc.icp_max_points, replace=False)]  # per-sample seed: order-free
        tgt = np.column_stack([Xs[tgt_mask], Ys[tgt_mask], dem_s[tgt_mask]])
        nrm = _normals(np.where(tgt_mask, dem_s, np.nanmedian(dem_s)), gs.resolution_m)[tgt_mask]
        res = icp_4dof(src, tgt, nrm, dc.icp_max_distance_m, dc.icp_iterations)
        fitness.append(res.fitness)
        if res.fitness < dc.min_fitness:
            writer.reject(int(t_s[k]), 0, reasons.LOW_FITNESS, res.fitness, res.rmse_m)
            continue
        if res.rmse_m > dc.max_rmse_m:
            writer.reject(int(t_s[k]), 0, reasons.HIGH_RMSE, res.fitness, res.rmse_m)
            continue
        T_crs_target = T_crs_target @ res.T
        T_prior = T_crs_target @ invert(T_odom_target)  # warm start for the next sample
        blocks.add((k, T_crs_target, res.fitness, res.rmse_m, res.T))
    blocks.finish()
    rej = [r[2] for r in writer.rejected]
    attrs = drive_store.jsonable({
        "store": sc.DATASET_STORE, "schema_version": sc.SCHEMA_VERSION, "complete": True,
        "gtgen_version": __version__, "config": cfg.model_dump(mode="json"),
        "drives": [{"drive_store": str(Path(ctx.drive_path).resolve()), "bags": drive.attrs.get("bags", [])}],
        "crs": index.crs, "reasons": reasons.REASONS, "splits": sc.SPLITS,
        "alignment": {"gnss_yaw_rad": fit.yaw, "gnss_tx_m": fit.tx, "gnss_ty_m": fit.ty, "gnss_rms_m": fit.rms_m,
                      "gnss_used": fit.n_used, "gnss_outliers": fit.n_outliers, "dz_dem_m": dz_dem,
                      "geoid_offset_m": fit.dz_gnss - dz_dem},
        "image_size": [W, H], "cameras": drive.attrs.get("cameras"),
    })
    n = writer.close(attrs)
    save_config(cfg, tmp / "gtgen-config.yaml")
    splits = {}
    if n:
        sp = writer.root["meta/split"][:]
        splits = {sc.SPLITS[int(v)]: int((sp == v).sum()) for v in np.unique(sp)}
    return AlignResult(tmp, S, n, {reasons.name(c): rej.count(c) for c in sorted(set(rej))}, fit, dz_dem,
                       fit.dz_gnss - dz_dem, fitness, splits)


@dataclass(frozen=True)
class _Context:
    """What a block-building worker needs to open everything itself (picklable)."""

    drive_path: str
    fused_path: str
    dem_dir: str
    index_cache: str
    out_path: str
    cfg_json: dict


class _Blocks:
    """Accepted samples, built and written one shard at a time, in worker processes."""

    def __init__(self, ctx: _Context, workers: int, writer: ShardWriter) -> None:
        self.ctx, self.writer = ctx, writer
        self.items: list[tuple] = []
        self.start = 0
        self.futures: list = []
        self.pool = None
        if workers > 1:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            self.pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"))

    def add(self, item: tuple) -> None:
        self.items.append(item)
        if len(self.items) == sc.SAMPLES_PER_SHARD:
            self._submit()

    def _submit(self) -> None:
        if not self.items:
            return
        args = (self.ctx, self.start, self.items)
        if self.pool is None:
            self.writer.add_block(_build_block(*args))
        else:
            self.futures.append(self.pool.submit(_build_block, *args))
            # collect finished blocks in order, so memory holds only a few
            while self.futures and (self.futures[0].done() or len(self.futures) > 4):
                self.writer.add_block(self.futures.pop(0).result())
        self.start += len(self.items)
        self.items = []

    def finish(self) -> None:
        try:
            self._submit()
            for f in self.futures:
                self.writer.add_block(f.result())
        finally:
            if self.pool is not None:
                self.pool.shutdown(wait=True, cancel_futures=True)


_OPEN: dict[tuple[str, str, str], tuple] = {}


# the fused arrays a dataset sample is built from; those not decoded here go into the
# dataset unchanged, as encoded bytes
_FUSED_READ = tuple(s.path for s in FUSED_ARRAYS if not s.path.startswith("samples/"))
_FUSED_DECODED = {f"fused/{r}/{name}" for r in RANGES for name in ("region", "elevation_m")}


def _build_block(ctx: _Context, start: int, items: list[tuple]) -> list[NDArray[np.float32]]:
    """Build the accepted samples ``items`` and write them from dataset index ``start``;
    return their voxel points in the target frame (appended in order by the caller)."""
    import zarr

    from gtgen.shards.writer import write_block

    key = (ctx.drive_path, ctx.fused_path, ctx.out_path)
    if key not in _OPEN:
        _OPEN.clear()
        fused = zarr.open_group(ctx.fused_path, mode="r")
        _OPEN[key] = (zarr.open_group(ctx.drive_path, mode="r"), {name: ChunkFiles(fused[name]) for name in _FUSED_READ},
                      TileIndex.build(Path(ctx.dem_dir), cache=Path(ctx.index_cache)), GtgenConfig.model_validate(ctx.cfg_json))
    drive, fused, index, cfg = _OPEN[key]
    gs = cfg.grids.short
    grids = {r: grid_xy(cfg.grids.get(r).size, cfg.grids.get(r).resolution_m) for r in RANGES}
    vox_index, vox_n = drive["samples/voxel_index"][:], drive["voxel_maps/n_points"][:]
    K, T_base_cam = drive["calib/K"][:], drive["calib/T_base_cam"][:]
    # the small per-sample arrays: one zarr read each for the block's samples (only theirs:
    # rejected ones between them are skipped), as zarr's cost per call dominates
    ks = np.array([it[0] for it in items])
    rows = {name: drive[name].oindex[ks] for name in ("samples/pos_odom_m", "samples/quat_odom_xyzw", "samples/images", "samples/t_ns")}
    vs = np.unique(vox_index[ks])
    vox = drive["voxel_maps/points_odom_m"].oindex[vs]
    samples, points = [], []
    for j, (k, T_crs_target, fit_k, rmse_k, T_corr) in enumerate(items):
        pos = rows["samples/pos_odom_m"][j]
        quat = rows["samples/quat_odom_xyzw"][j]
        yaw = float(quat_to_yaw(quat))
        rows_k = {name: fused[name].read(k) if name in _FUSED_DECODED else fused[name].encoded(k) for name in _FUSED_READ}
        sample = _sample_arrays(rows_k, index, T_crs_target, grids)
        T_target_base = make_transform(yaw_transform(0, 0, 0, -yaw)[:3, :3] @ quat_to_matrix(quat), np.zeros(3))
        v = vox_index[k]
        pts = vox[np.searchsorted(vs, v), : vox_n[v]].astype(np.float64)
        pts_t = ((pts - pos) @ yaw_transform(0, 0, 0, yaw)[:3, :3]).astype(np.float32)
        sample.update({
            "inputs/images": rows["samples/images"][j],
            "inputs/K": K,
            "inputs/T_base_cam": T_base_cam,
            "inputs/T_target_base": T_target_base,
            "inputs/raw_elevation_m": _raw_min_z(pts_t, gs.size, gs.resolution_m),
            "meta/t_ns": np.int64(rows["samples/t_ns"][j]),
            "meta/drive": np.uint16(0),
            "meta/pos_odom_m": pos,
            "meta/yaw_odom_rad": np.float64(yaw),
            "meta/crs_en_m": T_crs_target[:2, 3],
            "meta/T_crs_target": T_crs_target,
            "meta/icp_fitness": np.float32(fit_k),
            "meta/icp_rmse_m": np.float32(rmse_k),
            "meta/icp_correction": np.array([T_corr[0, 3], T_corr[1, 3], T_corr[2, 3], np.arctan2(T_corr[1, 0], T_corr[0, 0])], np.float32),
            "meta/split": np.uint8(_split(*T_crs_target[:2, 3], cfg)),
        })
        samples.append(sample)
        points.append(pts_t)
    write_block(Path(ctx.out_path), start, samples)
    return points


def _sample_arrays(fused: dict[str, NDArray | Encoded], index: TileIndex, T_crs_target: NDArray, grids) -> dict[str, NDArray | Encoded]:
    """Return one sample's label, X-Racer and DEM arrays from its fused arrays (by path;
    region and elevation as values, the rest as values or encoded chunks, which stay as
    they come: the dataset holds them unchanged)."""
    out: dict[str, NDArray | Encoded] = {}
    for r in RANGES:
        X, Y = grids[r]
        dem = _dem_patch(index, T_crs_target, X, Y)
        region = fused[f"fused/{r}/region"]
        elev = fused[f"fused/{r}/elevation_m"]
        unobs = region == 3
        elev = np.where(unobs, dem, elev).astype(np.float32)
        region[unobs & ~np.isfinite(dem)] = 0
        out[f"labels/{r}/elevation_m"] = elev
        out[f"labels/{r}/region"] = region
        for name in ("risk", "confidence", "count", "last_dt_s"):
            out[f"labels/{r}/{name}"] = fused[f"fused/{r}/{name}"]
        for name in ("elevation_m", "risk", "confidence"):
            out[f"xracer/{r}/{name}"] = fused[f"xracer/{r}/{name}"]
        out[f"dem/{r}/elevation_m"] = dem
    return out
