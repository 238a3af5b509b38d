"""Validated configuration: one pydantic model per stage, nested in :class:`GtgenConfig`.

No file at all gives working defaults; a YAML file is a partial override of them
(``--config FILE``). ``configs/default.yaml`` lists every key with its unit and a
test keeps it equal to these defaults.
"""

from __future__ import annotations

import difflib
import re
from pathlib import Path
from typing import Any, Literal, get_args

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from gtgen.errors import ConfigError, InputNotFoundError

RANGES = ("micro", "short")
CAMERAS = ("front", "left", "right", "back")  # X-Racer's rig (the default topics.cameras) and the synthetic drive's
MAX_CAMERAS = 8
LIDAR_REFERENCE = "lidar"  # extract.reference: sample times snap to the first lidar's scans
LIDARS = ("front", "front_tilted", "back")  # the synthetic drive's lidars (the paper's three VLP-32C)
LIDAR_TOPICS = tuple(f"/lidar/{n}/points" for n in LIDARS)
MAX_SPAN_S = 86_400.0  # longest time span a setting takes [s]: a day; stamps are int64 ns, and a window beyond any drive means nothing


class _Model(BaseModel):
    # a setting is a number a drive can have: inf or nan in a window or threshold reads as
    # "everything" or "nothing" silently, or overflows when converted to nanoseconds
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class GridSpec(_Model):
    """A square vehicle-centric grid: ``size`` x ``size`` cells of ``resolution_m``."""

    size: int = Field(gt=0, le=8192, description="cells per side")
    resolution_m: float = Field(gt=0, description="cell edge length [m]")

    @property
    def length_m(self) -> float:
        """Edge length of the grid [m]."""
        return self.size * self.resolution_m


class GridsConfig(_Model):
    """The two target grids of the paper (Sec. III-A)."""

    micro: GridSpec = Field(default_factory=lambda: GridSpec(size=500, resolution_m=0.2))
    short: GridSpec = Field(default_factory=lambda: GridSpec(size=250, resolution_m=0.8))

    def get(self, rng: str) -> GridSpec:
        """Return the grid of range ``rng`` ('micro' or 'short')."""
        if rng not in RANGES:
            raise ConfigError(f"range {rng!r} unknown; expected one of {list(RANGES)}")
        return getattr(self, rng)


class LayersConfig(_Model):
    """GridMap layer names of the three X-Racer layers."""

    elevation: str = Field("elevation", description="elevation layer [m, in the map frame]")
    risk: str = Field("risk", description="traversability risk layer [0 safe .. 1 fatal]")
    confidence: str = Field("confidence", description="confidence layer [0 .. 1]")


class CameraTopics(_Model):
    """One camera's topics (both are needed: the images and their calibration)."""

    image: str = Field(description="sensor_msgs/CompressedImage or Image topic")
    info: str = Field(description="sensor_msgs/CameraInfo topic")


def _default_cameras() -> dict[str, CameraTopics]:
    return {
        c: CameraTopics(image=f"/cam_{c}/image/compressed", info=f"/cam_{c}/camera_info")
        for c in CAMERAS
    }


