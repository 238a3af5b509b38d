"""A time-indexed pose track with linear + SLERP interpolation and no extrapolation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen.errors import PoseError
from gtgen.geometry import make_transform, quat_to_matrix, slerp


@dataclass
class PoseTrack:
    """Poses T_odom_base at strictly increasing times ``t_ns`` [ns]."""

    t_ns: NDArray[np.int64]
    pos: NDArray[np.float64]  # (N, 3) [m]
    quat: NDArray[np.float64]  # (N, 4) xyzw
    tolerance_ns: int = 100_000_000

    @classmethod
    def from_unsorted(cls, t_ns: NDArray, pos: NDArray, quat: NDArray, tolerance_ns: int) -> tuple[PoseTrack, int, int]:
        """Return the track sorted by stamp with duplicate stamps dropped, and the counts
        (out of order, duplicates) that were found."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        out_of_order = int(np.sum(np.diff(t_ns) < 0))
        order = np.argsort(t_ns, kind="stable")
        t_sorted = t_ns[order]
        keep = np.concatenate([[True], np.diff(t_sorted) > 0]) if len(t_sorted) else np.zeros(0, bool)
        dups = int(np.sum(~keep))
        sel = order[keep]
        return cls(t_ns[sel], np.asarray(pos, np.float64)[sel], np.asarray(quat, np.float64)[sel], tolerance_ns), out_of_order, dups

    def __len__(self) -> int:
        return len(self.t_ns)

    def covered(self, t_ns: NDArray) -> NDArray[np.bool_]:
        """Return whether each time lies within ``tolerance_ns`` of a pose on both sides,
        or within it of an end of the track (no extrapolation beyond the tolerance)."""
        t = np.asarray(t_ns, dtype=np.int64)
        if len(self.t_ns) == 0:
            return np.zeros(t.shape, bool)
        i = np.searchsorted(self.t_ns, t)
        lo = self.t_ns[np.clip(i - 1, 0, len(self.t_ns) - 1)]
        hi = self.t_ns[np.clip(i, 0, len(self.t_ns) - 1)]
        d_lo = np.where(i > 0, t - lo, np.iinfo(np.int64).max)
        d_hi = np.where(i < len(self.t_ns), hi - t, np.iinfo(np.int64).max)
        exact = (d_lo == 0) | (d_hi == 0)
        inside = (i > 0) & (i < len(self.t_ns)) & ((hi - lo) <= 2 * self.tolerance_ns)
        near_end = np.minimum(d_lo, d_hi) <= self.tolerance_ns
        return exact | inside | (near_end & ((i == 0) | (i == len(self.t_ns))))

    def interpolate(self, t_ns: NDArray, strict: bool = True) -> tuple[NDArray, NDArray]:
        """Return (pos (N, 3), quat (N, 4)) at times ``t_ns``; raise PoseError where not covered
        if ``strict`` (else those rows are NaN)."""
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        ok = self.covered(t)
        if strict and not ok.all():
            bad = t[~ok][0]
            raise PoseError(
                f"no pose at t={bad} ns: odometry covers [{self.t_ns[0] if len(self.t_ns) else 'none'}, "
                f"{self.t_ns[-1] if len(self.t_ns) else 'none'}] with gaps up to the tolerance {self.tolerance_ns / 1e9:.3f} s"
            )
        n = len(self.t_ns)
        i1 = np.clip(np.searchsorted(self.t_ns, t), 1, max(n - 1, 1))
        i0 = i1 - 1
        if n == 1:
            i0 = i1 = np.zeros_like(t)
        dt = (self.t_ns[i1] - self.t_ns[i0]).astype(np.float64)
        a = np.clip(np.where(dt > 0, (t - self.t_ns[i0]) / np.where(dt > 0, dt, 1), 0.0), 0.0, 1.0)
        pos = self.pos[i0] + (self.pos[i1] - self.pos[i0]) * a[:, None]
        quat = slerp(self.quat[i0], self.quat[i1], a)
        pos[~ok] = np.nan
        quat[~ok] = np.nan
        return pos, quat

    def transforms(self, t_ns: NDArray) -> NDArray[np.float64]:
        """Return T_odom_base (N, 4, 4) at times ``t_ns`` (strict)."""
        pos, quat = self.interpolate(t_ns)
        return make_transform(quat_to_matrix(quat), pos)

    def distance(self) -> NDArray[np.float64]:
        """Return the cumulative xy travel [m] at each pose."""
        step = np.linalg.norm(np.diff(self.pos[:, :2], axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(step)])
