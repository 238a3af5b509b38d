"""Raw lidar scans in the drive store: compact rows, motion correction, which scans to keep.

A scan is stored in its sensor's frame at its header stamp, as int16 centimetres (6 bytes
a point before zstd; +-327 m), in one chunk per scan padded with ``FILL`` to
``extract.max_scan_points`` (the padding compresses to almost nothing), with the pose of
its rows' origin in odom at the stamp beside it (the sensor's, or for a cloud published
far from its frame's origin that frame shifted to the cloud's median, see ``compact``). A cloud with a per-point time field is first
motion-corrected (deskewed): each point is moved into the sensor frame at the stamp
through the sensor's motion between the stamp and its time (TF, in ``DESKEW_BINS`` time
bins over the sweep). Extract keeps, per lidar, every scan at least ``shards.scan_travel_m``
of travel after the previous one kept, and each sample's newest scan (the N-scan input of
a sample is built from these, see ``gtgen.dataset.scans``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.tf import TfBuffer
from gtgen.geometry import all_columns, finite_rows, invert

CM = 0.01  # stored unit [m]
FILL = -32768  # int16 fill of the rows past a scan's points
LIMIT_M = 327.0  # points farther from the sensor on any axis are not stored [m]
DESKEW_BINS = 32  # time bins of a sweep for the motion correction


def compact(pts: NDArray[np.float32], n: int) -> tuple[NDArray[np.int16], int, NDArray[np.float64]]:
    """Return a scan (N, 3) in its frame [m] as one padded row (n, 3) of int16 cm, its point
    count and the shift of the row's origin in that frame [m]: 0, or for a cloud not
    centred on its frame's origin (one published in a map frame) its median point to the
    cm. Kept: the finite points within ``LIMIT_M`` of that origin, at most the ``n`` nearest."""
    pts = finite_rows(pts)
    shift = np.zeros(3)
    if len(pts) and np.abs(pts).max() >= LIMIT_M:
        shift = np.round(np.median(pts, axis=0).astype(np.float64), 2)
    p = pts - shift
    p = np.compress(all_columns(np.abs(p) < LIMIT_M), p, axis=0)
    if len(p) > n:
        r2 = np.einsum("ij,ij->i", p, p)
        p = p[np.sort(np.argpartition(r2, n - 1)[:n])]
    out = np.full((n, 3), FILL, np.int16)
    out[: len(p)] = np.round(p / CM).astype(np.int16)
    return out, len(p), shift


def expand(rows: NDArray[np.int16], n_points: int) -> NDArray[np.float64]:
    """Return the first ``n_points`` of a stored scan row as metres (n_points, 3)."""
    return rows[:n_points].astype(np.float64) * CM


def deskew(pts: NDArray[np.float32], dt_s: NDArray[np.float32], tf: TfBuffer, odom: str, frame: str, t_ns: int) -> NDArray[np.float32]:
    """Return the points of a sweep, each measured at stamp + ``dt_s`` in ``frame``, in
    ``frame`` at the stamp ``t_ns``: p' = T_odom_sensor(t)^-1 T_odom_sensor(t + dt) p,
    with T taken at ``DESKEW_BINS`` times over the sweep (points left as they are where
    TF does not know the motion)."""
    if len(pts) == 0 or float(np.ptp(dt_s)) == 0.0:
        return pts
    lo, hi = float(dt_s.min()), float(dt_s.max())
    edges = np.linspace(lo, hi, DESKEW_BINS + 1)
    b = np.clip(np.searchsorted(edges, dt_s, side="right") - 1, 0, DESKEW_BINS - 1)
    mid = 0.5 * (edges[:-1] + edges[1:])
    T, ok = tf.lookup(odom, frame, np.concatenate([[t_ns], t_ns + np.round(mid * 1e9).astype(np.int64)]))
    if not ok[0]:
        return pts
    rel = invert(T[0]) @ T[1:]
    rel[~ok[1:]] = np.eye(4)
    R, tr = rel[b, :3, :3], rel[b, :3, 3]
    return (np.einsum("nij,nj->ni", R, pts.astype(np.float64)) + tr).astype(np.float32)


def newest_within_ns(t: NDArray[np.int64], skew_ns: int) -> int:
    """Return how old a sample's newest scan of one lidar (stamps ``t``, sorted) may be:
    ``extract.scan_skew_s``, or two of the lidar's periods (median) if that is longer, so
    that a lidar slower than the skew still gives every sample its latest scan while a
    lidar that stopped gives none."""
    return max(int(skew_ns), int(2 * np.median(np.diff(t)))) if len(t) > 1 else int(skew_ns)


def kept_scans(t: NDArray[np.int64], dist: NDArray[np.float64], sample_t: NDArray[np.int64], travel_m: float,
               skew_ns: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Return (indices into ``t`` of the scans one lidar keeps, sorted; each sample's newest
    scan as an index into them, -1 where none is within ``newest_within_ns`` before it).

    ``t`` are the lidar's usable stamps, sorted, ``dist`` the travel at each [m]. Kept: the
    first scan, every scan at least ``travel_m`` after the previous one kept, and each
    sample's newest scan (the latest stamped at or before the sample)."""
    keep = np.zeros(len(t), bool)
    last = -np.inf
    for i, d in enumerate(dist):  # a loop over scans (a few per metre), not over points
        if d - last >= travel_m:
            keep[i] = True
            last = d
    newest = np.searchsorted(t, sample_t, side="right") - 1
    ok = (newest >= 0) & (sample_t - t[np.maximum(newest, 0)] <= newest_within_ns(t, skew_ns)) if len(t) else np.zeros(len(sample_t), bool)
    keep[newest[ok]] = True
    idx = np.nonzero(keep)[0]
    return idx, np.where(ok, np.searchsorted(idx, np.maximum(newest, 0)), -1)