class TopicsConfig(_Model):
    """Topic -> role mapping; ``configs/xracer.yaml`` is the default."""

    map_micro: str | None = Field("/xracer/map/micro", description="grid_map_msgs/GridMap, micro range; null: made from the raw lidar scans (topics.lidar) by gtgen.mapping")
    map_short: str | None = Field("/xracer/map/short", description="grid_map_msgs/GridMap, short range; null: made from the raw lidar scans (topics.lidar)")
    odometry: str | None = Field("/xracer/odometry", description="nav_msgs/Odometry odom -> base; null: poses from TF odom_frame -> base_frame")
    tf: str = Field("/tf", description="tf2_msgs/TFMessage (or tf/tfMessage): moving frames")
    tf_static: str = Field("/tf_static", description="tf2_msgs/TFMessage, latched extrinsics")
    gnss: str | None = Field("/gnss/fix", description="sensor_msgs/NavSatFix (optional: a topic the bags do not hold is skipped); null: no GNSS, so no DEM placement (gtgen dem-align --no-dem)")
    cameras: dict[str, CameraTopics] = Field(default_factory=_default_cameras, description="0 to 8 cameras by a name of your choosing (letters, digits, _ and -): {name: {image, info}}, in the order the stores keep them; a config file's mapping replaces the default one whole ({} for none)")
    voxel_map: str | None = Field("/xracer/voxel_map", description="sensor_msgs/PointCloud2; null: made from the raw lidar scans (topics.lidar)")
    lidar: list[str] = Field(default_factory=lambda: list(LIDAR_TOPICS), description="sensor_msgs/PointCloud2 raw scans, one topic per lidar in any frame TF connects to odom (optional: topics not in the bags are skipped; the N-scan input of Tab. III)")
    odom_frame: str = Field("odom", description="frame the drive is stored in (maps, voxel maps and poses are put in it through TF)")
    base_frame: str = Field("base_link", description="vehicle base frame")
    layers: LayersConfig = Field(default_factory=LayersConfig)

    def map_topic(self, rng: str) -> str | None:
        """Return the GridMap topic of range ``rng`` (None: the map is made from lidar)."""
        return self.map_micro if rng == "micro" else self.map_short

    def from_lidar(self) -> list[str]:
        """Return what gtgen.mapping makes from the raw scans: the ranges whose map topic is
        null, and 'voxel_map' if its topic is."""
        return [r for r in ("micro", "short") if self.map_topic(r) is None] + (["voxel_map"] if self.voxel_map is None else [])

    def roles(self) -> dict[str, str]:
        """Return {config key: topic} of every topic-valued key (tf topics excluded)."""
        out = {k: t for k, t in (("map_micro", self.map_micro), ("map_short", self.map_short), ("gnss", self.gnss),
                                 ("voxel_map", self.voxel_map)) if t is not None}
        out.update({f"lidar[{i}]": t for i, t in enumerate(self.lidar)})
        if self.odometry is not None:
            out["odometry"] = self.odometry
        for c, ct in self.cameras.items():
            out[f"cameras.{c}.image"] = ct.image
            out[f"cameras.{c}.info"] = ct.info
        return out

    @property
    def camera_names(self) -> list[str]:
        """The configured cameras' names, in the order the stores keep their images."""
        return list(self.cameras)

    @model_validator(mode="after")
    def _cameras_one_role_each(self) -> TopicsConfig:
        if len(self.cameras) > MAX_CAMERAS:
            raise ValueError(f"topics.cameras names {len(self.cameras)} cameras ({', '.join(self.cameras)}); expected at most {MAX_CAMERAS}")
        for name in self.cameras:
            if not re.fullmatch(r"[A-Za-z0-9_-]{1,32}", name) or name == LIDAR_REFERENCE:
                raise ValueError(f"camera name {name!r}: expected 1 to 32 letters, digits, '_' or '-', and not {LIDAR_REFERENCE!r} "
                                 "(extract.reference's name for the lidar)")
        keys: dict[str, list[str]] = {}
        for key, topic in {**self.roles(), "tf": self.tf, "tf_static": self.tf_static}.items():
            keys.setdefault(topic, []).append(key)
        twice = {t: k for t, k in keys.items() if len(k) > 1}
        if twice:
            t, k = next(iter(twice.items()))
            raise ValueError(f"topic {t!r} is given for {' and '.join(f'topics.{x}' for x in k)}; each topic plays one role")
        names = [self.layers.elevation, self.layers.risk, self.layers.confidence]
        if len(set(names)) < 3:
            raise ValueError(f"topics.layers names {names} must be three different GridMap layers")
        return self


