"""The per-drive store written by ``gtgen extract`` (Zarr v3), defined once here.

A store is complete only when its attribute ``complete`` is true; it is written under
``<name>.partial`` and renamed when done, so a failed extract leaves no store a later
stage would accept.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from gtgen.config import RANGES
from gtgen.errors import StoreError
from gtgen.format import ArraySpec, find

DRIVE_STORE = "gtgen-drive"
DRIVE_VERSION = 2

MAP_LAYERS = ("elevation_m", "risk", "confidence")  # the grids of each kept map, in GridMap layer order (topics.layers)

_MAPS: list[ArraySpec] = []
for _r in RANGES:
    _MAPS += [
        ArraySpec(f"maps/{_r}/t_ns", "int64", "(M_r,)", "ns", "-", "-", f"header stamp of each kept {_r} GridMap"),
        ArraySpec(f"maps/{_r}/elevation_m", "float32", "(M_r, nx, ny)", "m", "map grid in odom", "NaN", "X-Racer elevation; axis 0 = map x from -L/2"),
        ArraySpec(f"maps/{_r}/risk", "float32", "(M_r, nx, ny)", "0..1", "map grid in odom", "NaN", "X-Racer traversability risk"),
        ArraySpec(f"maps/{_r}/confidence", "float32", "(M_r, nx, ny)", "0..1", "map grid in odom", "NaN", "X-Racer confidence"),
        ArraySpec(f"maps/{_r}/center_odom_m", "float64", "(M_r, 3)", "m", "odom", "-", "grid centre (GridMap info.pose position)"),
        ArraySpec(f"maps/{_r}/yaw_odom_rad", "float64", "(M_r,)", "rad", "odom", "-", "grid yaw (GridMap info.pose orientation)"),
    ]

DRIVE_ARRAYS: list[ArraySpec] = [
    ArraySpec("poses/t_ns", "int64", "(N,)", "ns", "-", "-", "odometry stamps, sorted, unique"),
    ArraySpec("poses/pos_odom_m", "float64", "(N, 3)", "m", "odom", "-", "base position T_odom_base"),
    ArraySpec("poses/quat_odom_xyzw", "float64", "(N, 4)", "-", "odom", "-", "base orientation T_odom_base"),
    ArraySpec("gnss/t_ns", "int64", "(G,)", "ns", "-", "-", "NavSatFix stamps"),
    ArraySpec("gnss/lat_deg", "float64", "(G,)", "deg", "WGS84", "-", "latitude"),
    ArraySpec("gnss/lon_deg", "float64", "(G,)", "deg", "WGS84", "-", "longitude"),
    ArraySpec("gnss/alt_m", "float64", "(G,)", "m", "WGS84 ellipsoid", "-", "ellipsoidal altitude"),
    ArraySpec("gnss/var_enu_m2", "float64", "(G, 3)", "m^2", "ENU", "-", "diagonal of position_covariance (NaN if unknown)"),
    ArraySpec("gnss/status", "int8", "(G,)", "-", "-", "-", "NavSatStatus.status (-1 no fix)"),
    *_MAPS,
    ArraySpec("candidates/t_ns", "int64", "(C,)", "ns", "-", "-", "candidate sample times (every stride_m of travel)"),
    ArraySpec("candidates/reason", "uint8", "(C,)", "code", "-", "-", "0 = kept, else the rejection reason (gtgen.reasons)"),
    ArraySpec("samples/t_ns", "int64", "(S,)", "ns", "-", "-", "sample time (front camera stamp)"),
    ArraySpec("samples/pos_odom_m", "float64", "(S, 3)", "m", "odom", "-", "base position at t (interpolated)"),
    ArraySpec("samples/quat_odom_xyzw", "float64", "(S, 4)", "-", "odom", "-", "base orientation at t (SLERP)"),
    ArraySpec("samples/distance_m", "float64", "(S,)", "m", "-", "-", "odometry travel since the drive start"),
    ArraySpec("samples/map_index_micro", "int64", "(S,)", "-", "-", "-", "index into maps/micro of the X-Racer map at t"),
    ArraySpec("samples/map_index_short", "int64", "(S,)", "-", "-", "-", "index into maps/short of the X-Racer map at t"),
    ArraySpec("samples/images", "uint8", "(S, 4, H, W, 3)", "RGB", "camera", "-", "front, left, right, back; resized to extract.image_*"),
    ArraySpec("samples/image_t_ns", "int64", "(S, 4)", "ns", "-", "-", "stamp of each image"),
    ArraySpec("samples/voxel_t_ns", "int64", "(S,)", "ns", "-", "-", "stamp of the voxel map used"),
    ArraySpec("samples/voxel_index", "int64", "(S,)", "-", "-", "-", "index into voxel_maps of the voxel map used"),
    ArraySpec("voxel_maps/t_ns", "int64", "(V,)", "ns", "-", "-", "stamps of the voxel maps some sample uses"),
    ArraySpec("voxel_maps/n_points", "int64", "(V,)", "-", "-", "-", "points of each voxel map (at most shards.max_voxel_points)"),
    ArraySpec("voxel_maps/points_odom_m", "float32", "(V, P, 3)", "m", "odom", "NaN", "points of map v in rows [0, n_points[v]); P = shards.max_voxel_points, the nearest kept"),
    ArraySpec("calib/K", "float64", "(4, 3, 3)", "px", "camera", "-", "intrinsics rescaled to the stored image size"),
    ArraySpec("calib/T_base_cam", "float64", "(4, 4, 4)", "m", "base_link <- camera optical", "-", "camera extrinsics from tf_static"),
]


def spec(path: str) -> ArraySpec:
    """Return the spec of drive-store array ``path``."""
    return find(DRIVE_ARRAYS, path)


def partial_path(path: Path) -> Path:
    """Return where a store is written before it is complete."""
    return path.with_name(path.name + ".partial")


def finalize(tmp: Path, path: Path) -> None:
    """Replace ``path`` by the completed store ``tmp`` (near-atomic: two renames)."""
    old = path.with_name(path.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if path.exists():
        path.rename(old)
    tmp.rename(path)
    shutil.rmtree(old, ignore_errors=True)


def open_drive(path: Path, mode: str = "r") -> Any:
    """Return the zarr group of a complete drive store, or raise StoreError saying why not."""
    import zarr

    if not path.exists():
        hint = " (a failed extract left only a .partial store)" if partial_path(path).exists() else ""
        raise StoreError(f"drive store '{path}' does not exist{hint}; run 'gtgen extract BAG' first")
    try:
        g = zarr.open_group(str(path), mode=mode)
    except Exception as err:  # noqa: BLE001 - zarr raises several types for non-stores
        raise StoreError(f"'{path}' is not a zarr store: {err}".splitlines()[0]) from err
    attrs = g.attrs.asdict()
    if attrs.get("store") != DRIVE_STORE:
        raise StoreError(f"'{path}' is not a gtgen drive store (store={attrs.get('store')!r})")
    if attrs.get("version") != DRIVE_VERSION:
        raise StoreError(f"drive store '{path}' has version {attrs.get('version')}; this gtgen reads version {DRIVE_VERSION}: re-run 'gtgen extract'")
    if not attrs.get("complete"):
        raise StoreError(f"drive store '{path}' is incomplete (its extract did not finish); re-run 'gtgen extract'")
    return g


def jsonable(obj: Any) -> Any:
    """Return ``obj`` with numpy scalars and paths turned into JSON types."""
    return json.loads(json.dumps(obj, default=lambda o: o.item() if hasattr(o, "item") else str(o)))

