"""Point-to-plane ICP restricted to x, y, z and yaw (gravity stays down).

Correspondences are each source point's nearest target point within the correspondence
distance: from open3d's nearest-neighbour search for any target (``KdNearest``, built
once per target, queried in Z-order of the source so that neighbouring queries walk the
same tree branches), or, for a target that is a height field on a regular grid (a DEM
patch: ``GridNearest``), from the few cells a side whose centres can lie that close, with
no tree to build (the same neighbours: tests/test_dem.py holds it to ``KdNearest``). Each
iteration solves the linearised 4-DoF point-to-plane least squares in
closed form. Fitness is the share of source points with a target point within
``max_distance``; the inlier RMSE is point-to-plane over those points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen.geometry import yaw_transform


@dataclass(frozen=True)
class IcpResult:
    """The correction T (4x4, target <- source), fitness [0..1], inlier RMSE [m], iterations."""

    T: NDArray[np.float64]
    fitness: float
    rmse_m: float
    iterations: int
    n_source: int


class KdNearest:
    """Nearest target points of any point set (open3d's KD-tree, built on first use)."""

    def __init__(self, points: NDArray) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self._nns = None

    def query(self, q: NDArray, max_distance: float) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Return each query point's nearest target point (index) and its distance [m]
        (``max_distance`` is not used: every point gets its nearest)."""
        import open3d.core as o3c

        if self._nns is None:
            self._nns = o3c.nns.NearestNeighborSearch(o3c.Tensor(self.points))
            self._nns.knn_index()
        idx, d2 = self._nns.knn_search(o3c.Tensor(np.ascontiguousarray(q, dtype=np.float64)), 1)
        return idx.numpy().ravel().astype(np.int64), np.sqrt(d2.numpy().ravel())


class GridNearest:
    """Nearest target points of a height field: heights ``Z`` (nx, ny) at cell centres
    ``x`` (nx) by ``y`` (ny) on a regular grid, NaN where there is none. The target points
    are the finite cells in C order (``column_stack([X[ok], Y[ok], Z[ok]])`` with X, Y of
    ``meshgrid(x, y, indexing="ij")``). A query looks at the cells whose centres can lie
    within ``max_distance`` of it (3 x 3 at 1 m on a 0.8 m grid): exact within it, distance
    inf beyond; wide radii go to a KD-tree of the same points."""

    MAX_WINDOW = 4  # cells a side; wider windows cost more than the tree

    def __init__(self, x: NDArray, y: NDArray, Z: NDArray) -> None:
        self.x, self.y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        self.res = float(self.x[1] - self.x[0])
        ok = np.isfinite(Z)
        self.Z = np.where(ok, Z, np.inf).astype(np.float64)  # inf: never the nearest
        self.rank = np.cumsum(ok.ravel()) - 1  # cell (C order) -> target point
        X, Y = np.meshgrid(self.x, self.y, indexing="ij")
        self.points = np.column_stack([X[ok], Y[ok], Z[ok]])
        self._kd: KdNearest | None = None

    def query(self, q: NDArray, max_distance: float) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Return each query point's nearest target point within ``max_distance`` (index)
        and its distance [m], inf where there is none that close (index then meaningless)."""
        w = int(np.floor(2 * max_distance / self.res)) + 1
        if w > self.MAX_WINDOW:
            self._kd = self._kd or KdNearest(self.points)
            return self._kd.query(q, max_distance)
        nx, ny = self.Z.shape
        i0 = np.ceil((q[:, 0] - max_distance - self.x[0]) / self.res).astype(np.int64)
        j0 = np.ceil((q[:, 1] - max_distance - self.y[0]) / self.res).astype(np.int64)
        best, cell = np.full(len(q), np.inf), np.zeros(len(q), np.int64)
        for di in range(w):  # a loop over the window's offsets; each step is vectorised over the points
            i = i0 + di
            vi = (i >= 0) & (i < nx)
            i = np.clip(i, 0, nx - 1)
            dx2 = (self.x[i] - q[:, 0]) ** 2
            for dj in range(w):
                j = j0 + dj
                v = vi & (j >= 0) & (j < ny)
                j = np.clip(j, 0, ny - 1)
                d2 = dx2 + (self.y[j] - q[:, 1]) ** 2 + (self.Z[i, j] - q[:, 2]) ** 2
                better = v & (d2 < best)
                np.copyto(best, d2, where=better)  # copyto, not best[better] =: a third of the time
                np.copyto(cell, i * ny + j, where=better)
        return np.maximum(self.rank[cell], 0), np.sqrt(best)


def _z_order(points: NDArray, cell_m: float) -> NDArray[np.intp]:
    """Return the permutation that puts ``points`` (N, 3) in Z (Morton) order of their
    x, y cells of ``cell_m``."""
    q = np.floor(points[:, :2] / cell_m).astype(np.int64)
    q = (q - q.min(axis=0)).astype(np.uint64) & np.uint64(0xFFFF)  # 65 536 cells a side; beyond, only the order suffers

    def spread(v: NDArray) -> NDArray:  # put a zero bit between the 16 bits of v
        for shift, mask in ((8, 0x00FF00FF), (4, 0x0F0F0F0F), (2, 0x33333333), (1, 0x55555555)):
            v = (v | (v << np.uint64(shift))) & np.uint64(mask)
        return v

    return np.argsort(spread(q[:, 0]) | (spread(q[:, 1]) << np.uint64(1)), kind="stable")


def icp_4dof(
    source: NDArray, target: NDArray, normals: NDArray, max_distance: float, iterations: int, init: NDArray | None = None,
    nearest: KdNearest | GridNearest | None = None,
) -> IcpResult:
    """Return the x, y, z, yaw transform that aligns ``source`` (N, 3) to ``target`` (M, 3);
    ``nearest``, a search over ``target`` (default a ``KdNearest`` of it)."""
    if len(source) == 0 or len(target) == 0:
        return IcpResult(np.eye(4), 0.0, float("inf"), 0, len(source))
    nns = nearest if nearest is not None else KdNearest(target)
    source = np.take(source, _z_order(source, max_distance), axis=0)  # the result does not depend on the order
    x = np.zeros(4)  # yaw, tx, ty, tz
    if init is not None:
        x = np.array([np.arctan2(init[1, 0], init[0, 0]), init[0, 3], init[1, 3], init[2, 3]])
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 - the count of iterations run is read after the loop
        T = yaw_transform(x[1], x[2], x[3], x[0])
        p = source @ T[:3, :3].T + T[:3, 3]
        idx, d = nns.query(p, max_distance)
        inl = d < max_distance
        if inl.sum() < 6:
            break
        # take and compress: NumPy's fancy and boolean indexing of (N, 3) rows cost four times as much
        near = np.compress(inl, idx)
        q, n, pp = np.take(target, near, axis=0), np.take(normals, near, axis=0), np.compress(inl, p, axis=0)
        r = np.einsum("ij,ij->i", n, pp - q)
        # d(residual)/d(yaw) about the origin, then the three translations
        J = np.column_stack([n[:, 1] * pp[:, 0] - n[:, 0] * pp[:, 1], n[:, 0], n[:, 1], n[:, 2]])
        # a Huber-like weight keeps a few bad cells from dragging the solution
        w = 1.0 / np.maximum(1.0, np.abs(r) / 0.3)
        A = J.T @ (J * w[:, None]) + 1e-9 * np.eye(4)
        dx = -np.linalg.solve(A, J.T @ (w * r))
        # compose the increment with the current transform
        c, s = np.cos(dx[0]), np.sin(dx[0])
        t = np.array([x[1], x[2]])
        t = np.array([c * t[0] - s * t[1], s * t[0] + c * t[1]]) + dx[1:3]
        x = np.array([x[0] + dx[0], t[0], t[1], x[3] + dx[3]])
        if np.abs(dx[0]) < 1e-6 and np.linalg.norm(dx[1:]) < 1e-4:
            break
    T = yaw_transform(x[1], x[2], x[3], x[0])
    p = source @ T[:3, :3].T + T[:3, 3]
    idx, d = nns.query(p, max_distance)
    inl = d < max_distance
    fitness = float(inl.mean())
    if inl.any():
        r = np.einsum("ij,ij->i", normals[idx[inl]], p[inl] - target[idx[inl]])
        rmse = float(np.sqrt(np.mean(r**2)))
    else:
        rmse = float("inf")
    return IcpResult(T, fitness, rmse, it, len(source))