class SynthConfig(_Model):
    """The simulated drive (``gtgen synth``); every realism knob is here."""

    world: Literal["paper", "easy"] = Field("paper", description="paper: the stack's maps confident where its lidar returns are dense (falling with range, shadowed behind crests and obstacles, thinner at speed), hillier, with more rocks, bushes and trees of several heights; easy: the old smooth world (confidence halving with range wherever a beam reaches, few rocks and trees), whose values it gives every key of EASY_WORLD a config layer does not set")
    seed: int = Field(0, ge=0, description="random seed; same seed, same bytes")
    duration_s: float = Field(60.0, gt=0, le=3600, description="drive duration [s]")
    formats: Literal["mcap", "bag", "both"] = Field("both", description="bag flavours written")
    crs: str = Field("EPSG:26910", description="projected CRS of the terrain and DEM")
    origin_e_m: float = Field(708000.0, description="UTM easting of the drive start [m]")
    origin_n_m: float = Field(3944000.0, description="UTM northing of the drive start [m]")
    speed_min_mps: float = Field(5.0, gt=0, description="minimum vehicle speed [m/s]")
    speed_max_mps: float = Field(12.0, gt=0, description="maximum vehicle speed [m/s]")
    map_rate_hz: float = Field(10.0, gt=0, description="X-Racer map rate per range [Hz]")
    odom_rate_hz: float = Field(50.0, gt=0, description="odometry rate [Hz]")
    gnss_rate_hz: float = Field(10.0, gt=0, description="GNSS fix rate [Hz]")
    camera_rate_hz: float = Field(5.0, gt=0, description="camera frame rate, all four [Hz]")
    voxel_rate_hz: float = Field(2.0, gt=0, description="voxel map rate [Hz]")
    image_width: int = Field(640, ge=16, le=4096, description="width of the frames the cameras publish (JPEG) [px]")
    image_height: int = Field(396, ge=16, le=4096, description="height of the frames the cameras publish (JPEG) [px]")
    render_width: int = Field(160, ge=16, le=4096, description="width of the ray-marched render, upsampled (bilinear) to image_width: the cost of rendering grows with it [px]")
    render_height: int = Field(100, ge=16, le=4096, description="height of the ray-marched render, upsampled to image_height [px]")
    distorted_camera: Literal["front", "left", "right", "back"] | None = Field("left", description="the camera rendered through a plumb_bob lens (its CameraInfo says so), so that extract's rectification is exercised; null: all pinhole")
    distortion: list[float] = Field([-0.25, 0.06, 0.0008, -0.0005, 0.0], min_length=5, max_length=5, description="plumb_bob coefficients k1, k2, p1, p2, k3 of distorted_camera")
    camera_hfov_deg: float = Field(100.0, gt=10, lt=170, description="horizontal field of view [deg]")
    lidar_height_m: float = Field(2.0, gt=0, description="lidar height above the base [m]")
    lidar_range_m: float = Field(90.0, gt=1, description="maximum lidar range [m]")
    confidence_range_m: float = Field(28.0, gt=0, description="range where confidence halves [m]")
    confidence_model: Literal["density", "range"] = Field("density", description="density: a map cell is seen when lidar returns land in it (expected returns from the beams' angular spacing over the visible surface, Poisson drawn), and its confidence grows with them and halves every confidence_range_m; range: every cell a beam reaches is seen, confidence halving with range, at least 0.12")
    lidar_beams: int = Field(2, ge=1, le=1024, description="beams, evenly over lidar_vfov_deg, whose returns count for the stack's confidence (fewer than the sensors have: the paper's vehicle carries three 32-beam VLP-32C; the default puts the demo's region shares near the paper's Tab. I) (density model)")
    lidar_vfov_deg: float = Field(40.0, gt=0, le=180, description="vertical field of view the beams span, from -25 deg up [deg] (density model)")
    lidar_az_points: int = Field(1800, ge=8, le=100000, description="returns per beam per revolution (density model)")
    lidar_rate_hz: float = Field(10.0, gt=0, description="lidar revolutions per second (density model)")
    stack_memory_s: float = Field(6.0, gt=0, le=MAX_SPAN_S, description="the stack's maps hold the returns of the last this many seconds, of at most stack_memory_m of travel [s] (density model)")
    stack_memory_m: float = Field(45.0, gt=0, description="travel the stack's maps hold the returns of, at most: at speed they hold fewer revolutions and are thinner [m] (density model)")
    stack_memory_views: int = Field(3, ge=1, le=16, description="lidar poses the stack's memory is drawn from, the current one included, evenly over its span (density model)")
    stack_voxel_m: float = Field(0.4, ge=0, description="the stack counts a map cell's returns over at least this column edge (its voxels) [m] (density model)")
    stack_points_conf: float = Field(1.0, gt=0, description="returns in a cell that make it 63 % confident before the range factor (density model)")
    stack_drift_xy_m: float = Field(0.1, ge=0, description="std of the horizontal misregistration of a published map: the odometry's drift over the stack's memory (stack_memory_s), which places the older returns of its voxel map off from the newer; a random walk, so consecutive maps share most of it [m] (0: none)")
    stack_drift_z_m: float = Field(0.05, ge=0, description="std of the vertical misregistration of a published map from the odometry's z drift over the stack's memory (as stack_drift_xy_m) [m]")
    stack_drift_tilt_deg: float = Field(0.05, ge=0, description="std of the roll and pitch misregistration of a published map from the attitude drift over the stack's memory: its error grows linearly with range [deg]")
    stack_jitter_xy_m: float = Field(0.15, ge=0, description="std of the horizontal registration jitter of each published map on its own (pose interpolation at the map's stamp, timing) [m]")
    stack_jitter_z_m: float = Field(0.15, ge=0, description="std of the vertical registration jitter of each published map [m]")
    stack_jitter_tilt_deg: float = Field(0.2, ge=0, description="std of the roll and pitch jitter of each published map (IMU attitude noise) [deg]")
    stack_smoothing_m: float = Field(0.5, ge=0, description="std of the footprint the stack's elevation averages over at 50 m range, growing linearly from 0 at the sensor: sparse returns at range are binned over wide voxels, so rocks and ditches blur there (a blend of the cell and its neighbourhood blurred by this, weighted range / 50 m, at most 2) [m] (density model)")
    stack_fill_micro_m: float = Field(3.0, ge=0, description="the stack extrapolates its micro map into unseen cells up to this far from a seen one, along the local slope of what it saw [m] (density model; 0: no fill)")
    stack_fill_short_m: float = Field(32.0, ge=0, description="as stack_fill_micro_m for the short map [m] (density model)")
    stack_fill_slope_sd: float = Field(0.12, ge=0, description="std of the error of the slope a map extrapolates along (one per map: the stack's plane fit to sparse returns), so a guess errs more the farther it is from what was seen [m/m] (density model)")
    stack_fill_confidence: float = Field(0.05, ge=0, lt=0.1, description="confidence of an extrapolated cell next to a seen one, falling linearly to 0 at the fill distance: below fuse.min_conf's default (0.1), a guess never makes a label (density model)")
    voxel_map_memory: Literal["stack", "two_sweeps"] = Field("stack", description="stack: the voxel map holds the returns of the stack's memory (the current lidar pose and the earlier ones of stack_memory_s, as its maps do); two_sweeps: the last two sweeps published (the easy world's)")
    elevation_noise_m: float = Field(0.04, ge=0, description="elevation noise at 0 m range [m]")
    elevation_noise_per_m: float = Field(0.006, ge=0, description="elevation noise growth with range [m/m]: a cell seen by few returns at range gets them at grazing angles, off grass tops and edges (divided by the square root of the returns with the density model)")
    drift_xy_per_m: float = Field(0.003, ge=0, description="odometry xy drift per metre driven")
    drift_yaw_deg_per_100m: float = Field(0.2, ge=0, description="odometry heading drift")
    drift_z_m_per_s: float = Field(0.004, ge=0, description="odometry z drift rate [m/s]")
    gnss_bias_m: float = Field(1.5, ge=0, description="std of the slowly varying GNSS bias [m]")
    gnss_bias_tau_s: float = Field(120.0, gt=0, le=MAX_SPAN_S, description="correlation time of the bias [s]")
    gnss_noise_m: float = Field(0.3, ge=0, description="white GNSS noise std per axis [m]")
    geoid_offset_m: float = Field(-33.0, description="NAVD88 -> ellipsoid height offset [m]")
    dem_tile_m: int = Field(400, ge=50, description="DEM tile edge [m]")
    dem_margin_m: float = Field(150.0, ge=0, description="DEM coverage beyond the path [m]")
    dem_noise_m: float = Field(0.03, ge=0, description="DEM height noise [m]")
    hill_amplitude_m: float = Field(8.0, ge=0, description="rolling hill amplitude [m]")
    crest_amplitude_m: float = Field(0.5, ge=0, description="amplitude of short hills and crests (30-80 m wavelength) on top of the rolling hills [m]")
    valley_depth_m: float = Field(8.0, ge=0, description="valley depth [m]")
    ditch_depth_m: float = Field(0.35, ge=0, description="ditch / rut depth [m]")
    trees_per_ha: float = Field(6.0, ge=0, description="tree density [1/ha]")
    tree_height_min_m: float = Field(3.0, gt=0, description="lowest tree [m]")
    tree_height_max_m: float = Field(15.0, gt=0, description="tallest tree [m]")
    rocks_per_ha: float = Field(20.0, ge=0, description="rock density [1/ha]")
    canopy: bool = Field(False, description="X-Racer maps show the top of tree crowns and bushes where the lidar hits them (the DEM stays bare earth)")
    bushes_per_ha: float = Field(15.0, ge=0, description="bush density (1-2.5 m radius) [1/ha]")
    bush_height_min_m: float = Field(0.4, gt=0, description="lowest bush [m]")
    bush_height_max_m: float = Field(2.5, gt=0, description="tallest bush [m]")
    gnss_jumps: int = Field(0, ge=0, description="GNSS multipath events: the fixes jump by gnss_jump_m for gnss_jump_s")
    gnss_jump_m: float = Field(4.0, ge=0, description="size of a GNSS multipath jump [m]")
    gnss_jump_s: float = Field(5.0, gt=0, le=MAX_SPAN_S, description="duration of a GNSS multipath jump [s]")
    gnss_outages: int = Field(0, ge=0, description="GNSS outages: no fix for gnss_outage_s")
    gnss_outage_s: float = Field(20.0, gt=0, le=MAX_SPAN_S, description="duration of a GNSS outage [s]")
    terrain_changes: int = Field(0, ge=0, description="patches on the path where the terrain changed since the DEM survey (a cut, a berm)")
    terrain_change_m: float = Field(1.5, description="height of a terrain change, + berm / - cut [m]")
    terrain_change_radius_m: float = Field(12.0, gt=0, description="radius of a terrain change [m]")
    dem_shifted_tile_m: float = Field(0.0, ge=0, description="one DEM tile under the drive is georeferenced this far off to the east [m] (0 = none)")
    dem_wrong_tile: bool = Field(False, description="one DEM tile under the drive holds the terrain of a neighbouring area (1 km north)")
    scan_rate_hz: float = Field(10.0, ge=0, description="raw scans published per lidar (three spinning 32-beam lidars: front, front tilted down, back) [Hz]; 0: none")
    scan_beams: int = Field(32, ge=1, le=32, description="beams cast of the VLP-32C's 32 (evenly thinned, the lowest and highest kept)")
    scan_azimuth_deg: float = Field(1.0, gt=0, le=10, description="azimuth step of a scan's columns [deg]; a VLP-32C at 10 Hz has 0.2, 5 times the columns, rays and bag bytes")
    scan_range_m: float = Field(100.0, gt=1, description="maximum range of a raw scan [m]")
    scan_noise_m: float = Field(0.03, ge=0, description="range noise std of a raw scan return [m]")
    scan_dropout: float = Field(0.05, ge=0, lt=1, description="share of a raw scan's returns dropped at random")
    workers: int = Field(2, ge=1, le=64, description="processes simulating in parallel (output does not depend on it)")
    circular_buffer_every: int = Field(3, ge=0, description="every n-th map has non-zero start indices (0 = never)")

    @model_validator(mode="before")
    @classmethod
    def _world(cls, data: Any) -> Any:
        """``world: easy`` given with only some keys: the easy world's values for the rest."""
        if isinstance(data, dict) and data.get("world") == "easy":
            data = {**EASY_WORLD, **data}
        return data

    @model_validator(mode="after")
    def _speeds(self) -> SynthConfig:
        if self.speed_max_mps < self.speed_min_mps:
            raise ValueError(
                f"speed_max_mps={self.speed_max_mps} is below speed_min_mps={self.speed_min_mps}"
            )
        for name in ("tree", "bush"):
            lo, hi = getattr(self, f"{name}_height_min_m"), getattr(self, f"{name}_height_max_m")
            if hi < lo:
                raise ValueError(f"{name}_height_max_m={hi} is below {name}_height_min_m={lo}")
        return self


