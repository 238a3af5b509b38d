"""Which topic plays which role: the config's mapping checked against the bags' topics."""

from __future__ import annotations

from gtgen.bag.reader import TopicInfo
from gtgen.config import CAMERAS, RANGES, GtgenConfig
from gtgen.errors import TopicError

TYPES = {
    "odometry": ("nav_msgs/msg/Odometry",),
    "gnss": ("sensor_msgs/msg/NavSatFix",),
    "voxel_map": ("sensor_msgs/msg/PointCloud2",),
    "lidar": ("sensor_msgs/msg/PointCloud2",),
    "image": ("sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image"),
    "info": ("sensor_msgs/msg/CameraInfo",),
    "tf": ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage"),
    "map": ("grid_map_msgs/msg/GridMap",),
}

LARGE = ("camera.", "map.", "voxel_map", "lidar.")  # roles whose messages are staged or read again (or mapped)


def is_large(role: str) -> bool:
    """Whether messages of ``role`` are large (images, maps, voxel maps, raw scans)."""
    return role.startswith(LARGE)


def lidar_roles(roles: dict[str, str]) -> list[str]:
    """Return the raw-scan roles present (``lidar.<i>``, i the index in topics.lidar), in order."""
    return sorted((r for r in roles.values() if r.startswith("lidar.")), key=lambda r: int(r.split(".")[1]))


def _require(topics: dict[str, TopicInfo], role: str, topic: str, kind: str) -> None:
    info = topics.get(topic)
    types = TYPES[kind]
    if info is None:
        cands = sorted(t for t, i in topics.items() if i.msgtype in types)
        raise TopicError(f"role '{role}': topic '{topic}' not in the bags; {types[0].split('/')[-1]} topics found: {cands}")
    if info.msgtype not in types:
        raise TopicError(f"role '{role}': topic '{topic}' has type {info.msgtype}; expected {' or '.join(types)}")


def resolve_roles(cfg: GtgenConfig, topics: dict[str, TopicInfo]) -> dict[str, str]:
    """Return topic -> role for every role present, raising for missing required roles."""
    tp = cfg.topics
    roles: dict[str, str] = {}
    for r in RANGES:
        topic = tp.map_topic(r)
        if topic is not None:
            _require(topics, f"map.{r}", topic, "map")
            roles[topic] = f"map.{r}"
    if tp.voxel_map is not None:
        _require(topics, "voxel_map", tp.voxel_map, "voxel_map")
        roles[tp.voxel_map] = "voxel_map"
    mapping_topics(cfg, topics)  # checks the raw scans are there when maps are made from them
    for c in CAMERAS:
        _require(topics, f"camera.{c}", tp.cameras[c].image, "image")
        _require(topics, f"camera_info.{c}", tp.cameras[c].info, "info")
        roles[tp.cameras[c].image] = f"camera.{c}"
        roles[tp.cameras[c].info] = f"camera_info.{c}"
    if tp.odometry is not None:
        if tp.odometry not in topics and tp.tf in topics:
            cands = sorted(t for t, i in topics.items() if i.msgtype in TYPES["odometry"])
            raise TopicError(f"role 'odometry': topic '{tp.odometry}' not in the bags; Odometry topics found: {cands}; "
                             f"set topics.odometry: null to take poses from TF '{tp.odom_frame}' -> '{tp.base_frame}' on '{tp.tf}'")
        _require(topics, "odometry", tp.odometry, "odometry")
        roles[tp.odometry] = "odometry"
    elif tp.tf not in topics:
        raise TopicError(f"topics.odometry is null (poses from TF), but topic '{tp.tf}' is not in the bags")
    if tp.tf in topics:
        _require(topics, "tf", tp.tf, "tf")
        roles[tp.tf] = "tf"
    if tp.tf_static in topics:
        _require(topics, "tf_static", tp.tf_static, "tf")
        roles[tp.tf_static] = "tf_static"
    else:
        raise TopicError(f"role 'tf_static': topic '{tp.tf_static}' not in the bags; camera extrinsics come from it")
    if tp.gnss in topics:
        _require(topics, "gnss", tp.gnss, "gnss")
        roles[tp.gnss] = "gnss"
    for i, topic in enumerate(tp.lidar):  # optional: a lidar the bags do not hold is skipped
        if topic in topics:
            _require(topics, f"lidar[{i}]", topic, "lidar")
            roles[topic] = f"lidar.{i}"
    return roles


def mapping_topics(cfg: GtgenConfig, topics: dict[str, TopicInfo]) -> list[str]:
    """Return the raw-scan topics (``topics.lidar``) the bags hold when some map is made from
    lidar (``topics.from_lidar()``), raising if there is none; [] when no map is."""
    made = cfg.topics.from_lidar()
    if not made:
        return []
    held = [t for t in cfg.topics.lidar if t in topics]
    for i, t in enumerate(cfg.topics.lidar):
        if t in held:
            _require(topics, f"lidar[{i}]", t, "lidar")
    if not held:
        cands = sorted(t for t, i in topics.items() if i.msgtype in TYPES["lidar"])
        what = ", ".join(f"topics.{'map_' + m if m != 'voxel_map' else m}" for m in made)
        raise TopicError(f"{what} null (made from lidar), but none of topics.lidar {cfg.topics.lidar} is in the bags; "
                         f"PointCloud2 topics found: {cands}")
    return held
