"""The settings of each stage after synth: extract, fuse, dem-align, the report, the shards,
the trainer and the mapping of raw lidar."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from gtgen.config.base import MAX_SPAN_S, RANGES, _Model


class ExtractConfig(_Model):
    """Bags -> drive store, and sample selection."""

    stride_m: float = Field(2.0, gt=0, description="travel between samples [m]")
    reference: str | None = Field(None, description="the sensor whose stamps sample times snap to: a camera's name (topics.cameras) or 'lidar' (the first topics.lidar topic the bags hold); null: the first camera, else the lidar")
    image_skew_s: float = Field(0.05, ge=0, le=MAX_SPAN_S, description="max image-to-sample time skew [s]")
    map_skew_s: float = Field(0.1, ge=0, le=MAX_SPAN_S, description="max GridMap-to-sample time skew [s]")
    voxel_skew_s: float = Field(0.3, ge=0, le=MAX_SPAN_S, description="max voxel-map-to-sample skew [s]; the voxel map is stored with its pose, so a few hundred ms is harmless")
    pose_tolerance_s: float = Field(0.1, ge=0, le=MAX_SPAN_S, description="max gap to an odometry message before a pose is refused [s]")
    map_rate_hz: float = Field(2.0, ge=1 / MAX_SPAN_S, description="GridMaps kept per range [Hz]; they overlap heavily")
    image_width: int = Field(640, ge=8, le=4096, description="stored image width at most: the source is scaled to fit image_width x image_height, aspect kept, never upscaled [px]")
    image_height: int = Field(396, ge=8, le=4096, description="stored image height at most [px]")
    jpeg_quality: int = Field(90, ge=1, le=95, description="JPEG quality of stored images that are resized or rectified (the camera's own JPEG is kept as it is otherwise)")
    scan_skew_s: float = Field(0.2, ge=0, le=MAX_SPAN_S, description="max scan-to-sample skew of a sample's newest raw scan per lidar [s] (or two of the lidar's periods, if that is longer)")
    max_scan_points: int = Field(131072, ge=1, le=10_000_000, description="points stored per raw scan (the nearest kept beyond)")
    record_skew_warn_s: float = Field(1.0, ge=0, le=MAX_SPAN_S, description="report header vs record time differences above this [s]")


class FuseConfig(_Model):
    """Hindsight fusion of the X-Racer maps in a window around each sample."""

    window_s: float = Field(60.0, gt=0, le=MAX_SPAN_S, description="future window after the sample [s], at most a day")
    past_s: float = Field(0.0, ge=0, le=MAX_SPAN_S, description="past window before the sample [s], at most a day")
    min_conf: float = Field(0.1, ge=0, le=1, description="elevation used where confidence > this")
    risk_min_conf: float = Field(0.5, ge=0, le=1, description="risk used where confidence >= this")
    tile_cells: int = Field(128, ge=8, le=4096, description="accumulator tile edge [cells]")
    chunk_samples: int = Field(128, ge=1, description="samples per parallel fusion job (exact: labels do not depend on it)")
    elevation_rule: Literal["mean", "ground"] = Field("mean", description="elevation over the window: 'mean' of the confident observations (the paper's), or 'ground': the mean of those not in a map's top layer (crowns, bushes: standing more than top_height_m above the map's opening by a top_footprint_m square), all of them where every one is")
    top_height_m: float = Field(0.5, gt=0, description="rule 'ground': a map cell this far above the map's opened surface is top layer [m]")
    top_footprint_m: float = Field(8.0, gt=0, description="rule 'ground': edge of the square the map's surface is opened by; wider than the widest crown [m]")


class DemConfig(_Model):
    """DEM placement, ICP refinement and inpainting."""

    enabled: bool = Field(True, description="false: no DEM (gtgen dem-align --no-dem): the dataset holds the fused labels alone, unobserved cells stay unlabelled (region 0) and samples are not georeferenced")
    dir: str | None = Field(None, description="DEM folder; default: 'dem/' beside the first bag")
    min_fitness: float = Field(0.6, ge=0, le=1, description="reject a sample below this ICP fitness")
    max_rmse_m: float = Field(0.25, gt=0, description="reject a sample above this ICP inlier RMSE [m]")
    icp_max_distance_m: float = Field(1.0, gt=0, description="ICP correspondence distance [m]")
    icp_iterations: int = Field(30, ge=1, description="ICP iterations")
    icp_max_points: int = Field(20000, ge=100, description="source points used by ICP (subsampled)")
    gnss_outlier_m: float = Field(4.0, gt=0, description="GNSS residual treated as an outlier [m]")
    min_gnss_fixes: int = Field(10, ge=3, description="fewest usable fixes for the drive fit")
    vegetation_m: float = Field(0.5, gt=0, description="observed cells in blobs standing this far above the DEM surface (after the median offset) are vegetation: left out of ICP, its fitness and the disagreement [m]")
    max_correction_m: float = Field(1.0, gt=0, description="reject a sample whose ICP moves it farther than this horizontally from its prior (the last kept placement carried by odometry) [m]")
    max_correction_z_m: float = Field(0.5, gt=0, description="reject a sample whose ICP moves it farther than this vertically from its prior [m]")
    max_correction_yaw_deg: float = Field(2.0, gt=0, description="reject a sample whose ICP turns it more than this from its prior [deg]")
    drift_allowance: float = Field(0.01, ge=0, description="the correction allowed grows by this per metre travelled since the last kept sample (odometry drift) [m/m]")
    disagreement_m: float = Field(0.5, gt=0, description="an observed ground cell disagrees with the aligned DEM when they differ by more than this [m]")
    max_disagreement: float = Field(0.1, ge=0, le=1, description="reject a sample when more than this share of its observed ground cells disagree with the aligned DEM")
    gnss_window_s: float = Field(10.0, gt=0, le=MAX_SPAN_S, description="GNSS fixes within this of a sample's time judge its placement [s]")
    min_window_fixes: int = Field(10, ge=1, description="fewest usable fixes in the window for the GNSS check (fewer: GNSS is not consulted)")
    max_gnss_offset_m: float = Field(5.0, gt=0, description="reject a sample whose placement puts the window's fixes farther than this (median) from the track [m]")
    judge_within_m: float = Field(20.0, gt=0, description="a sample whose prior is a kept placement farther back than this starts ICP with a coarse pass (odometry has drifted since) [m]")
    carry_over_m: float = Field(20.0, ge=0, description="a sample mostly over set-aside tiles is kept at the last kept placement carried by odometry (not refined by ICP, not filled from those tiles) while that placement is at most this far back; farther, or 0, it is rejected as suspect_tile [m]")
    max_tile_disagreement: float = Field(0.2, ge=0, le=1, description="a DEM tile is not used when more than this share of the observed ground cells over it disagree with it where the drive was placed (another place, a stale survey)")
    min_tile_cells: int = Field(2000, ge=1, description="observed ground cells a tile needs before the observed ground judges it")
    tile_border_gain: float = Field(1.5, gt=1, description="a tile is put back horizontally only when its borders continue its neighbours this many times better (height steps' spread) read at its measured offset than as it is")
    tile_offset_min_m: float = Field(0.5, ge=0, description="a tile is put back horizontally when its measured offset exceeds this and twice its uncertainty [m]")
    tile_offset_min_z_m: float = Field(0.1, ge=0, description="a tile is put back vertically when its measured offset exceeds this and twice its uncertainty [m]")
    max_tile_offset_m: float = Field(10.0, gt=0, description="a tile's offset is searched within this horizontally (and tiles whose files leave a gap this wide still neighbour) [m]")
    tile_track_min_m: float = Field(1.0, gt=0, description="a tile is read put back when the drive's placements over it stand farther than this from those over its other tiles, and farther than drift_allowance times the travel between them: a shift its borders could not see (smooth ground) that ICP followed [m]")
    tile_track_samples: int = Field(5, ge=1, description="kept samples over a tile (the base's position on it) before its placements are compared with the other tiles'")
    max_border_step_m: float = Field(0.15, gt=0, description="a tile whose heights step by more than this (spread about the median step) across its borders with its neighbours at every offset is set aside: another place [m]")

class ReportConfig(_Model):
    """What ``gtgen report`` calls a truly bad sample on a synthetic drive with truth."""

    bad_horizontal_m: float | None = Field(None, gt=0, description="also call a sample bad when it is placed farther than this from the truth horizontally [m]; off (null) by default: on smooth ground an offset of a metre moves no label, and bad_fill_m counts the offsets that do")
    bad_vertical_m: float = Field(0.15, gt=0, description="a sample placed farther than this from the truth vertically is bad [m]")
    bad_fill_m: float = Field(0.15, gt=0, description="a sample is bad when its DEM fill would be this wrong on average over its short grid [m]: the DEM where the sample was put minus the true ground (misplaced on a slope, a shifted or wrong tile, changed terrain)")


class PrecisionConfig(_Model):
    """Steps the dataset stores its float grids and points at, as CF packed integers
    (``scale_factor``; ``gtgen/storage/packing.py``): a value is stored rounded to its step,
    so it reads back within half a step."""

    elevation_m: float = Field(0.001, ge=1e-5, le=0.05, description="step of the label and X-Racer elevations (int32) [m]")
    fraction: float = Field(0.001, ge=2e-5, le=0.01, description="step of risk and confidence (uint16) [1]")
    time_s: float = Field(0.001, ge=1e-4, le=1.0, description="step of the label's last observation time (int32) [s]")
    dem_m: float = Field(0.01, ge=1e-5, le=0.1, description="step of the aligned DEM grids (int32) [m]")
    points_m: float = Field(0.01, ge=1e-4, le=0.05, description="step of the voxel and raw-scan point coordinates and of the raw min-z grid (int32) [m]")


class ShardsConfig(_Model):
    """The dataset store."""

    precision: PrecisionConfig = Field(default_factory=PrecisionConfig, description="steps of the packed arrays")
    qa_ranges: list[Literal["micro", "short"]] = Field(default_factory=list, description="ranges whose QA-only grids are stored (labels confidence, count, last_dt_s; X-Racer confidence; the aligned DEM): read by viz, export and report's comparisons, never by train or eval; [micro, short] keeps them all")

    val_fraction: float = Field(0.25, ge=0, lt=1, description="share of geography blocks held out")
    split_block_m: float = Field(200.0, gt=0, description="edge of the geography blocks of the split [m]")
    max_voxel_points: int = Field(60000, ge=1, le=10_000_000, description="voxel-map points kept per map: all of them near the vehicle, and beyond the radius that keeps them within this count one per far_voxel_m voxel")
    far_voxel_m: float = Field(0.8, gt=0, description="voxel edge of the far part of a voxel map that exceeds max_voxel_points [m]")
    max_scans: int = Field(10, ge=1, le=254, description="raw scans per lidar in a sample's N-scan input (inputs/scan_*; train.n_scans takes up to this many)")
    scan_travel_m: float = Field(2.0, ge=0, description="travel between the scans of the N-scan input (and between the scans extract keeps) [m]")
    scan_voxel_m: float = Field(0.4, gt=0, description="voxel edge of the N-scan input's filter (the first point per voxel, newest scan first) [m]")
    max_scan_points: int = Field(120000, ge=1, le=10_000_000, description="points of a sample's N-scan input (the nearest kept), within the short grid")


class TrainConfig(_Model):
    """The M&M-lite trainer; presets in ``gtgen.train.presets``, mirrored in ``configs/presets/``."""

    preset: str = Field("tiny", description="name of the preset the values came from")
    micro_size: int = Field(500, ge=8, description="micro grid cells the model predicts")
    short_size: int = Field(250, ge=8, description="short grid cells the model predicts")
    image_width: int = Field(160, ge=8, description="network image width [px]")
    image_height: int = Field(100, ge=8, description="network image height [px]")
    depth_min_m: float = Field(1.0, gt=0, description="first Lift-Splat depth bin [m]")
    depth_max_m: float = Field(110.0, gt=0, description="last Lift-Splat depth bin [m]")
    depth_step_m: float = Field(0.8, gt=0, description="Lift-Splat depth bin width [m]")
    image_channels: int = Field(80, ge=1, description="Lift-Splat BEV channels")
    pillar_channels: int = Field(256, ge=1, description="PointPillars BEV channels")
    max_points_per_pillar: int = Field(16, ge=1, description="PointPillars points per pillar (random ones in training, the first in the stored order in testing)")
    max_pillars_train: int = Field(32000, ge=1, description="PointPillars pillars per sample in training (random ones beyond)")
    max_pillars_test: int = Field(64000, ge=1, description="PointPillars pillars per sample in eval, prediction and export")
    decoder_channels: int = Field(128, ge=4, description="decoder base width")
    image_backbone: Literal["small_cnn", "efficientnet_b0"] = Field("small_cnn", description="image branch: a small CNN to 1/8 (CPU), or EfficientNet-B0 with an FPN over stages {5, 6, 8} to 1/8 (the paper)")
    fpn_channels: int = Field(128, ge=8, description="FPN width of the efficientnet_b0 image branch")
    backbone_weights: str | None = Field(None, description="local file of torchvision's efficientnet_b0 ImageNet state dict, loaded strictly (efficientnet_b0 only; nothing is downloaded)")
    bev_pool_chunk_mb: float = Field(256.0, gt=0, description="Lift-Splat pooling lifts this many MiB of features at a time (forward and backward) [MiB]")
    alpha: float = Field(0.2, ge=0, description="unobserved elevation weight")
    mu: float = Field(2.0, ge=0, description="risk loss weight")
    lam: float = Field(2.0, ge=0, description="elevation loss weight")
    gamma: float = Field(5.0, ge=0, description="consistency loss weight")
    elevation_clip_m: float = Field(25.0, gt=0, description="elevation clip, scaled to +-1 [m]")
    elevation_beta_m: float = Field(0.2, gt=0, description="Smooth-L1 transition of the elevation and consistency losses [m]; the default 1 scaled unit (25 m) leaves decimetre errors almost no gradient")
    prior_window_m: float = Field(4.0, ge=0, description="smoothing window of the min-z prior the heads correct (filled beyond the points) [m]")
    fatal_risk: float = Field(0.5, gt=0, lt=1, description="fatal-risk threshold for P/R/F1")
    risk_loss: Literal["mse", "weighted_mse", "weighted_bce"] = Field("weighted_bce", description="risk loss: the paper's MSE, or MSE / binary cross-entropy with the fatal cells weighted risk_fatal_weight times")
    risk_fatal_weight: float = Field(10.0, ge=1, description="weight of the fatal cells (label >= fatal_risk) in weighted_mse and weighted_bce")
    mirror_p: float = Field(0.5, ge=0, le=1, description="probability that a training sample is mirrored left-right (inputs and labels alike; 0: off)")
    lr: float = Field(5e-4, gt=0, description="peak learning rate (OneCycle)")
    steps: int = Field(16000, ge=1, description="optimizer steps")
    batch_size: int = Field(4, ge=1, description="samples per optimizer step, over all processes under torchrun (a multiple of their number)")
    workers: int = Field(0, ge=0, description="DataLoader workers (per process)")
    ckpt_every: int = Field(500, ge=1, description="checkpoint every n steps")
    val_every: int = Field(250, ge=0, description="validate on the val split every n steps and at the end, keeping best.pt (0: never)")
    val_max_samples: int | None = Field(None, ge=1, description="validate on at most this many val samples, evenly spread (null: all)")
    seed: int = Field(0, ge=0, description="random seed")
    device: str = Field("auto", description="torch device: auto (cuda when present, else cpu), cpu, cuda, cuda:N; under torchrun each process takes cuda:LOCAL_RANK")
    precision: Literal["auto", "32", "bf16-mixed", "16-mixed"] = Field("auto", description="float precision: auto (bf16-mixed on a CUDA device that has bf16, 16-mixed on other CUDA devices, 32 on cpu), 32, bf16-mixed, or 16-mixed (with a gradient scaler)")
    check_memory: bool = Field(True, description="stop before the first step when the preset's estimated memory need at batch_size exceeds what the device has free (gtgen/train/memory.py); false: try anyway")
    sync_batchnorm: bool = Field(True, description="under torchrun on CUDA, batch norms take their statistics over the global batch (SyncBatchNorm); gloo on cpu keeps each process's own")
    cameras: bool = Field(True, description="the cameras' Lift-Splat BEV features are an input (off: no images are loaded)")
    points: bool = Field(True, description="PointPillars features of the point input (train.geometry) are an input (off: no points are loaded)")
    raw_elevation: bool = Field(True, description="the raw min-z channel and the filled prior are inputs and the elevation heads correct the prior (off: the heads predict the elevation directly)")
    ranges: Literal["both", "micro", "short"] = Field("both", description="the ranges one network predicts: both (the micro maps from the centre of the short BEV features), or one range alone with BEV features over that range only (micro: +-micro length / 2 at the short grid's cell size)")
    geometry: Literal["voxel_map", "scans"] = Field("voxel_map", description="the point input: the stack's voxel map at t, or the last n_scans raw lidar scans (Tab. III)")
    n_scans: int = Field(10, ge=1, description="raw scans of the N-scan input (train.geometry: scans), at least 2 m of travel apart")
    scan_voxel_m: float = Field(0.4, gt=0, description="voxel filter edge of the accumulated scans (train.geometry: scans) [m]")

    @model_validator(mode="after")
    def _some_input(self) -> TrainConfig:
        if not (self.cameras or self.points or self.raw_elevation):
            raise ValueError("train.cameras, points and raw_elevation are all off: the model needs at least one input")
        return self

    @property
    def predicted_ranges(self) -> tuple[str, ...]:
        """The ranges the model predicts, in ``RANGES`` order."""
        return RANGES if self.ranges == "both" else (self.ranges,)


class MappingConfig(_Model):
    """Grid maps from raw lidar (``gtgen.mapping``): what a range's map is where no stack publishes one
    (``topics.map_<range>: null``). Maps are made at the front camera's stamps that extract keeps
    (``extract.map_rate_hz`` and each sample's map at t). Cells hold the points of the last
    ``memory_s``; the layers follow the stack's semantics, so fuse reads them as X-Racer's."""

    memory_s: float = Field(10.0, gt=0, le=MAX_SPAN_S, description="a cell forgets points older than this [s] (odometry drifts)")
    ground_band_m: float = Field(0.15, gt=0, description="a cell's ground is the mean of its points within this of its lowest point [m]: vegetation and overhangs above stay out")
    min_points: int = Field(2, ge=1, description="ground points a cell needs before it has an elevation")
    overhang_m: float = Field(2.5, gt=0, description="points higher than this above a cell's ground are overhangs (branches the vehicle passes under): not obstacles [m]")
    max_height_m: float | None = Field(None, description="points higher than this above the base (odom z) at their sweep are left out of the maps and the voxel map: ceilings, bridges, crowns seen where no ground is, which the lowest points of a cell would read as ground indoors [m]; null keeps every point (off-road: hills ahead rise above the base)")
    body_x_m: tuple[float, float] = Field((-2.5, 2.5), description="the vehicle's own body along base x, masked out of every sweep [m]")
    body_y_m: tuple[float, float] = Field((-1.2, 1.2), description="the vehicle's body along base y [m]")
    body_z_m: tuple[float, float] = Field((-0.5, 2.5), description="the vehicle's body along base z [m]")
    full_points: float = Field(4.0, gt=0, description="confidence from density is 1 - exp(-n / this) for n ground points")
    range_half_m: float = Field(30.0, gt=0, description="confidence halves every this much range from the sensor at the closest view [m]")
    age_half_s: float = Field(5.0, gt=0, description="confidence halves every this much age of a cell's latest point [s]")
    clearance_m: float = Field(0.3, gt=0, description="ground clearance: stuff standing this high above the ground is an obstacle (risk 0.5 = fatal) [m]")
    max_step_m: float = Field(0.3, gt=0, description="a ground step this high within neighbourhood_m is fatal [m]")
    max_slope_deg: float = Field(30.0, gt=0, lt=90, description="a ground slope this steep is fatal [deg]")
    max_roughness_m: float = Field(0.2, gt=0, description="ground roughness (std in neighbourhood_m) this large is fatal [m]")
    neighbourhood_m: float = Field(0.6, gt=0, description="edge of the neighbourhood of step and roughness [m]")
    ground_window_m: float = Field(2.0, gt=0, description="edge of the window of the local ground [m]: what stands on the ground narrower than this (a rock, a trunk) is taken off it and judged by its own height, wider relief is terrain judged by step, slope and roughness, so a rock's neighbours are not fatal; about the vehicle's track, the width its wheels straddle")
    cover_cell_m: float | None = Field(0.2, gt=0, description="a cell coarser than this is as high as what covers half of it: its points' tops are kept per sub-cell of about this edge, and its height is the top that half of its seen sub-cells reach, so a 0.8 m cell whose corner a crown or a rock's side crosses is not an obstacle, one the obstacle covers is [m]; null: the cell's highest point")
    voxel_m: float = Field(0.4, gt=0, description="voxel edge of the voxel map made from lidar (topics.voxel_map: null) [m]; it holds the voxels seen in the last memory_s within the short grid")

    def sub_cells(self, res: float) -> int:
        """Return the sub-cells a side (1: none) of a cell of edge ``res`` [m] judged by its
        cover at sub-cells of about ``cover_cell_m`` (None: by its highest point)."""
        return 1 if self.cover_cell_m is None else max(1, int(round(res / self.cover_cell_m)))

    @model_validator(mode="after")
    def _body_box(self) -> MappingConfig:
        for k in ("body_x_m", "body_y_m", "body_z_m"):
            lo, hi = getattr(self, k)
            if not lo < hi:
                raise ValueError(f"mapping.{k} = ({lo}, {hi}): expected (low, high) with low < high")
        return self