# The easy world (gtgen before issue 29): what ``synth.world: easy`` sets where a config
# layer does not. Its drives are the ones the paper world's defaults replaced.
EASY_WORLD: dict[str, Any] = {
    "confidence_model": "range", "confidence_range_m": 35.0, "hill_amplitude_m": 6.0, "crest_amplitude_m": 0.0,
    "trees_per_ha": 2.0, "tree_height_min_m": 5.0, "tree_height_max_m": 12.0, "rocks_per_ha": 6.0,
    "bushes_per_ha": 0.0, "bush_height_min_m": 0.5, "bush_height_max_m": 1.5,
    "stack_drift_xy_m": 0.0, "stack_drift_z_m": 0.0, "stack_drift_tilt_deg": 0.0, "stack_jitter_xy_m": 0.0, "stack_jitter_z_m": 0.0,
    "stack_jitter_tilt_deg": 0.0, "voxel_map_memory": "two_sweeps", "elevation_noise_per_m": 0.002,
}


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

    @model_validator(mode="after")
    def _body_box(self) -> MappingConfig:
        for k in ("body_x_m", "body_y_m", "body_z_m"):
            lo, hi = getattr(self, k)
            if not lo < hi:
                raise ValueError(f"mapping.{k} = ({lo}, {hi}): expected (low, high) with low < high")
        return self


