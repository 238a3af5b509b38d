"""Lift-Splat's BEV pooling without the lifted tensor.

Lifting gives every image pixel p of every camera n, at every depth bin d, the feature
``depth[n, d, p] * feat[n, p, :]``; pooling sums those into the BEV cell ``cell[n, d, p]``
lands in. Written out (``bev_pool_naive``, the tests' oracle) that is a tensor of
N x D x P x C floats (camera images x depth bins x feature pixels x channels): 4.2 GB at
the paper's sizes and batch 6, and as much again for its gradient. ``bev_pool`` computes
the same sums a few depth bins at a time, forward and backward (a custom autograd
Function), so that at most one chunk of ``chunk_mb`` exists at once; the role BEVFusion's
CUDA BEV pooling plays in the paper, in plain torch so it runs on any device.
"""

from __future__ import annotations

import torch


def add_rows(target: torch.Tensor, index: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Return ``target`` (n, C) with ``rows`` (m, C) added at the rows ``index`` (m,), in
    place: ``index_add_``, or while exporting to ONNX (whose exporter refuses a repeated index
    there) the equivalent ``scatter_add``."""
    if torch.onnx.is_in_onnx_export():
        return target.scatter_add(0, index[:, None].expand(-1, rows.shape[1]), rows)
    return target.index_add_(0, index, rows)


def bev_pool_naive(depth: torch.Tensor, feat: torch.Tensor, cell: torch.Tensor, n_cells: int) -> torch.Tensor:
    """Return (n_cells, C): the sums of ``depth`` (N, D, P) x ``feat`` (N, P, C) over the
    cells ``cell`` (N, D, P, int64; ``n_cells`` or more: outside the grid), through the
    whole lifted tensor (the oracle of ``bev_pool``)."""
    lifted = depth[..., None] * feat[:, None]
    ok = cell < n_cells
    return lifted.new_zeros(n_cells, feat.shape[-1]).index_add_(0, cell[ok], lifted[ok])


def _depth_chunk(depth: torch.Tensor, feat: torch.Tensor, chunk_mb: float) -> int:
    """Return how many depth bins one chunk of ``chunk_mb`` MiB holds (at least 1)."""
    per_bin = depth.shape[0] * depth.shape[2] * feat.shape[-1] * feat.element_size()
    return max(1, int(chunk_mb * 2**20 // max(per_bin, 1)))


def _splat(depth: torch.Tensor, feat: torch.Tensor, cell: torch.Tensor, n_cells: int, chunk: int) -> torch.Tensor:
    """Return the pooled (n_cells, C), lifting ``chunk`` depth bins at a time; cells outside
    the grid go to one spare row, dropped at the end (no boolean indexing, no copy)."""
    C = feat.shape[-1]
    cell = cell.clamp(max=n_cells)
    bev = feat.new_zeros(n_cells + 1, C)
    for d0 in range(0, depth.shape[1], chunk):
        lifted = depth[:, d0 : d0 + chunk, :, None] * feat[:, None]
        bev = add_rows(bev, cell[:, d0 : d0 + chunk].reshape(-1), lifted.reshape(-1, C))
    return bev[:n_cells]


class _BevPool(torch.autograd.Function):
    @staticmethod
    def forward(ctx, depth, feat, cell, n_cells, chunk):  # type: ignore[override]
        ctx.save_for_backward(depth, feat, cell)
        ctx.n_cells, ctx.chunk = n_cells, chunk
        return _splat(depth, feat, cell, n_cells, chunk)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        depth, feat, cell = ctx.saved_tensors
        n_cells, chunk = ctx.n_cells, ctx.chunk
        # d out[c] / d depth[n, d, p] = feat[n, p] where cell[n, d, p] = c; the spare row's gradient is 0
        g = torch.cat([grad, grad.new_zeros(1, grad.shape[1])])
        cell = cell.clamp(max=n_cells)
        gdepth = torch.empty_like(depth) if ctx.needs_input_grad[0] else None
        gfeat = torch.zeros_like(feat) if ctx.needs_input_grad[1] else None
        for d0 in range(0, depth.shape[1], chunk):
            gc = g[cell[:, d0 : d0 + chunk]]  # (N, dc, P, C): the gradient each lifted feature receives
            if gdepth is not None:
                gdepth[:, d0 : d0 + chunk] = (gc * feat[:, None]).sum(-1)
            if gfeat is not None:
                gfeat += (gc * depth[:, d0 : d0 + chunk, :, None]).sum(1)
        return gdepth, gfeat, None, None, None


def bev_pool(depth: torch.Tensor, feat: torch.Tensor, cell: torch.Tensor, n_cells: int, chunk_mb: float = 256.0) -> torch.Tensor:
    """Return what ``bev_pool_naive`` returns, holding at most about ``chunk_mb`` MiB of
    lifted features at once (forward and backward)."""
    chunk = _depth_chunk(depth, feat, chunk_mb)
    if torch.is_grad_enabled() and (depth.requires_grad or feat.requires_grad):
        return _BevPool.apply(depth, feat, cell, n_cells, chunk)
    return _splat(depth, feat, cell, n_cells, chunk)
