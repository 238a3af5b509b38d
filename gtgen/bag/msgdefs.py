"""Message definitions gtgen ships for bags that carry none (grid_map_msgs)."""

from __future__ import annotations

from functools import cache

from rosbags.typesys import Stores, get_typestore, get_types_from_msg
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

GRIDMAP = "grid_map_msgs/msg/GridMap"
GRIDMAPINFO = "grid_map_msgs/msg/GridMapInfo"


def gridmap_types(ros1: bool) -> dict:
    """Return the rosbags type dictionary of grid_map_msgs for ROS 1 or ROS 2."""
    types = {}
    types.update(get_types_from_msg(GRIDMAP_ROS1 if ros1 else GRIDMAP_ROS2, GRIDMAP))
    types.update(get_types_from_msg(GRIDMAPINFO_ROS1 if ros1 else GRIDMAPINFO_ROS2, GRIDMAPINFO))
    return types


@cache
def typestore(ros1: bool) -> Typestore:
    """Return a typestore of the standard ROS types plus grid_map_msgs."""
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    store.register(gridmap_types(ros1))
    if "tf2_msgs/msg/TFMessage" not in store.types:  # not in rosbags' noetic store
        store.register(get_types_from_msg(TFMESSAGE_ROS1, "tf2_msgs/msg/TFMessage"))
    return store