class GtgenConfig(_Model):
    """Root configuration; every stage reads its own part."""

    grids: GridsConfig = Field(default_factory=GridsConfig)
    topics: TopicsConfig = Field(default_factory=TopicsConfig)
    synth: SynthConfig = Field(default_factory=SynthConfig)
    extract: ExtractConfig = Field(default_factory=ExtractConfig)
    fuse: FuseConfig = Field(default_factory=FuseConfig)
    dem: DemConfig = Field(default_factory=DemConfig)
    shards: ShardsConfig = Field(default_factory=ShardsConfig)
    report: ReportConfig = Field(default_factory=ReportConfig)
    train: TrainConfig = Field(default_factory=TrainConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)

    @model_validator(mode="after")
    def _reference_is_a_sensor(self) -> GtgenConfig:
        ref = self.extract.reference
        if ref is not None and ref != LIDAR_REFERENCE and ref not in self.topics.cameras:
            raise ValueError(f"extract.reference = {ref!r} names no configured sensor; expected one of "
                             f"{[*self.topics.cameras, LIDAR_REFERENCE]} (a camera of topics.cameras, or the lidar)")
        if ref == LIDAR_REFERENCE and not self.topics.lidar:
            raise ValueError("extract.reference = 'lidar', but topics.lidar lists no lidar topic")
        return self

    @property
    def reference(self) -> str:
        """The sensor sample times snap to: ``extract.reference``, else the first camera, else 'lidar'."""
        if self.extract.reference is not None:
            return self.extract.reference
        return next(iter(self.topics.cameras), LIDAR_REFERENCE)


