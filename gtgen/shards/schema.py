"""The dataset format, defined once: names, dtypes, shapes, units, frames, fill values.

``data_schema.md`` mirrors this list (a test checks that they agree). Symbols:
S samples, R rejected samples, n_m / n_s micro / short grid cells per side, H x W the
stored image size, P voxel points of all samples. The target frame of a sample is
vehicle-centric and gravity-aligned at its time t (SPEC section 3).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gtgen.config import RANGES
from gtgen.errors import StoreError
from gtgen.format import ArraySpec, find

SCHEMA_VERSION = 1
DATASET_STORE = "gtgen-dataset"
SAMPLES_PER_SHARD = 16
POINTS_PER_CHUNK = 1 << 17

SPLITS = {0: "train", 1: "val"}

_TGT = "target (vehicle, gravity-aligned, at t)"

DATASET_ARRAYS: list[ArraySpec] = []
for _r in RANGES:
    _n = "n_m" if _r == "micro" else "n_s"
    DATASET_ARRAYS += [
        ArraySpec(f"labels/{_r}/elevation_m", "float32", f"(S, {_n}, {_n})", "m, rel. base z at t", _TGT, "NaN", "fused elevation (regions 1, 2), aligned DEM (region 3)"),
        ArraySpec(f"labels/{_r}/risk", "float32", f"(S, {_n}, {_n})", "0..1", _TGT, "NaN", "latest confident X-Racer risk in the window"),
        ArraySpec(f"labels/{_r}/confidence", "float32", f"(S, {_n}, {_n})", "0..1", _TGT, "NaN", "max X-Racer confidence in the window"),
        ArraySpec(f"labels/{_r}/region", "uint8", f"(S, {_n}, {_n})", "code", _TGT, "0", "0 no label, 1 observed past/current, 2 observed future, 3 unobserved (DEM)"),
        ArraySpec(f"labels/{_r}/count", "uint16", f"(S, {_n}, {_n})", "maps", _TGT, "0", "observations averaged into the elevation"),
        ArraySpec(f"labels/{_r}/last_dt_s", "float32", f"(S, {_n}, {_n})", "s, rel. t", _TGT, "NaN", "time of the last observation minus t"),
        ArraySpec(f"xracer/{_r}/elevation_m", "float32", f"(S, {_n}, {_n})", "m, rel. base z at t", _TGT, "NaN", "X-Racer map at t (the baseline row)"),
        ArraySpec(f"xracer/{_r}/risk", "float32", f"(S, {_n}, {_n})", "0..1", _TGT, "NaN", "X-Racer risk at t"),
        ArraySpec(f"xracer/{_r}/confidence", "float32", f"(S, {_n}, {_n})", "0..1", _TGT, "NaN", "X-Racer confidence at t"),
        ArraySpec(f"dem/{_r}/elevation_m", "float32", f"(S, {_n}, {_n})", "m, rel. base z at t", _TGT, "NaN", "aligned DEM, bilinear"),
    ]
DATASET_ARRAYS += [
    ArraySpec("inputs/images", "uint8", "(S, 4, H, W, 3)", "RGB", "camera", "0", "front, left, right, back"),
    ArraySpec("inputs/K", "float64", "(S, 4, 3, 3)", "px", "camera", "0", "intrinsics for the stored image size"),
    ArraySpec("inputs/T_base_cam", "float64", "(S, 4, 4, 4)", "m", "base <- camera optical", "0", "camera extrinsics"),
    ArraySpec("inputs/T_target_base", "float64", "(S, 4, 4)", "m", "target <- base", "0", "the base's roll and pitch in the target frame"),
    ArraySpec("inputs/raw_elevation_m", "float32", "(S, n_s, n_s)", "m, rel. base z at t", _TGT, "NaN", "lowest voxel-map point per short cell"),
    ArraySpec("inputs/voxel_offsets", "int64", "(S + 1,)", "-", "-", "0", "sample s owns voxel_points_m[offsets[s]:offsets[s+1]]"),
    ArraySpec("inputs/voxel_points_m", "float32", "(P, 3)", "m", _TGT, "0", "voxel map points, flat"),
    ArraySpec("meta/t_ns", "int64", "(S,)", "ns", "-", "0", "sample time"),
    ArraySpec("meta/drive", "uint16", "(S,)", "-", "-", "0", "index into the attribute 'drives'"),
    ArraySpec("meta/pos_odom_m", "float64", "(S, 3)", "m", "odom", "0", "base position at t"),
    ArraySpec("meta/yaw_odom_rad", "float64", "(S,)", "rad", "odom", "0", "base yaw at t"),
    ArraySpec("meta/crs_en_m", "float64", "(S, 2)", "m", "DEM CRS", "0", "sample position (easting, northing) after ICP"),
    ArraySpec("meta/T_crs_target", "float64", "(S, 4, 4)", "m", "DEM CRS <- target", "0", "alignment after ICP (z: DEM heights)"),
    ArraySpec("meta/icp_fitness", "float32", "(S,)", "0..1", "-", "0", "share of source cells within dem.icp_max_distance_m"),
    ArraySpec("meta/icp_rmse_m", "float32", "(S,)", "m", "-", "0", "point-to-plane RMSE of the inliers"),
    ArraySpec("meta/icp_correction", "float32", "(S, 4)", "m, m, m, rad", _TGT, "0", "ICP correction dx, dy, dz, dyaw over the prior placement"),
    ArraySpec("meta/split", "uint8", "(S,)", "code", "-", "0", "0 train, 1 val (by geography block)"),
    ArraySpec("rejected/t_ns", "int64", "(R,)", "ns", "-", "0", "time of each rejected sample"),
    ArraySpec("rejected/drive", "uint16", "(R,)", "-", "-", "0", "drive of each rejected sample"),
    ArraySpec("rejected/reason", "uint8", "(R,)", "code", "-", "0", "why (gtgen.reasons)"),
    ArraySpec("rejected/icp_fitness", "float32", "(R,)", "0..1", "-", "NaN", "ICP fitness if ICP ran"),
    ArraySpec("rejected/icp_rmse_m", "float32", "(R,)", "m", "-", "NaN", "ICP RMSE if ICP ran"),
]


# the arrays with one row per sample (sharded along the sample axis)
SAMPLE_ARRAYS: list[ArraySpec] = [s for s in DATASET_ARRAYS if not s.path.startswith(("rejected/", "inputs/voxel_"))]


def spec(path: str) -> ArraySpec:
    """Return the spec of dataset array ``path``."""
    return find(DATASET_ARRAYS, path)


def row_shape(s: ArraySpec, dims: dict[str, int]) -> tuple[int, ...]:
    """Return one sample's shape of per-sample array ``s``; ``dims`` gives the symbols
    (n_m, n_s, H, W)."""
    axes = [d.strip() for d in s.shape.strip("()").split(",") if d.strip()][1:]
    return tuple(int(dims[d]) if d in dims else int(d) for d in axes)


@dataclass(frozen=True)
class DatasetInfo:
    """The validated top-level attributes of a dataset store."""

    path: Path
    n_samples: int
    micro: int
    short: int
    image_hw: tuple[int, int]
    attrs: dict[str, Any]


def open_dataset(path: Path) -> tuple[Any, DatasetInfo]:
    """Return (zarr group, info) of a complete dataset, or raise StoreError saying why not."""
    import zarr

    if not path.exists():
        raise StoreError(f"dataset '{path}' does not exist; run 'gtgen dem-align' first")
    try:
        g = zarr.open_group(str(path), mode="r")
    except Exception as err:  # noqa: BLE001
        raise StoreError(f"'{path}' is not a zarr store: {err}".splitlines()[0]) from err
    a = g.attrs.asdict()
    if a.get("store") != DATASET_STORE:
        raise StoreError(f"'{path}' is not a gtgen dataset (store={a.get('store')!r})")
    if a.get("schema_version") != SCHEMA_VERSION:
        raise StoreError(f"dataset '{path}' has schema version {a.get('schema_version')}; this gtgen reads version {SCHEMA_VERSION}")
    if not a.get("complete"):
        raise StoreError(f"dataset '{path}' is incomplete; re-run 'gtgen dem-align'")
    S = int(g["meta/t_ns"].shape[0])
    img = g["inputs/images"].shape
    return g, DatasetInfo(path, S, int(g["labels/micro/region"].shape[1]), int(g["labels/short/region"].shape[1]), (int(img[2]), int(img[3])), a)
