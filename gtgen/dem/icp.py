"""Point-to-plane ICP restricted to x, y, z and yaw (gravity stays down).

Correspondences come from open3d's nearest-neighbour search (built once per target,
queried in Z-order of the source so that neighbouring queries walk the same tree
branches); each iteration solves the linearised 4-DoF point-to-plane least squares in
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


def _nns(points: NDArray):
    import open3d.core as o3c

    nns = o3c.nns.NearestNeighborSearch(o3c.Tensor(np.ascontiguousarray(points, dtype=np.float64)))
    nns.knn_index()
    return nns


def _query(nns, q: NDArray) -> tuple[NDArray, NDArray]:
    import open3d.core as o3c

    idx, d2 = nns.knn_search(o3c.Tensor(np.ascontiguousarray(q, dtype=np.float64)), 1)
    return idx.numpy().ravel().astype(np.int64), np.sqrt(d2.numpy().ravel())


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
    source: NDArray, target: NDArray, normals: NDArray, max_distance: float, iterations: int, init: NDArray | None = None
) -> IcpResult:
    """Return the x, y, z, yaw transform that aligns ``source`` (N, 3) to ``target`` (M, 3)."""
    if len(source) == 0 or len(target) == 0:
        return IcpResult(np.eye(4), 0.0, float("inf"), 0, len(source))
    nns = _nns(target)
    source = source[_z_order(source, max_distance)]  # the result does not depend on the order
    x = np.zeros(4)  # yaw, tx, ty, tz
    if init is not None:
        x = np.array([np.arctan2(init[1, 0], init[0, 0]), init[0, 3], init[1, 3], init[2, 3]])
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 - the count of iterations run is read after the loop
        T = yaw_transform(x[1], x[2], x[3], x[0])
        p = source @ T[:3, :3].T + T[:3, 3]
        idx, d = _query(nns, p)
        inl = d < max_distance
        if inl.sum() < 6:
            break
        q, n, pp = target[idx[inl]], normals[idx[inl]], p[inl]
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
    idx, d = _query(nns, p)
    inl = d < max_distance
    fitness = float(inl.mean())
    if inl.any():
        r = np.einsum("ij,ij->i", normals[idx[inl]], p[inl] - target[idx[inl]])
        rmse = float(np.sqrt(np.mean(r**2)))
    else:
        rmse = float("inf")
    return IcpResult(T, fitness, rmse, it, len(source))