def configs_dir() -> Path:
    """Return the project's ``configs/`` folder (YAML only)."""
    return Path(__file__).resolve().parent.parent / "configs"


# mappings a config layer gives whole: a robot's cameras replace the default rig, they do
# not join it (a layer that names two cameras means two)
WHOLE = {("topics", "cameras")}


def _deep_merge(base: dict[str, Any], over: dict[str, Any], at: tuple[str, ...] = ()) -> dict[str, Any]:
    out = dict(base)
    for key, val in over.items():
        if isinstance(val, dict) and isinstance(out.get(key), dict) and (*at, key) not in WHOLE:
            out[key] = _deep_merge(out[key], val, (*at, key))
        else:
            out[key] = val
    return out


def _world_layer(layer: dict[str, Any]) -> dict[str, Any]:
    """Return ``layer`` with the keys its ``synth.world`` implies where it does not set them
    (the easy world's values, or the paper world's defaults), so a later layer's world
    replaces an earlier one's."""
    synth = layer.get("synth")
    if not isinstance(synth, dict) or synth.get("world") not in ("easy", "paper"):
        return layer
    base = EASY_WORLD if synth["world"] == "easy" else {k: SynthConfig.model_fields[k].default for k in EASY_WORLD}
    return {**layer, "synth": {**base, **synth}}


