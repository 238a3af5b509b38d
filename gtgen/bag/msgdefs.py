"""Message definitions gtgen ships: grid_map_msgs for bags that carry none, and the ROS 2
foxglove_msgs Grid that ``gtgen export mcap`` writes (so no network is needed for them)."""

from __future__ import annotations

from functools import cache, lru_cache

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

GRIDMAP_ROS2 = """\
std_msgs/Header header
grid_map_msgs/GridMapInfo info
string[] layers
string[] basic_layers
std_msgs/Float32MultiArray[] data
uint16 outer_start_index
uint16 inner_start_index
"""

GRIDMAPINFO_ROS2 = """\
float64 resolution
float64 length_x
float64 length_y
geometry_msgs/Pose pose
"""

GRIDMAP_ROS1 = """\
grid_map_msgs/GridMapInfo info
string[] layers
string[] basic_layers
std_msgs/Float32MultiArray[] data
uint16 outer_start_index
uint16 inner_start_index
"""

GRIDMAPINFO_ROS1 = """\
std_msgs/Header header
float64 resolution
float64 length_x
float64 length_y
geometry_msgs/Pose pose
"""

TFMESSAGE_ROS1 = "geometry_msgs/TransformStamped[] transforms\n"

# foxglove_msgs (ROS 2), as in github.com/foxglove/schemas: the grid Foxglove's 3D panel draws
FOXGLOVE_GRID = """\
builtin_interfaces/Time timestamp
string frame_id
geometry_msgs/Pose pose
uint32 column_count
foxglove_msgs/Vector2 cell_size
uint32 row_stride
uint32 cell_stride
foxglove_msgs/PackedElementField[] fields
uint8[] data
"""
FOXGLOVE_VECTOR2 = "float64 x\nfloat64 y\n"
FOXGLOVE_PACKED_FIELD = """\
uint8 UNKNOWN=0
uint8 UINT8=1
uint8 INT8=2
uint8 UINT16=3
uint8 INT16=4
uint8 UINT32=5
uint8 INT32=6
uint8 FLOAT32=7
uint8 FLOAT64=8
string name
uint32 offset
uint8 type
"""

GRIDMAP = "grid_map_msgs/msg/GridMap"
GRIDMAPINFO = "grid_map_msgs/msg/GridMapInfo"


def gridmap_types(ros1: bool) -> dict:
    """Return the rosbags type dictionary of grid_map_msgs for ROS 1 or ROS 2."""
    types = {}
    types.update(get_types_from_msg(GRIDMAP_ROS1 if ros1 else GRIDMAP_ROS2, GRIDMAP))
    types.update(get_types_from_msg(GRIDMAPINFO_ROS1 if ros1 else GRIDMAPINFO_ROS2, GRIDMAPINFO))
    return types


def normalize_msgtype(name: str) -> str:
    """Return a message type name in rosbags' form: 'pkg/Type' (ROS 1) becomes 'pkg/msg/Type'."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def typestore_of(schemas: list, ros1: bool) -> Typestore:
    """Return a typestore of the message definitions a bag carries (``schemas``, each with
    ``name``, ``encoding`` and ``data``), or the default one when it carries none. Bags of
    one robot carry the same definitions: their typestore (parsed definitions and the
    deserializers rosbags generates, about 0.1 s a bag) is made once per process."""
    texts = tuple(dict.fromkeys((s.name, s.encoding, s.data.decode() if isinstance(s.data, bytes) else str(s.data)) for s in schemas))
    return _typestore_of_texts(texts, ros1)


@lru_cache(maxsize=8)
def _typestore_of_texts(texts: tuple[tuple[str, str, str], ...], ros1: bool) -> Typestore:
    from rosbags.typesys import get_types_from_idl

    types: dict = {}
    for name, encoding, text in texts:
        if encoding == "ros2idl":
            types.update(get_types_from_idl(text))
        elif encoding in ("ros1msg", "ros2msg"):
            types.update(get_types_from_msg(text, normalize_msgtype(name)))
    if not types:
        return typestore(ros1)
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    return store


@cache
def typestore(ros1: bool) -> Typestore:
    """Return a typestore of the standard ROS types plus grid_map_msgs."""
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    store.register(gridmap_types(ros1))
    if "tf2_msgs/msg/TFMessage" not in store.types:  # not in rosbags' noetic store
        store.register(get_types_from_msg(TFMESSAGE_ROS1, "tf2_msgs/msg/TFMessage"))
    if not ros1:
        for text, name in ((FOXGLOVE_VECTOR2, "foxglove_msgs/msg/Vector2"), (FOXGLOVE_PACKED_FIELD, "foxglove_msgs/msg/PackedElementField"),
                           (FOXGLOVE_GRID, "foxglove_msgs/msg/Grid")):
            store.register(get_types_from_msg(text, name))
    return store
