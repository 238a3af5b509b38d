"""The settings every stage shares: ranges, cameras and lidars, the grids and the topics a
drive's roles are read from; ``_Model``, the base of every settings model (unknown keys,
inf and NaN refused)."""

from __future__ import annotations

import re

from pydantic import BaseModel, ConfigDict, Field, model_validator

from gtgen.errors import ConfigError

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