def _format_validation(err: ValidationError) -> str:
    errors = err.errors()
    # a misspelt key is also a missing one (topics.cameras.front: 'imag' and no 'image'):
    # the unknown key is the one to name, with its nearest valid spelling
    first = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
    parts = tuple(str(p) for p in first["loc"])
    loc = ".".join(parts) or "<root>"
    more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    if first["type"] == "extra_forbidden":
        return f"config key '{loc}' is not a gtgen setting; {_nearest_key(parts)}{more}"
    if first["type"] == "value_error":  # a validator's own message names the keys and values
        msg = first["msg"].removeprefix("Value error, ")
        return f"config: {msg}{more}" if loc == "<root>" else f"config key '{loc}': {msg}{more}"
    val = first.get("input")
    shown = "" if isinstance(val, dict) else f" = {val!r}"
    return f"config key '{loc}'{shown}: {first['msg']}{more}"


def _nearest_key(parts: tuple[str, ...]) -> str:
    """Return 'did you mean ...?' with the valid key nearest the unknown ``parts``, or the
    keys its section takes."""
    model: type[BaseModel] = GtgenConfig
    path: list[str] = []
    rest = list(parts[:-1])
    while rest:
        name = rest.pop(0)
        ann = model.model_fields[name].annotation
        path.append(name)
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            model = ann
        else:  # a mapping of models (topics.cameras): the next part is its key
            model = get_args(ann)[-1]
            path.append(rest.pop(0))
    prefix = "".join(f"{p}." for p in path)
    keys = list(model.model_fields)
    near = difflib.get_close_matches(parts[-1], keys, n=1, cutoff=0.6)
    if near:
        return f"did you mean '{prefix}{near[0]}'?"
    return f"{prefix.rstrip('.') or 'the top level'} takes: {', '.join(keys)}"


def read_yaml(path: Path, what: str = "config file") -> dict[str, Any]:
    """Return the mapping in YAML file ``path`` (``what`` names the file in errors)."""
    if not path.exists():
        raise InputNotFoundError(f"{what} '{path}' does not exist")
    if not path.is_file():
        raise ConfigError(f"{what} '{path}' is a folder; expected a YAML file")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except UnicodeDecodeError as err:
        raise ConfigError(f"{what} '{path}' is not a text file: byte {err.start} is not UTF-8") from err
    except yaml.YAMLError as err:
        raise ConfigError(f"{what} '{path}' is not valid YAML: {_yaml_problem(err)}") from err
    if not isinstance(data, dict):
        raise ConfigError(f"{what} '{path}' must hold a mapping of keys to values, got a {type(data).__name__}")
    return data


def _yaml_problem(err: yaml.YAMLError) -> str:
    problem = getattr(err, "problem", None) or str(err).splitlines()[0]
    mark = getattr(err, "problem_mark", None)
    return problem + (f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "")


