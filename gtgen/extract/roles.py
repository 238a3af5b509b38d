"""Which topic plays which role: the config's mapping checked against the bags' topics."""

from __future__ import annotations

from collections.abc import Iterable

from gtgen.bag.reader import TopicInfo
from gtgen.config import LIDAR_REFERENCE, RANGES, GtgenConfig
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


def lidar_roles(roles: Iterable[str]) -> list[str]:
    """Return the raw-scan roles among ``roles`` (``lidar.<i>``, i the index in topics.lidar), in order."""
    return sorted((r for r in roles if r.startswith("lidar.")), key=lambda r: int(r.split(".")[1]))


def reference_role(cfg: GtgenConfig, roles: Iterable[str]) -> str:
    """Return the role whose stamps sample times snap to (``GtgenConfig.reference``): a
    camera's, or the first lidar's among ``roles``; raise TopicError when there is none."""
    ref = cfg.reference
    if ref != LIDAR_REFERENCE:
        return f"camera.{ref}"
    lidars = lidar_roles(roles)
    if not lidars:
        what = "extract.reference is 'lidar'" if cfg.extract.reference else "no camera is configured (topics.cameras)"
        raise TopicError(f"{what} and none of topics.lidar {cfg.topics.lidar} is in the bags: samples snap to a camera's or "
                         "a lidar's stamps; name the bags' PointCloud2 scans in topics.lidar or a camera in topics.cameras")
    return lidars[0]


# how a log of another rig says which cameras it has
_CAMERA_HINT = "; name your cameras in topics.cameras ({name: {image, info}}; {} for none)"


def _require(topics: dict[str, TopicInfo], role: str, topic: str, kind: str, hint: str = "") -> None:
    info = topics.get(topic)
    types = TYPES[kind]
    if info is None:
        cands = sorted(t for t, i in topics.items() if i.msgtype in types)
        raise TopicError(f"role '{role}': topic '{topic}' not in the bags; {types[0].split('/')[-1]} topics found: {cands}{hint}")
    if info.msgtype not in types:
        raise TopicError(f"role '{role}': topic '{topic}' has type {info.msgtype}; expected {' or '.join(types)}")


def resolve_roles(cfg: GtgenConfig, topics: dict[str, TopicInfo]) -> dict[str, str]:
    """Return topic -> role for every role present, raising for missing required roles."""
    tp = cfg.topics
    roles: dict[str, str] = {}
    for r in RANGES:
        topic = tp.map_topic(r)
        if topic is not None:
            _no_stack_maps(topics, f"map.{r}", topic)
            _require(topics, f"map.{r}", topic, "map")
            roles[topic] = f"map.{r}"
    if tp.voxel_map is not None:
        _require(topics, "voxel_map", tp.voxel_map, "voxel_map")
        roles[tp.voxel_map] = "voxel_map"
    mapping_topics(cfg, topics)  # checks the raw scans are there when maps are made from them
    for c, ct in tp.cameras.items():
        _require(topics, f"camera.{c}", ct.image, "image", hint=_CAMERA_HINT)
        _require(topics, f"camera_info.{c}", ct.info, "info", hint=_CAMERA_HINT)
        roles[ct.image] = f"camera.{c}"
        roles[ct.info] = f"camera_info.{c}"
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
    if tp.gnss is not None and tp.gnss in topics:
        _require(topics, "gnss", tp.gnss, "gnss")
        roles[tp.gnss] = "gnss"
    for i, topic in enumerate(tp.lidar):  # optional: a lidar the bags do not hold is skipped
        if topic in topics:
            _require(topics, f"lidar[{i}]", topic, "lidar")
            roles[topic] = f"lidar.{i}"
    reference_role(cfg, roles.values())
    return roles


def _no_stack_maps(topics: dict[str, TopicInfo], role: str, topic: str) -> None:
    """Raise TopicError naming the lidar topics and the recipe when the bags hold no GridMap
    at all but raw scans: a log of a robot without a stack."""
    if topic in topics or any(i.msgtype in TYPES["map"] for i in topics.values()):
        return
    clouds = sorted(t for t, i in topics.items() if i.msgtype in TYPES["lidar"])
    if clouds:
        raise TopicError(f"role '{role}': topic '{topic}' not in the bags, which hold no GridMap but PointCloud2 topics {clouds}: "
                         f"to make the maps from lidar set topics.map_micro, map_short and voxel_map to null and topics.lidar to "
                         f"[{', '.join(repr(c) for c in clouds)}] (or the scans among them)")


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
