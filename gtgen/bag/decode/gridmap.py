"""Decode grid_map_msgs/GridMap into arrays in gtgen's grid layout."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.tf import frame_id
from gtgen.bag.reader import stamp_ns
from gtgen.errors import DecodeError
from gtgen.geometry import quat_to_yaw


@dataclass
class GridMapData:
    """One decoded GridMap.

    ``layers`` are (nx, ny) float32 with axis 0 along the map's x, index 0 at the most
    negative x (gtgen layout); the cell (i, j) centre in the map frame is
    ``center + Rz(yaw) @ (-length_x/2 + (i + .5) r, -length_y/2 + (j + .5) r)``.
    """

    stamp_ns: int
    frame_id: str
    resolution_m: float
    center_m: NDArray[np.float64]
    yaw_rad: float
    layers: dict[str, NDArray[np.float32]]

    @property
    def shape(self) -> tuple[int, int]:
        return next(iter(self.layers.values())).shape if self.layers else (0, 0)


def _header(msg: object) -> object:
    # ROS 2 GridMap carries a top-level header; ROS 1 puts it in info
    if hasattr(msg, "header"):
        return msg.header  # type: ignore[attr-defined]
    return msg.info.header  # type: ignore[attr-defined]


def decode_gridmap(msg: object, layers: list[str] | None = None) -> GridMapData:
    """Return the GridMap ``msg`` decoded; ``layers`` selects and requires layer names."""
    info = msg.info  # type: ignore[attr-defined]
    names = list(msg.layers)  # type: ignore[attr-defined]
    hdr = _header(msg)
    res = float(info.resolution)
    want = names if layers is None else layers
    missing = [n for n in want if n not in names]
    if missing:
        raise DecodeError(f"GridMap has layers {names}; expected layer(s) {missing} (set topics.layers in the config)")
    if res <= 0 or not np.isfinite(res):
        raise DecodeError(f"GridMap resolution {res} is not a positive number")
    nx = int(round(info.length_x / res))
    ny = int(round(info.length_y / res))
    outer = int(msg.outer_start_index)  # type: ignore[attr-defined]
    inner = int(msg.inner_start_index)  # type: ignore[attr-defined]
    out: dict[str, NDArray[np.float32]] = {}
    for name in want:
        arr = msg.data[names.index(name)]  # type: ignore[attr-defined]
        dims = arr.layout.dim
        data = np.asarray(arr.data, dtype=np.float32)
        if len(dims) != 2:
            raise DecodeError(f"GridMap layer '{name}' has {len(dims)} layout dims; expected 2")
        labels = (dims[0].label, dims[1].label)
        if labels[0] == "column_index":
            cols, rows = int(dims[0].size), int(dims[1].size)
            order = "F"
        elif labels[0] == "row_index":
            rows, cols = int(dims[0].size), int(dims[1].size)
            order = "C"
        else:
            raise DecodeError(f"GridMap layer '{name}' has layout labels {list(labels)}; expected column_index/row_index")
        if rows * cols != data.size:
            raise DecodeError(f"GridMap layer '{name}' has {data.size} values for a {rows} x {cols} layout")
        if (rows, cols) != (nx, ny):
            raise DecodeError(f"GridMap layer '{name}' is {rows} x {cols} cells but info says {nx} x {ny} (length / resolution)")
        buf = data.reshape((rows, cols), order=order)
        # undo the circular buffer, then flip: grid_map index (0, 0) is the +x/+y corner
        unwrapped = np.roll(buf, (-outer, -inner), axis=(0, 1)) if (outer or inner) else buf
        out[name] = np.ascontiguousarray(unwrapped[::-1, ::-1])
    p = info.pose.position
    q = info.pose.orientation
    return GridMapData(
        stamp_ns=stamp_ns(hdr),
        frame_id=frame_id(hdr.frame_id),
        resolution_m=res,
        center_m=np.array([p.x, p.y, p.z], dtype=np.float64),
        yaw_rad=float(quat_to_yaw(np.array([q.x, q.y, q.z, q.w]))) if (q.x or q.y or q.z or q.w) else 0.0,
        layers=out,
    )