def check_value(key: str, value: Any) -> Any:
    """Return ``value`` as config key ``key`` ('section.name') takes it; raise ConfigError
    saying what the key takes (a command-line option is held to its key's bounds)."""
    section, name = key.split(".")
    model = getattr(GtgenConfig(), section)
    try:
        setattr(model, name, value)
    except ValidationError as err:
        first = err.errors()[0]
        raise ConfigError(f"{value!r} is not a valid {key}: {first['msg']}") from err
    return getattr(model, name)


def build_config(*layers: dict[str, Any]) -> GtgenConfig:
    """Return the defaults overridden by each partial mapping in ``layers``, in order."""
    merged: dict[str, Any] = GtgenConfig().model_dump(mode="json")
    for layer in layers:
        merged = _deep_merge(merged, _world_layer(layer))
    try:
        return GtgenConfig.model_validate(merged)
    except ValidationError as err:
        raise ConfigError(_format_validation(err)) from err


def stored_config(data: dict[str, Any], source: str, sections: tuple[str, ...] = ()) -> GtgenConfig:
    """Return the resolved config a store or checkpoint recorded (``source`` names it in
    the error): its ``sections`` (all but ``train`` when empty), the others at their
    defaults. The ``train`` section is always left out: how the maker of a dataset would
    train says nothing about the data, and trainer keys change between versions, so a
    dataset stays readable by a gtgen whose trainer has other keys; so are the sections of
    stages after a store's. Raises ConfigError, one line, for any key of those sections
    this gtgen does not accept."""
    try:
        return GtgenConfig.model_validate({k: v for k, v in data.items() if k != "train" and (not sections or k in sections)})
    except ValidationError as err:
        raise ConfigError(f"{source} records a config this gtgen does not accept ({_format_validation(err)}); "
                          "rebuild it with this version") from err


def load_config(path: Path | None = None, *overrides: dict[str, Any]) -> GtgenConfig:
    """Return the defaults, overridden by YAML file ``path`` and then by ``overrides``."""
    layers = [read_yaml(path)] if path is not None else []
    return build_config(*layers, *overrides)


def save_config(cfg: GtgenConfig, path: Path, overwrite: bool = False) -> None:
    """Write the resolved ``cfg`` as YAML to ``path`` (atomically; the signature in its first
    line; a file there that gtgen did not write only with ``overwrite``)."""
    from gtgen.runtime.output import signature, write_atomic

    write_atomic(path, f"# {signature()}: the resolved config\n" + yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False), overwrite)


def default_yaml() -> str:
    """Return the defaults as YAML with each field's description (and unit) as a comment."""
    lines = ["# gtgen defaults: every key, its unit and meaning. A --config file overrides any subset.", ""]

    def walk(model: type[BaseModel], value: BaseModel, indent: int) -> None:
        pad = "  " * indent
        for name, field in model.model_fields.items():
            v = getattr(value, name)
            desc = field.description or ""
            if isinstance(v, BaseModel):
                lines.append(f"{pad}{name}:" + (f"  # {desc}" if desc else ""))
                walk(type(v), v, indent + 1)
            elif isinstance(v, dict) and v and isinstance(next(iter(v.values())), BaseModel):
                lines.append(f"{pad}{name}:" + (f"  # {desc}" if desc else ""))
                for k, sub in v.items():
                    lines.append(f"{pad}  {k}:")
                    walk(type(sub), sub, indent + 2)
            else:
                dumped = yaml.safe_dump({name: v}, default_flow_style=True, width=1000).strip()[1:-1]
                lines.append(f"{pad}{dumped}" + (f"  # {desc}" if desc else ""))

    cfg = GtgenConfig()
    for name in GtgenConfig.model_fields:
        sub = getattr(cfg, name)
        lines.append(f"{name}:  # {(type(sub).__doc__ or '').strip().splitlines()[0]}")
        walk(type(sub), sub, 1)
        lines.append("")
    return "\n".join(lines)
