"""The paper's N-scan input of a sample (Tab. III): its last scans, accumulated and voxel-filtered.

Per lidar, a sample's scans are its newest (the latest stamped at or before t, at most
``extract.scan_skew_s`` or two of the lidar's periods before it: ``newest_within_ns``), then repeatedly the latest stamped where the travel
was at least ``shards.scan_travel_m`` less than at the previous one chosen, up to
``shards.max_scans``; age a is the a-th of that chain. Their points are put in the
sample's target frame, kept within the short grid, ordered by (age, lidar, point), and
filtered to the first point of each ``shards.scan_voxel_m`` voxel. First-per-voxel in
that order makes the last n scans' filtered input a prefix of the stored one (a voxel's
point comes from the newest scan that has it), so ``inputs/scan_counts[n - 1]`` points
are exactly the filtered last n scans and one stored input serves every n.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.config import GtgenConfig
from gtgen.extract.lidar import expand, newest_within_ns
from gtgen.geometry import yaw_transform
from gtgen.storage.drive import DriveStore, Scans


def chains(scans: Scans, t_ns: NDArray[np.int64], n: int, travel_m: float, skew_ns: int) -> NDArray[np.int64]:
    """Return (S, n, K): per sample, age and lidar (the K lidars of ``scans``, in order) the
    index into ``scans`` of the scan used, -1 where there is none."""
    lidars = np.unique(scans.lidar)
    out = np.full((len(t_ns), n, len(lidars)), -1, np.int64)
    for j, lid in enumerate(lidars):
        idx = np.nonzero(scans.lidar == lid)[0]
        t, d = scans.t_ns[idx], scans.distance_m[idx]
        cur = np.searchsorted(t, t_ns, side="right") - 1
        ok = (cur >= 0) & (t_ns - t[np.maximum(cur, 0)] <= newest_within_ns(t, skew_ns))
        for a in range(n):  # a loop over ages (a few), vectorised over samples
            out[ok, a, j] = idx[cur[ok]]
            nxt = np.minimum(np.searchsorted(d, d[np.maximum(cur, 0)] - travel_m, side="right") - 1, cur - 1)
            ok &= nxt >= 0
            cur = nxt
    return out


def _voxel_keys(pts: NDArray, voxel_m: float) -> NDArray[np.int64]:
    ijk = np.floor(pts / voxel_m).astype(np.int64) + (1 << 20)  # 21 bits per axis
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def first_per_voxel(pts: NDArray, voxel_m: float) -> NDArray[np.int64]:
    """Return the indices, in order, of the first point of each ``voxel_m`` voxel (a hash
    of the voxel keys: no sort; 2-5x ``first_per_voxel_naive``, its oracle)."""
    import pandas as pd

    return np.flatnonzero(~pd.Series(_voxel_keys(pts, voxel_m)).duplicated(keep="first").to_numpy()).astype(np.int64)


def first_per_voxel_naive(pts: NDArray, voxel_m: float) -> NDArray[np.int64]:
    """:func:`first_per_voxel` by sorting the keys (``np.unique``): the test oracle."""
    return np.sort(np.unique(_voxel_keys(pts, voxel_m), return_index=True)[1])


class ScanInput:
    """Builds the N-scan inputs of a block of samples of one drive (its scans read once)."""

    def __init__(self, drive: DriveStore, cfg: GtgenConfig, ks: NDArray[np.int64]) -> None:
        self.cfg = cfg
        self.scans = drive.scans
        s = drive.samples
        self.chain = chains(self.scans, s.t_ns[ks], cfg.shards.max_scans, cfg.shards.scan_travel_m, int(cfg.extract.scan_skew_s * 1e9))
        self.used = np.unique(self.chain[self.chain >= 0])
        self.rows = drive.scan_rows(self.used) if len(self.used) else np.zeros((0, 1, 3), np.int16)
        # the scans' points in odom, each made once per block: a scan serves about eight
        # samples' chains (in the default drive's blocks, 1785 uses of 216 scans)
        self._odom: dict[int, NDArray[np.float64]] = {}

    def odom_points(self, i: int) -> NDArray[np.float64]:
        """Return scan ``i``'s points in odom (N, 3), made on first use and kept for the block."""
        p = self._odom.get(i)
        if p is None:
            T = self.scans.T_odom_sensor[i]
            p = self._odom[i] = expand(self.rows[np.searchsorted(self.used, i)], int(self.scans.n_points[i])) @ T[:3, :3].T + T[:3, 3]
        return p

    def sample(self, j: int, pos: NDArray, yaw: float) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """Return the N-scan input of the block's sample ``j`` (base position ``pos`` and yaw in
        odom at t): points (P_s, 3) in the target frame, NaN after the last, and the points
        of the scans of age < a + 1 (N_s,)."""
        sh = self.cfg.shards
        R_odom_target = yaw_transform(0, 0, 0, yaw)[:3, :3]
        parts, ages = [], []
        for a, row in enumerate(self.chain[j]):
            for i in row[row >= 0]:
                p = self.odom_points(int(i))
                parts.append((p - pos) @ R_odom_target)
                ages.append(np.full(len(p), a, np.int64))
        pts = np.concatenate(parts) if parts else np.zeros((0, 3))
        age = np.concatenate(ages) if ages else np.zeros(0, np.int64)
        half = 0.5 * self.cfg.grids.short.length_m
        inside = (np.abs(pts[:, 0]) < half) & (np.abs(pts[:, 1]) < half)
        pts, age = np.compress(inside, pts, axis=0), age[inside]
        keep = first_per_voxel(pts, sh.scan_voxel_m)[: sh.max_scan_points]
        out = np.full((sh.max_scan_points, 3), np.nan, np.float32)
        out[: len(keep)] = np.take(pts, keep, axis=0)
        return out, np.searchsorted(age[keep], np.arange(sh.max_scans), side="right").astype(np.int32)
