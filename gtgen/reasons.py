"""Per-sample rejection reason codes, shared by every stage (uint8 on disk)."""

from __future__ import annotations

OK = 0
NO_POSE = 1
NO_MAP_MICRO = 2
NO_MAP_SHORT = 3
NO_VOXEL = 4
NO_IMAGE = 5
NO_FUSED_MAPS = 10
NO_DEM = 20
LOW_FITNESS = 21
HIGH_RMSE = 22
TOO_FEW_POINTS = 23
NO_ALIGNMENT = 24

REASONS: dict[int, str] = {
    OK: "ok",
    NO_POSE: "no_pose: odometry does not cover the time within pose_tolerance_s",
    NO_MAP_MICRO: "no_map_micro: no micro GridMap within map_skew_s",
    NO_MAP_SHORT: "no_map_short: no short GridMap within map_skew_s",
    NO_VOXEL: "no_voxel: no voxel map within voxel_skew_s",
    NO_IMAGE: "no_image: a camera has no image within image_skew_s",
    NO_FUSED_MAPS: "no_fused_maps: no confident map cell in the fusion window",
    NO_DEM: "no_dem: the DEM has no valid cells under the sample",
    LOW_FITNESS: "low_fitness: ICP fitness below dem.min_fitness",
    HIGH_RMSE: "high_rmse: ICP inlier RMSE above dem.max_rmse_m",
    TOO_FEW_POINTS: "too_few_points: too few observed cells to align the DEM",
    NO_ALIGNMENT: "no_alignment: the drive could not be placed in the DEM CRS",
}


def name(code: int) -> str:
    """Return the short name of reason ``code``."""
    return REASONS.get(int(code), f"unknown_{int(code)}").split(":")[0]
