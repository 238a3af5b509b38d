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


@dataclass(frozen=True)
class _Layout:
    """Where a GridMap's layers lie in its buffers: the checked outcome of its info and layouts."""

    names: list[str]
    want: list[str]
    shape: tuple[int, int]
    resolution_m: float
    orders: tuple[str, ...]  # per wanted layer: 'F' column-major, 'C' row-major


def _layout(msg: object, layers: list[str] | None) -> _Layout:
    """Return the layout of GridMap ``msg``, raising DecodeError for anything its arrays
    cannot be read by: a missing layer, a bad resolution or length, layout dims that do not
    match the data length or the info."""
    info = msg.info  # type: ignore[attr-defined]
    names = list(msg.layers)  # type: ignore[attr-defined]
    res = float(info.resolution)
    want = names if layers is None else layers
    missing = [n for n in want if n not in names]
    if missing:
        raise DecodeError(f"GridMap has layers {names}; expected layer(s) {missing} (set topics.layers in the config)")
    if len(msg.data) != len(names):  # type: ignore[attr-defined]
        raise DecodeError(f"GridMap has {len(msg.data)} data arrays for {len(names)} layers {names}")  # type: ignore[attr-defined]
    if res <= 0 or not np.isfinite(res):
        raise DecodeError(f"GridMap resolution {res} is not a positive number")
    lengths = (float(info.length_x), float(info.length_y))
    if not all(np.isfinite(v) and 0 < v / res < 1 << 20 for v in lengths):
        raise DecodeError(f"GridMap length {list(lengths)} m at resolution {res} m is not a grid")
    nx, ny = (int(round(v / res)) for v in lengths)
    orders = []
    for name in want:
        arr = msg.data[names.index(name)]  # type: ignore[attr-defined]
        dims = arr.layout.dim
        if len(dims) != 2:
            raise DecodeError(f"GridMap layer '{name}' has {len(dims)} layout dims; expected 2")
        labels = (dims[0].label, dims[1].label)
        if labels[0] == "column_index":
            cols, rows = int(dims[0].size), int(dims[1].size)
            orders.append("F")
        elif labels[0] == "row_index":
            rows, cols = int(dims[0].size), int(dims[1].size)
            orders.append("C")
        else:
            raise DecodeError(f"GridMap layer '{name}' has layout labels {list(labels)}; expected column_index/row_index")
        if rows * cols != len(arr.data):
            raise DecodeError(f"GridMap layer '{name}' has {len(arr.data)} values for a {rows} x {cols} layout")
        if (rows, cols) != (nx, ny):
            raise DecodeError(f"GridMap layer '{name}' is {rows} x {cols} cells but info says {nx} x {ny} (length / resolution)")
    return _Layout(names, want, (nx, ny), res, tuple(orders))


def check_gridmap(msg: object, layers: list[str]) -> tuple[tuple[int, int], float]:
    """Return the (shape, resolution [m]) GridMap ``msg`` decodes to with ``layers``, without
    decoding its arrays; raise DecodeError where ``decode_gridmap`` would."""
    lay = _layout(msg, layers)
    return lay.shape, lay.resolution_m


def decode_gridmap(msg: object, layers: list[str] | None = None) -> GridMapData:
    """Return the GridMap ``msg`` decoded; ``layers`` selects and requires layer names."""
    lay = _layout(msg, layers)
    info = msg.info  # type: ignore[attr-defined]
    hdr = _header(msg)
    outer = int(msg.outer_start_index)  # type: ignore[attr-defined]
    inner = int(msg.inner_start_index)  # type: ignore[attr-defined]
    out: dict[str, NDArray[np.float32]] = {}
    for name, order in zip(lay.want, lay.orders):
        data = np.asarray(msg.data[lay.names.index(name)].data, dtype=np.float32)  # type: ignore[attr-defined]
        buf = data.reshape(lay.shape, order=order)
        # undo the circular buffer, then flip: grid_map index (0, 0) is the +x/+y corner
        unwrapped = np.roll(buf, (-outer, -inner), axis=(0, 1)) if (outer or inner) else buf
        out[name] = np.ascontiguousarray(unwrapped[::-1, ::-1])
    p = info.pose.position
    q = info.pose.orientation
    return GridMapData(
        stamp_ns=stamp_ns(hdr),
        frame_id=frame_id(hdr.frame_id),
        resolution_m=lay.resolution_m,
        center_m=np.array([p.x, p.y, p.z], dtype=np.float64),
        yaw_rad=float(quat_to_yaw(np.array([q.x, q.y, q.z, q.w]))) if (q.x or q.y or q.z or q.w) else 0.0,
        layers=out,
    )
