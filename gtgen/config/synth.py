"""The simulated drive's settings (``gtgen synth``): every realism knob, and the easy world's values."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, model_validator

from gtgen.config.base import MAX_SPAN_S, _Model


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
