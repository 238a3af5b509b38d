"""PointPillars on the voxel map (Sec. III-D): pillars of the short grid's cells, at most
``per_pillar`` points each and ``max_pillars`` pillars per sample (the paper: 16 points;
32,000 pillars in training, 64,000 in testing).

``pillarize`` picks the points (vectorised, on the points' device): in training a random
draw (priorities the trainer draws from the seed and the step, so a resumed run draws the
same), in testing the first points and pillars in the stored order. ``PointPillars.encode`` is
the network part: a PointNet per point (xyz, offset to its pillar's mean, offset to its
pillar's centre), max-pooled per pillar and scattered to the grid, then a 2D CNN. The ONNX
export takes the picked points and their cells as inputs (see ``gtgen.train.onnx``).
"""

from __future__ import annotations

import torch
from torch import nn

from gtgen.train.backbones import ResBlock
from gtgen.train.bev_pool import add_rows


def cell_index(x: torch.Tensor, y: torch.Tensor, size: int, res: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Return the integer cell indices (i, j) of points (x, y) [m] on a vehicle-centric grid
    of ``size`` cells of ``res``; -1 out of the grid. The torch twin of
    ``gtgen.grids.xy_to_index`` (a test holds the two equal)."""
    half = size * res / 2
    i = torch.floor((x + half) / res).long()
    j = torch.floor((y + half) / res).long()
    bad = (i < 0) | (i >= size) | (j < 0) | (j >= size)
    return torch.where(bad, -1, i), torch.where(bad, -1, j)

def pillarize(points: torch.Tensor, n_points: torch.Tensor, size: int, res: float, max_pillars: int, per_pillar: int,
              priority: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Return the kept points (n, 3) of the padded batch ``points`` (B, P, 3; the first
    ``n_points`` of each valid) and their cells (n,) int64 in the batch's flat grid
    ``b * size**2 + ix * size + iy`` (x, y in [-size * res / 2, size * res / 2)).

    A point comes before another if its ``priority`` (B, P; random numbers in training) is
    lower, or without one, if it comes first in the sample; each pillar keeps its
    ``per_pillar`` first points, and each sample its ``max_pillars`` pillars whose first
    point comes first."""
    B, P, _ = points.shape
    dev = points.device
    valid = torch.arange(P, device=dev)[None] < n_points[:, None]
    if priority is not None:
        order = torch.argsort(priority.to(dev), dim=1)
        points = torch.gather(points, 1, order[..., None].expand(-1, -1, 3))
        valid = torch.gather(valid, 1, order)
    ix, iy = cell_index(points[..., 0], points[..., 1], size, res)
    valid &= ix >= 0
    b, p = valid.nonzero(as_tuple=True)
    lin = (b * size + ix[b, p]) * size + iy[b, p]
    # sorted by pillar, then priority: a pillar's points are one run, its best first
    srt = torch.argsort(lin * P + p)
    lin, b, p = lin[srt], b[srt], p[srt]
    first = torch.ones_like(lin, dtype=torch.bool)
    first[1:] = lin[1:] != lin[:-1]
    pos = torch.arange(len(lin), device=dev)
    start = torch.cummax(torch.where(first, pos, torch.zeros_like(pos)), 0).values
    keep = (pos - start) < per_pillar
    # pillars ranked within their sample by their best point's priority
    pil_b, pil_p = b[first], p[first]
    o = torch.argsort(pil_b * P + pil_p)
    counts = torch.bincount(pil_b, minlength=B)
    offsets = torch.cumsum(counts, 0) - counts
    rank = torch.empty_like(o)
    rank[o] = torch.arange(len(o), device=dev) - offsets[pil_b[o]]
    keep &= (rank < max_pillars)[torch.cumsum(first.long(), 0) - 1]
    return points[b[keep], p[keep]], lin[keep]


class PointPillars(nn.Module):
    """A PointNet per pillar (max-pooled) scattered to the short BEV grid, then a 2D CNN."""

    def __init__(self, channels: int, bev_size: int, bev_res: float, max_pillars_train: int, max_pillars_test: int, per_pillar: int) -> None:
        super().__init__()
        c = channels
        self.pfn = nn.Sequential(nn.Linear(8, c), nn.LayerNorm(c), nn.ReLU())
        self.cnn = nn.Sequential(ResBlock(c, c), ResBlock(c, c))
        self.bev_size, self.bev_res, self.C = bev_size, bev_res, c
        self.caps = (max_pillars_train, max_pillars_test)
        self.per_pillar = per_pillar

    def forward(self, points: torch.Tensor, n_points: torch.Tensor, priority: torch.Tensor | None = None) -> torch.Tensor:
        """Return the (B, C, S, S) features of the padded points, picked by ``priority`` as in
        ``pillarize``, with the pillar cap of training or testing (the module's mode)."""
        cap = self.caps[0] if self.training else self.caps[1]
        pts, cell = pillarize(points, n_points, self.bev_size, self.bev_res, cap, self.per_pillar, priority)
        return self.encode(pts, cell, points.shape[0])

    def encode(self, pts: torch.Tensor, cell: torch.Tensor, batch: int) -> torch.Tensor:
        """Return the (batch, C, S, S) features of the points ``pts`` (n, 3) in the flat cells
        ``cell`` (n,) that ``pillarize`` returns."""
        S, res = self.bev_size, self.bev_res
        L = S * res
        ncell = batch * S * S
        pts = pts.float()
        sums = add_rows(pts.new_zeros(ncell, 4), cell, torch.cat([pts, torch.ones_like(pts[:, :1])], 1))
        mean = sums[:, :3] / sums[:, 3:].clamp(min=1)
        cx = ((cell // S) % S).to(pts.dtype) * res - L / 2 + res / 2
        cy = (cell % S).to(pts.dtype) * res - L / 2 + res / 2
        feats = torch.cat([pts, pts - mean[cell], (pts[:, 0] - cx)[:, None], (pts[:, 1] - cy)[:, None]], 1)
        h = self.pfn(feats)
        # features are >= 0 (ReLU): the empty cells' 0 is no pillar's max
        bev = h.new_zeros(ncell, self.C).scatter_reduce(0, cell[:, None].expand(-1, self.C), h, "amax", include_self=True)
        return self.cnn(bev.view(batch, S, S, self.C).permute(0, 3, 1, 2))
