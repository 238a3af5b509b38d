"""Sample selection: candidate times every ``stride_m`` of travel, snapped to the reference
sensor (``extract.reference``: a camera, else the first lidar's scans), kept only where a
pose, both maps, the voxel map and every configured camera's image exist within their
skew tolerances; every rejected candidate gets a reason code. Also which maps are
kept (thinned to ``extract.map_rate_hz``, plus each sample's map at t) and which raw
scans (``extract.lidar.kept_scans``; they are optional: no sample is rejected for them)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.bag.poses import PoseTrack
from gtgen.config import GtgenConfig
from gtgen.extract.inventory import Scan
from gtgen.extract.lidar import kept_scans
from gtgen.extract.roles import reference_role
from gtgen.extract.stage import period_ns


def _nearest(stamps: NDArray, t: NDArray) -> tuple[NDArray, NDArray]:
    """Return (index, |skew| ns) of the stamp nearest each t; stamps sorted; -1 stamps ignored."""
    if len(stamps) == 0:
        return np.full(len(t), -1), np.full(len(t), np.iinfo(np.int64).max)
    i = np.clip(np.searchsorted(stamps, t), 1, len(stamps) - 1) if len(stamps) > 1 else np.zeros(len(t), np.int64)
    lo = np.maximum(i - 1, 0)
    d_lo = np.abs(t - stamps[lo])
    d_hi = np.abs(stamps[i] - t)
    best = np.where(d_lo <= d_hi, lo, i)
    return best, np.minimum(d_lo, d_hi)


def _sorted_valid(stamps: list[int]) -> tuple[NDArray, NDArray]:
    """Return (sorted valid stamps, their ordinal in the message stream)."""
    a = np.asarray(stamps, dtype=np.int64)
    ords = np.nonzero(a >= 0)[0]
    order = np.argsort(a[ords], kind="stable")
    return a[ords][order], ords[order]


@dataclass
class Plan:
    """The samples and what the store keeps for them (ordinals index each role's messages)."""

    t: NDArray  # (S,)
    cand_t: NDArray
    cand_reason: NDArray
    image_ord: NDArray  # (S, n_cameras) ordinal of the image message per camera (topics.cameras' order)
    image_t: NDArray
    voxel_t: NDArray  # (S,)
    voxel_index: NDArray  # (S,) index into the kept voxel maps
    voxel_ord: NDArray  # (V,) ordinals of the kept voxel maps, sorted by stamp
    voxel_map_t: NDArray  # (V,)
    map_ord: dict[str, NDArray]  # kept map ordinals per range, sorted by stamp
    map_t: dict[str, NDArray]
    sample_map: dict[str, NDArray]  # (S,) index into kept maps
    scan_ord: dict[str, NDArray]  # per lidar role, the kept raw scans' ordinals, sorted by stamp
    scan_t: dict[str, NDArray]  # their stamps
    scan_dist: dict[str, NDArray]  # the travel at each [m]
    cameras: list[str]  # the cameras of image_ord's columns

    def skews(self) -> dict[str, float]:
        """Return the largest and mean image and voxel-map skews to the sample times [s]."""
        if len(self.t) == 0:
            return {}
        img = np.abs(self.image_t - self.t[:, None]) * 1e-9
        vox = np.abs(self.voxel_t - self.t) * 1e-9
        out = {"image_max": round(float(img.max()), 4), "image_mean": round(float(img.mean()), 4)} if img.size else {}
        return {**out, "voxel_max": round(float(vox.max()), 4), "voxel_mean": round(float(vox.mean()), 4)}


def reference_stamps(cfg: GtgenConfig, scan: Scan) -> NDArray[np.int64]:
    """Return the usable stamps of the reference sensor (``GtgenConfig.reference``), sorted."""
    return _sorted_valid(scan.stamps[reference_role(cfg, (s.role for s in scan.stats.values()))])[0]


def _candidates(cfg: GtgenConfig, track: PoseTrack, scan: Scan) -> tuple[NDArray, NDArray]:
    """Return candidate times (the travel reaches each stride mark, snapped to the reference
    sensor so that its data are never interpolated) and their reasons (pose checked)."""
    dist = track.distance()
    marks = np.arange(0.0, dist[-1] + 1e-9, cfg.extract.stride_m) if len(dist) else np.zeros(0)
    cand = np.interp(marks, dist, track.t_ns.astype(np.float64)).astype(np.int64) if len(marks) else np.zeros(0, np.int64)
    cand = np.unique(cand)
    ref_t = reference_stamps(cfg, scan)
    fi, _ = _nearest(ref_t, cand)
    t = np.where(fi >= 0, ref_t[np.maximum(fi, 0)], cand) if len(ref_t) else cand
    t = np.unique(t)
    reason = np.zeros(len(t), np.uint8)
    reason[~track.covered(t)] = codes.NO_POSE
    return t, reason


def _images(cfg: GtgenConfig, scan: Scan, t: NDArray, reason: NDArray) -> tuple[NDArray, NDArray]:
    """Return each candidate's image ordinal and stamp per camera; mark NO_IMAGE."""
    n = len(cfg.topics.cameras)
    img_ord = np.full((len(t), n), -1, np.int64)
    img_t = np.zeros((len(t), n), np.int64)
    for c_i, c in enumerate(cfg.topics.camera_names):
        s, o = _sorted_valid(scan.stamps[f"camera.{c}"])
        i, d = _nearest(s, t)
        ok = (i >= 0) & (d <= int(cfg.extract.image_skew_s * 1e9))
        img_ord[:, c_i] = np.where(ok, o[np.maximum(i, 0)] if len(o) else -1, -1)
        img_t[:, c_i] = np.where(ok, s[np.maximum(i, 0)] if len(s) else 0, 0)
        reason[(reason == 0) & ~ok] = codes.NO_IMAGE
    return img_ord, img_t


def _maps_at(cfg: GtgenConfig, scan: Scan, t: NDArray, reason: NDArray) -> dict[str, tuple[NDArray, NDArray, NDArray]]:
    """Return per range (sorted valid map stamps, their ordinals, each candidate's map at t:
    the latest one stamped <= t, what the robot had then); mark NO_MAP_*."""
    out = {}
    for r, code in (("micro", codes.NO_MAP_MICRO), ("short", codes.NO_MAP_SHORT)):
        stamps = [m[0] if m[1] else -1 for m in scan.map_meta[f"map.{r}"]]
        ms, mo = _sorted_valid(stamps)
        mi = np.searchsorted(ms, t, side="right") - 1
        mok = (mi >= 0) & (t - ms[np.maximum(mi, 0)] <= int(cfg.extract.map_skew_s * 1e9)) if len(ms) else np.zeros(len(t), bool)
        reason[(reason == 0) & ~mok] = code
        out[r] = (ms, mo, np.where(mok, mi, 0))
    return out


def _kept_maps(period: int, ms: NDArray, mo: NDArray, mi: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Return (kept ordinals, their stamps, each sample's index into them): the earliest
    valid map of each period (a rule each slice can apply alone) and every sample's map."""
    bins = ms // period
    first_in_bin = np.nonzero(np.r_[True, bins[1:] != bins[:-1]])[0] if len(ms) else np.zeros(0, np.int64)
    ks = np.union1d(first_in_bin, mi).astype(np.int64)
    if not len(ks):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    return mo[ks], ms[ks], np.searchsorted(ks, mi)


def _scans(cfg: GtgenConfig, track: PoseTrack, scan: Scan, t: NDArray) -> tuple[dict[str, NDArray], ...]:
    """Return per lidar role the ordinals, stamps and travel of the raw scans kept for samples ``t``."""
    ords, stamps, dists = {}, {}, {}
    dist, tt = track.distance(), track.t_ns.astype(np.float64)
    for role in sorted(r for r in scan.stamps if r.startswith("lidar.")):
        s, o = _sorted_valid(scan.stamps[role])
        s, o = s[track.covered(s)], o[track.covered(s)]
        d = np.interp(s.astype(np.float64), tt, dist)
        idx, _ = kept_scans(s, d, t, cfg.shards.scan_travel_m, int(cfg.extract.scan_skew_s * 1e9))
        ords[role], stamps[role], dists[role] = o[idx], s[idx], d[idx]
    return ords, stamps, dists


def select(cfg: GtgenConfig, track: PoseTrack, scan: Scan) -> Plan:
    """Return the plan of a drive: its samples, their rejected candidates, what to keep."""
    t, reason = _candidates(cfg, track, scan)
    img_ord, img_t = _images(cfg, scan, t, reason)
    vs, vo = _sorted_valid(scan.stamps["voxel_map"])
    vi, vd = _nearest(vs, t)
    reason[(reason == 0) & ~((vi >= 0) & (vd <= int(cfg.extract.voxel_skew_s * 1e9)))] = codes.NO_VOXEL
    maps = _maps_at(cfg, scan, t, reason)
    keep = reason == codes.OK
    vk = np.unique(vi[keep])  # kept voxel maps, in stamp order
    kept = {r: _kept_maps(period_ns(cfg), ms, mo, mi[keep]) for r, (ms, mo, mi) in maps.items()}
    empty = np.zeros(0, np.int64)
    scan_ord, scan_t, scan_dist = _scans(cfg, track, scan, t[keep])
    return Plan(
        t=t[keep], cand_t=t, cand_reason=reason,
        image_ord=img_ord[keep], image_t=img_t[keep],
        voxel_t=vs[vi[keep]] if len(vs) else empty, voxel_index=np.searchsorted(vk, vi[keep]),
        voxel_ord=vo[vk] if len(vo) else empty, voxel_map_t=vs[vk] if len(vs) else empty,
        map_ord={r: k[0] for r, k in kept.items()}, map_t={r: k[1] for r, k in kept.items()},
        sample_map={r: k[2] for r, k in kept.items()}, scan_ord=scan_ord, scan_t=scan_t, scan_dist=scan_dist,
        cameras=cfg.topics.camera_names,
    )
