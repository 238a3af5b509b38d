"""Named codes stored on disk as integers: per-sample rejection reasons, cell regions, splits.

Every stage and every reader uses these names; no bare code appears elsewhere. The
tables are also written into each store's attributes, so a store explains itself.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

# -- per-sample rejection reasons (uint8) ---------------------------------------------
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
LARGE_CORRECTION = 25
DEM_DISAGREES = 26
GNSS_DISAGREES = 27
SUSPECT_TILE = 28

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
    LARGE_CORRECTION: "large_correction: ICP moved the sample beyond dem.max_correction_* from its prior",
    DEM_DISAGREES: "dem_disagrees: more than dem.max_disagreement of the observed ground differs from the aligned DEM",
    GNSS_DISAGREES: "gnss_disagrees: the placement puts the window's GNSS fixes beyond dem.max_gnss_offset_m",
    SUSPECT_TILE: "suspect_tile: most of the sample lies on DEM tiles the drive's observations contradict (set aside)",
}


def reason_name(code: int) -> str:
    """Return the short name of rejection reason ``code``."""
    return REASONS.get(int(code), f"unknown_{int(code)}").split(":")[0]


def reason_counts(codes: NDArray) -> dict[str, int]:
    """Return {reason name: count} of the rejected entries (code != OK) of ``codes``."""
    u, c = np.unique(np.asarray(codes), return_counts=True)
    return {reason_name(k): int(v) for k, v in zip(u, c) if k != OK}


# -- cell regions (uint8), Sec. III-C of the paper ------------------------------------
NO_LABEL = 0  # no observation and no DEM
OBS_PC = 1  # observed past/current: confident in the latest map stamped <= t
OBS_F = 2  # observed future: confident only in maps of the window after t
UNOBS = 3  # unobserved: filled from the aligned DEM

REGIONS: dict[int, str] = {NO_LABEL: "no_label", OBS_PC: "obs_pc", OBS_F: "obs_f", UNOBS: "unobs"}
LABELLED = (OBS_PC, OBS_F, UNOBS)


def observed(region: NDArray) -> NDArray[np.bool_]:
    """Return where ``region`` holds an X-Racer observation (obs PC or obs F)."""
    return (region == OBS_PC) | (region == OBS_F)


# -- dataset splits (uint8): train / val by geography, test by whole drive ---------------
TRAIN = 0
VAL = 1
TEST = 2  # a drive held out whole (``split: test`` in the build manifest)
SPLITS: dict[int, str] = {TRAIN: "train", VAL: "val", TEST: "test"}


def split_code(name: str) -> int:
    """Return the code of split ``name`` ('train', 'val' or 'test')."""
    for code, n in SPLITS.items():
        if n == name:
            return code
    raise ValueError(f"split {name!r} unknown; expected one of {list(SPLITS.values())}")
