"""Every on-disk format gtgen writes, defined once: store kinds, versions, arrays.

A store is a Zarr v3 group whose attributes say its ``store`` kind, its version and
``complete`` (true only once written whole). Its arrays are lists of :class:`ArraySpec`
(name, dtype, shape symbols, units, frame, fill, meaning); ``data_schema.md`` mirrors
these lists and ``tests/test_schema_doc.py`` checks that they agree. Shape symbols: N
poses, G fixes, M_r kept maps of range r, Q_c candidates, C cameras (topics.cameras, 0 to
8; the store's ``cameras`` attribute names them in this order), S samples, V voxel maps, R
rejected samples, n_m / n_s micro / short cells per side, B the bytes a stored JPEG may
take (3 x extract.image_width x image_height), P voxel points, L kept raw scans, Q =
extract.max_scan_points, P_s = shards.max_scan_points, N_s = shards.max_scans. The target frame of a sample is vehicle-centric and gravity-aligned at
its time t (see data_schema.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from gtgen import codes
from gtgen.config import RANGES
from gtgen.storage.specs import ArraySpec, find


@dataclass(frozen=True)
class StoreFormat:
    """One kind of store: its ``store`` attribute, version, arrays, the command that makes
    it, and the sections of its recorded config that its data depend on."""

    kind: str
    version: int
    arrays: tuple[ArraySpec, ...]
    made_by: str
    rebuild: str = ""  # how a store of an older version is rebuilt (it may need earlier stages again)
    # read back from its recorded config; the later stages' sections say nothing about its
    # data, so a gtgen whose later stages have other keys still reads it
    config_sections: tuple[str, ...] = ()

    def spec(self, path: str) -> ArraySpec:
        """Return the spec of array ``path``."""
        return find(list(self.arrays), path)


# -- the drive store (``gtgen extract``) ---------------------------------------------------
MAP_LAYERS = ("elevation_m", "risk", "confidence")  # the grids of each kept map, in GridMap layer order (topics.layers)

_MAPS: list[ArraySpec] = []
for _r in RANGES:
    _MAPS += [
        ArraySpec(f"maps/{_r}/t_ns", "int64", "(M_r,)", "ns", "-", "-", f"header stamp of each kept {_r} GridMap"),
        ArraySpec(f"maps/{_r}/elevation_m", "float32", "(M_r, nx, ny)", "m", "map grid in odom", "NaN", "X-Racer elevation; axis 0 = map x from -L/2", codec="lz4"),
        ArraySpec(f"maps/{_r}/risk", "float32", "(M_r, nx, ny)", "0..1", "map grid in odom", "NaN", "X-Racer traversability risk", codec="lz4"),
        ArraySpec(f"maps/{_r}/confidence", "float32", "(M_r, nx, ny)", "0..1", "map grid in odom", "NaN", "X-Racer confidence", codec="lz4"),
        ArraySpec(f"maps/{_r}/center_odom_m", "float64", "(M_r, 3)", "m", "odom", "-", "grid centre (GridMap info.pose position)"),
        ArraySpec(f"maps/{_r}/yaw_odom_rad", "float64", "(M_r,)", "rad", "odom", "-", "grid yaw (GridMap info.pose orientation)"),
        ArraySpec(f"maps/{_r}/z_offset_m", "float64", "(M_r,)", "m", "odom", "-", "added to the map's elevations to put them in odom: its frame's height at the grid centre (0 in odom)"),
    ]

_DRIVE: list[ArraySpec] = [
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
    ArraySpec("candidates/t_ns", "int64", "(Q_c,)", "ns", "-", "-", "candidate sample times (every stride_m of travel)"),
    ArraySpec("candidates/reason", "uint8", "(Q_c,)", "code", "-", "-", "0 = kept, else the rejection reason (gtgen.codes)"),
    ArraySpec("samples/t_ns", "int64", "(S,)", "ns", "-", "-", "sample time (a stamp of the reference sensor: extract.reference)"),
    ArraySpec("samples/pos_odom_m", "float64", "(S, 3)", "m", "odom", "-", "base position at t (interpolated)"),
    ArraySpec("samples/quat_odom_xyzw", "float64", "(S, 4)", "-", "odom", "-", "base orientation at t (SLERP)"),
    ArraySpec("samples/distance_m", "float64", "(S,)", "m", "-", "-", "odometry travel since the drive start"),
    ArraySpec("samples/map_index_micro", "int64", "(S,)", "-", "-", "-", "index into maps/micro of the X-Racer map at t"),
    ArraySpec("samples/map_index_short", "int64", "(S,)", "-", "-", "-", "index into maps/short of the X-Racer map at t"),
    ArraySpec("samples/jpeg", "uint8", "(S, C, B)", "JPEG file", "camera (rectified)", "0", "each camera's JPEG file in bytes [0, jpeg_nbytes), zeros after; the camera's own when not resized or rectified (see Images)"),
    ArraySpec("samples/jpeg_nbytes", "int64", "(S, C)", "bytes", "-", "-", "length of each stored JPEG file"),
    ArraySpec("samples/image_t_ns", "int64", "(S, C)", "ns", "-", "-", "stamp of each image"),
    ArraySpec("samples/voxel_t_ns", "int64", "(S,)", "ns", "-", "-", "stamp of the voxel map used"),
    ArraySpec("samples/voxel_index", "int64", "(S,)", "-", "-", "-", "index into voxel_maps of the voxel map used"),
    ArraySpec("voxel_maps/t_ns", "int64", "(V,)", "ns", "-", "-", "stamps of the voxel maps some sample uses"),
    ArraySpec("voxel_maps/n_points", "int64", "(V,)", "-", "-", "-", "points of each voxel map (at most shards.max_voxel_points)"),
    ArraySpec("voxel_maps/points_odom_m", "float32", "(V, P, 3)", "m", "odom", "NaN", "points of map v in rows [0, n_points[v]); P = shards.max_voxel_points, the nearest kept"),
    ArraySpec("samples/T_base_cam", "float64", "(S, C, 4, 4)", "m", "base_link <- camera optical", "-", "camera extrinsics at each image's stamp (TF)"),
    ArraySpec("calib/K", "float64", "(C, 3, 3)", "px", "camera (rectified)", "-", "intrinsics of the stored (rectified) images: CameraInfo's K rescaled to calib/image_size"),
    ArraySpec("calib/image_size", "int64", "(C, 2)", "px", "-", "-", "width, height of each camera's stored images"),
    ArraySpec("scans/t_ns", "int64", "(L,)", "ns", "-", "-", "header stamp of each kept raw scan (lidar role; sorted by lidar, then stamp)"),
    ArraySpec("scans/lidar", "uint8", "(L,)", "-", "-", "-", "the scan's lidar: index into topics.lidar of the stored config"),
    ArraySpec("scans/n_points", "int64", "(L,)", "-", "-", "-", "points of each scan (at most extract.max_scan_points, the nearest kept)"),
    ArraySpec("scans/distance_m", "float64", "(L,)", "m", "-", "-", "odometry travel at the scan's stamp"),
    ArraySpec("scans/T_odom_sensor", "float64", "(L, 4, 4)", "m", "odom <- sensor", "-", "pose of the rows' origin at the stamp: the lidar (TF), or for a cloud far from its frame's origin that frame shifted to the cloud's median (extract.lidar.compact)"),
    ArraySpec("scans/points_cm", "int16", "(L, Q, 3)", "cm", "sensor at the stamp", "-32768", "points of scan l in rows [0, n_points[l]), motion-corrected to the stamp if the cloud has per-point times; one chunk per scan"),
]

DRIVE = StoreFormat("gtgen-drive", 8, tuple(_DRIVE), "gtgen extract BAG",
                    "re-run 'gtgen extract BAG --overwrite' (version 8 stores the maps' float grids with lz4, faster to write and read)",
                    ("grids", "topics", "extract", "mapping"))


# -- the fused store (``gtgen fuse``) ------------------------------------------------------
_FUSED: list[ArraySpec] = [
    ArraySpec("samples/reason", "uint8", "(S,)", "code", "-", "-", "0 = fused, else why not (gtgen.codes)"),
]
for _r in RANGES:
    _f = "vehicle frame at t"
    _FUSED += [
        ArraySpec(f"fused/{_r}/elevation_m", "float32", "(S, n, n)", "m, rel. base z at t", _f, "NaN", "elevation of the confident observations in the window: their mean (fuse.elevation_rule mean), or the mean of those off the maps' top layer (rule ground)", codec="lz4"),
        ArraySpec(f"fused/{_r}/confidence", "float32", "(S, n, n)", "0..1", _f, "NaN", "max confidence in the window", codec="lz4"),
        ArraySpec(f"fused/{_r}/risk", "float32", "(S, n, n)", "0..1", _f, "NaN", "latest risk with confidence >= risk_min_conf", codec="lz4"),
        ArraySpec(f"fused/{_r}/count", "uint16", "(S, n, n)", "maps", _f, "0", "observations averaged into the elevation (rule ground: the ground ones where there are any)"),
        ArraySpec(f"fused/{_r}/last_dt_s", "float32", "(S, n, n)", "s, rel. t", _f, "NaN", "stamp of the last observation minus t", codec="lz4"),
        ArraySpec(f"fused/{_r}/region", "uint8", "(S, n, n)", "code", _f, "0", "1 observed past/current, 2 observed future, 3 unobserved"),
        ArraySpec(f"xracer/{_r}/elevation_m", "float32", "(S, n, n)", "m, rel. base z at t", _f, "NaN", "X-Racer map at t (latest stamped <= t), resampled", codec="lz4"),
        ArraySpec(f"xracer/{_r}/risk", "float32", "(S, n, n)", "0..1", _f, "NaN", "X-Racer risk at t", codec="lz4"),
        ArraySpec(f"xracer/{_r}/confidence", "float32", "(S, n, n)", "0..1", _f, "NaN", "X-Racer confidence at t", codec="lz4"),
    ]
FUSED = StoreFormat("gtgen-fused", 4, tuple(_FUSED), "gtgen fuse",
                    "re-run 'gtgen fuse DRIVE --overwrite' (version 4 computes and stores the QA-only grids only for "
                    "shards.qa_ranges)",
                    config_sections=("grids", "topics", "extract", "mapping", "fuse"))


# -- the dataset (``gtgen dem-align``, ``gtgen build``) ---------------------------------
SAMPLES_PER_SHARD = 16
POINTS_PER_CHUNK = 1 << 17

_TGT = "target (vehicle, gravity-aligned, at t)"

_DATASET: list[ArraySpec] = []
for _r in RANGES:
    _n = "n_m" if _r == "micro" else "n_s"
    _DATASET += [
        ArraySpec(f"labels/{_r}/elevation_m", "int32", f"(S, {_n}, {_n})", "m, rel. base z at t", _TGT, "NaN", "fused elevation (regions 1, 2), aligned DEM (region 3)", "elevation_m"),
        ArraySpec(f"labels/{_r}/risk", "uint16", f"(S, {_n}, {_n})", "0..1", _TGT, "NaN", "latest confident X-Racer risk in the window", "fraction"),
        ArraySpec(f"labels/{_r}/confidence", "uint16", f"(S, {_n}, {_n})", "0..1", _TGT, "NaN", "max X-Racer confidence in the window", "fraction"),
        ArraySpec(f"labels/{_r}/region", "uint8", f"(S, {_n}, {_n})", "code", _TGT, "0", "0 no label, 1 observed past/current, 2 observed future, 3 unobserved (DEM)"),
        ArraySpec(f"labels/{_r}/count", "uint16", f"(S, {_n}, {_n})", "maps", _TGT, "0", "observations averaged into the elevation (rule ground: the ground ones where there are any)"),
        ArraySpec(f"labels/{_r}/last_dt_s", "int32", f"(S, {_n}, {_n})", "s, rel. t", _TGT, "NaN", "time of the last observation minus t", "time_s"),
        ArraySpec(f"xracer/{_r}/elevation_m", "int32", f"(S, {_n}, {_n})", "m, rel. base z at t", _TGT, "NaN", "X-Racer map at t (the baseline row)", "elevation_m"),
        ArraySpec(f"xracer/{_r}/risk", "uint16", f"(S, {_n}, {_n})", "0..1", _TGT, "NaN", "X-Racer risk at t", "fraction"),
        ArraySpec(f"xracer/{_r}/confidence", "uint16", f"(S, {_n}, {_n})", "0..1", _TGT, "NaN", "X-Racer confidence at t", "fraction"),
        ArraySpec(f"dem/{_r}/elevation_m", "int32", f"(S, {_n}, {_n})", "m, rel. base z at t", _TGT, "NaN", "aligned DEM, bilinear", "dem_m"),
    ]
_DATASET += [
    ArraySpec("inputs/jpeg", "uint8", "(S, C, B)", "JPEG file", "camera (rectified)", "0", "only with cameras: each camera's JPEG file in bytes [0, jpeg_nbytes), zeros after (see Images), in the order of the attribute 'cameras'"),
    ArraySpec("inputs/jpeg_nbytes", "int32", "(S, C)", "bytes", "-", "0", "only with cameras: length of each stored JPEG file"),
    ArraySpec("inputs/K", "float64", "(S, C, 3, 3)", "px", "camera (rectified)", "0", "only with cameras: intrinsics of the stored (rectified) image, at the size its JPEG header gives"),
    ArraySpec("inputs/T_base_cam", "float64", "(S, C, 4, 4)", "m", "base <- camera optical", "0", "only with cameras: camera extrinsics"),
    ArraySpec("inputs/T_target_base", "float64", "(S, 4, 4)", "m", "target <- base", "0", "the base's roll and pitch in the target frame"),
    ArraySpec("inputs/raw_elevation_m", "int32", "(S, n_s, n_s)", "m, rel. base z at t", _TGT, "NaN", "lowest voxel-map point per short cell", "points_m"),
    ArraySpec("inputs/voxel_offsets", "int64", "(S + 1,)", "-", "-", "0", "sample s owns voxel_points_m[offsets[s]:offsets[s+1]]"),
    ArraySpec("inputs/voxel_points_m", "int32", "(P, 3)", "m", _TGT, "NaN", "voxel map points, flat", "points_m"),
    ArraySpec("inputs/scan_points_m", "int32", "(S, P_s, 3)", "m", _TGT, "NaN", "only with raw scans: the N-scan input, the last N_s scans of every lidar at least shards.scan_travel_m apart within the short grid, voxel-filtered (first point per shards.scan_voxel_m voxel, newest scan first), in that order; the newest P_s kept", "points_m"),
    ArraySpec("inputs/scan_counts", "int32", "(S, N_s)", "-", "-", "0", "only with raw scans: points of the scans of age < a + 1 (a prefix of scan_points_m); the filtered last n scans are rows [0, scan_counts[n - 1])"),
    ArraySpec("meta/t_ns", "int64", "(S,)", "ns", "-", "0", "sample time"),
    ArraySpec("meta/drive", "uint16", "(S,)", "-", "-", "0", "index into the attribute 'drives'"),
    ArraySpec("meta/pos_odom_m", "float64", "(S, 3)", "m", "odom", "0", "base position at t"),
    ArraySpec("meta/yaw_odom_rad", "float64", "(S,)", "rad", "odom", "0", "base yaw at t"),
    ArraySpec("meta/crs_en_m", "float64", "(S, 2)", "m", "DEM CRS", "0", "sample position (easting, northing) after ICP"),
    ArraySpec("meta/T_crs_target", "float64", "(S, 4, 4)", "m", "DEM CRS <- target", "0", "alignment after ICP (z: DEM heights)"),
    ArraySpec("meta/icp_fitness", "float32", "(S,)", "0..1", "-", "0", "share of source cells within dem.icp_max_distance_m; NaN: kept by odometry over set-aside tiles (dem.carry_over_m)"),
    ArraySpec("meta/icp_rmse_m", "float32", "(S,)", "m", "-", "0", "point-to-plane RMSE of the inliers; NaN: no ICP (as icp_fitness)"),
    ArraySpec("meta/icp_correction", "float32", "(S, 4)", "m, m, m, rad", _TGT, "0", "ICP correction dx, dy, dz, dyaw over the prior placement"),
    ArraySpec("meta/dem_disagreement", "float32", "(S,)", "0..1", "-", "0", "share of observed ground cells beyond dem.disagreement_m from the aligned DEM"),
    ArraySpec("meta/gnss_offset_m", "float32", "(S,)", "m", "DEM CRS", "NaN", "median distance of the window's GNSS fixes from the placed track (NaN: too few fixes)"),
    ArraySpec("meta/vegetation_share", "float32", "(S,)", "0..1", "-", "0", "share of observed cells left out of ICP as vegetation"),
    ArraySpec("meta/split", "uint8", "(S,)", "code", "-", "0", "0 train, 1 val (by geography block), 2 test (whole drives held out: split: test in the build manifest)"),
    ArraySpec("rejected/t_ns", "int64", "(R,)", "ns", "-", "0", "time of each rejected sample"),
    ArraySpec("rejected/drive", "uint16", "(R,)", "-", "-", "0", "drive of each rejected sample"),
    ArraySpec("rejected/reason", "uint8", "(R,)", "code", "-", "0", "why (gtgen.codes)"),
    ArraySpec("rejected/pos_odom_m", "float64", "(R, 3)", "m", "odom", "NaN", "base position at t"),
    ArraySpec("rejected/yaw_odom_rad", "float64", "(R,)", "rad", "odom", "NaN", "base yaw at t"),
    ArraySpec("rejected/icp_fitness", "float32", "(R,)", "0..1", "-", "NaN", "ICP fitness if ICP ran"),
    ArraySpec("rejected/icp_rmse_m", "float32", "(R,)", "m", "-", "NaN", "ICP RMSE if ICP ran"),
    ArraySpec("rejected/T_crs_target", "float64", "(R, 4, 4)", "m", "DEM CRS <- target", "NaN", "the placement ICP proposed (NaN if ICP did not run)"),
    ArraySpec("rejected/icp_correction", "float32", "(R, 4)", "m, m, m, rad", _TGT, "NaN", "ICP correction dx, dy, dz, dyaw over the prior"),
    ArraySpec("rejected/dem_disagreement", "float32", "(R,)", "0..1", "-", "NaN", "as meta/dem_disagreement"),
    ArraySpec("rejected/gnss_offset_m", "float32", "(R,)", "m", "DEM CRS", "NaN", "as meta/gnss_offset_m"),
    ArraySpec("rejected/vegetation_share", "float32", "(R,)", "0..1", "-", "NaN", "as meta/vegetation_share"),
]
# coordinates, so that xarray.open_zarr(dataset, group=...) labels the grids in metres and
# the samples by time: each group of per-sample grids holds its dimension coordinates
TIME_ATTRS = {"units": "nanoseconds since 1970-01-01", "calendar": "proleptic_gregorian", "standard_name": "time"}
COORDS: list[ArraySpec] = []
for _g, _n in [(f"{k}/{r}", "n_m" if r == "micro" else "n_s") for k in ("labels", "xracer", "dem") for r in RANGES] + [("inputs", "n_s")]:
    COORDS += [
        ArraySpec(f"{_g}/x_m", "float64", f"({_n},)", "m", _TGT, "-", "cell-centre x (forward) of grid axis 1, the dimension coordinate x_m"),
        ArraySpec(f"{_g}/y_m", "float64", f"({_n},)", "m", _TGT, "-", "cell-centre y (left) of grid axis 2, the dimension coordinate y_m"),
    ]
for _g in ("labels/micro", "labels/short", "xracer/micro", "xracer/short", "dem/micro", "dem/short", "inputs", "meta"):
    COORDS.append(ArraySpec(f"{_g}/sample", "int64", "(S,)", "ns since 1970 (CF)", "-", "-", "sample time (= meta/t_ns), the dimension coordinate sample"))
DATASET = StoreFormat("gtgen-dataset", 9, tuple(_DATASET + COORDS), "gtgen dem-align",
                      "rebuild it with 'gtgen dem-align --overwrite' (or 'gtgen build DRIVES... -o OUT --overwrite'): version 9 "
                      "stores grids and points as CF packed integers at the steps of shards.precision")

# the grids only quality checks read (gtgen viz, export, report's comparisons; never train
# or eval), stored only for the ranges in shards.qa_ranges (none by default): the DEM's
# heights where the label needs them are its region-3 cells already
QA_GRIDS = {"labels": ("confidence", "count", "last_dt_s"), "xracer": ("confidence",), "dem": ("elevation_m",)}


# what reads each per-sample grid and point array of a dataset (data_schema.md's packing table)
READ_BY = {
    "labels/{r}/elevation_m": "train, eval, report, viz, export", "labels/{r}/risk": "train, eval, report, viz, export",
    "labels/{r}/region": "train, eval, report, viz, export", "labels/{r}/confidence": "QA: viz, export mcap",
    "labels/{r}/count": "QA: export", "labels/{r}/last_dt_s": "QA: export", "xracer/{r}/elevation_m": "eval (X-Racer row), report, viz",
    "xracer/{r}/risk": "eval (X-Racer row), export mcap", "xracer/{r}/confidence": "QA: report (X-Racer's confident cells; else region 1), export mcap",
    "dem/{r}/elevation_m": "QA: viz, export (its heights the label needs are region 3's already)",
    "inputs/raw_elevation_m": "train (the raw and prior grids), eval (raw-grid rows)", "inputs/voxel_points_m": "train, eval, export mcap",
    "inputs/scan_points_m": "train (train.geometry: scans)",
}


def qa_paths(ranges: Any = RANGES, grids: dict[str, tuple[str, ...]] = QA_GRIDS) -> tuple[str, ...]:
    """Return the paths of the QA grids of ``ranges`` (of a dataset; ``grids=FUSED_QA``: of
    a fused store)."""
    return tuple(f"{k}/{r}/{layer}" for k, layers in grids.items() for r in ranges for layer in layers)


# the fused store's grids the dataset's QA grids come from (the fused labels are its
# "labels"): fuse computes and writes them only for shards.qa_ranges
FUSED_QA = {"fused": QA_GRIDS["labels"], "xracer": QA_GRIDS["xracer"]}


# the arrays with one row per sample (sharded along the sample axis); the N-scan input's
# are there only when the drives have raw scans, the images' only when they have cameras
SCAN_ARRAYS: tuple[ArraySpec, ...] = tuple(s for s in _DATASET if s.path.startswith("inputs/scan_"))
CAMERA_ARRAYS: tuple[ArraySpec, ...] = tuple(s for s in _DATASET if "C" in s.axes())
SAMPLE_ARRAYS: tuple[ArraySpec, ...] = tuple(s for s in _DATASET if not s.path.startswith(("rejected/", "inputs/voxel_", "inputs/scan_"))
                                             and s not in CAMERA_ARRAYS)

FORMATS = {f.kind: f for f in (DRIVE, FUSED, DATASET)}


class BagRef(BaseModel):
    """A bag a drive was read from, and its sha256."""

    model_config = ConfigDict(extra="forbid")
    path: str
    sha256: str


class TileEntry(BaseModel):
    """What dem-align measured and decided of one DEM tile near a drive (``gtgen.dem.judge.TileJudgement``)."""

    model_config = ConfigDict(extra="forbid")
    path: str = Field(description="the tile (GDAL path)")
    status: str = Field(description="ok (used as it is), corrected (read put back by applied_m), set_aside (not used), unjudged (no "
                                    "neighbour to judge it by: used as it is unless its observed ground disagrees)")
    reason: str = Field("", description="why it was corrected, set aside or left unjudged")
    border_pixels: int = Field(0, description="pixels along its borders with a neighbour (0: none; both horizontal axes are observed "
                                              "only with neighbours on two sides at right angles)")
    border_step_m: float | None = Field(None, description="spread of the height steps across its borders with its neighbours as its file "
                                                          "places it [m] (the DEM's noise where it belongs)")
    border_step_put_back_m: float | None = Field(None, description="the same, read put back by offset_m [m]; above dem.max_border_step_m "
                                                                   "no offset continues its neighbours and it is set aside")
    offset_m: list[float | None] = Field(description="(dx, dy, dz) that makes it continue its neighbours best [m, working CRS]: the tile "
                                                     "shows at (E + dx, N + dy) the ground of (E, N), dz higher (null: not measured)")
    sigma_m: list[float | None] = Field(description="1-sigma uncertainty of offset_m per axis [m]: half the reach of the offsets that "
                                                    "continue the neighbours as well within the steps' noise (large along smooth borders)")
    applied_m: list[float] = Field(description="the offset the tile is read put back by [m] (zeros unless corrected)")
    ground_cells: int = Field(0, description="observed ground cells over it at the drive's placements")
    ground_disagreement: float | None = Field(None, description="share of those that disagree with it by more than dem.disagreement_m")


class DriveEntry(BaseModel):
    """One drive of a dataset: where it came from and how it was placed in the DEM's CRS."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field(description="drive name (the build's unit; the drive store's folder for dem-align)")
    drive_store: str = Field(description="the drive store the samples were built from")
    bags: list[BagRef]
    crs: str = Field(description="working CRS of the drive's DEM placement (meta/T_crs_target, meta/crs_en_m)")
    alignment: dict[str, float | int] = Field(description="GNSS fit and vertical offset of the drive")
    suspect_tiles: list[str] = Field(default_factory=list, description="DEM tiles judged wrong against the drive's observations: not used for filling")
    tiles: list[TileEntry] = Field(default_factory=list, description="every DEM tile the drive measured or judged: offset, uncertainty, status")


class DatasetAttrs(BaseModel):
    """The attributes of a dataset store: written by ``gtgen dem-align`` and ``gtgen build``
    through this one model."""

    model_config = ConfigDict(extra="forbid")
    store: str = DATASET.kind
    version: int = DATASET.version
    complete: bool = True
    gtgen_version: str
    config: dict[str, Any] = Field(description="the resolved config the dataset was built with")
    drives: list[DriveEntry] = Field(description="meta/drive indexes this list")
    reasons: dict[str, str] = Field(default_factory=lambda: {str(k): v for k, v in codes.REASONS.items()})
    regions: dict[str, str] = Field(default_factory=lambda: {str(k): v for k, v in codes.REGIONS.items()})
    splits: dict[str, str] = Field(default_factory=lambda: {str(k): v for k, v in codes.SPLITS.items()})
    image_size: tuple[int, int] = Field(description="the box stored images fit in: extract.image_width, image_height [px] (each JPEG's header gives its own size)")
    cameras: list[str]
    provenance: dict[str, Any] | None = Field(None, description="dependency versions and per-drive timings (gtgen build)")
