"""M&M-lite: Lift-Splat image BEV + PointPillars + raw elevation -> hierarchical decoder.

Short maps come from a U-Net over the fused BEV features; the micro maps from the
centre crop (+-50 m) of the BEV and short features, upsampled (Sec. III-D). Each input
(``train.cameras``, ``points``, ``raw_elevation``) can be left out, and a network can
predict one range alone (``train.ranges``): the paper's baselines (Sec. IV-B).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gtgen.config import GridsConfig, TrainConfig
from gtgen.train.backbones import EfficientNetFPN, ResBlock, SmallCNN, _block
from gtgen.train.bev_pool import bev_pool
from gtgen.train.pillars import PointPillars, cell_index

IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)


def normalize_images(images: torch.Tensor) -> torch.Tensor:
    """Return uint8 RGB images (..., 3, h, w) as ImageNet-normalised float32 (on their device:
    the loader ships bytes, a quarter of the floats' size, and does no arithmetic)."""
    mean = images.new_tensor(IMAGE_MEAN, dtype=torch.float32)[:, None, None]
    std = images.new_tensor(IMAGE_STD, dtype=torch.float32)[:, None, None]
    return (images.float() * (1.0 / 255.0) - mean) / std


def _inverse_K(K: torch.Tensor) -> torch.Tensor:
    """Return the inverses of intrinsics ``K`` (..., 3, 3), upper triangular with a last row
    (0, 0, 1), in closed form (elementwise ops: exact, and exportable to ONNX, which has no
    matrix inverse)."""
    fx, s, cx, fy, cy = K[..., 0, 0], K[..., 0, 1], K[..., 0, 2], K[..., 1, 1], K[..., 1, 2]
    z, o = torch.zeros_like(fx), torch.ones_like(fx)
    rows = [torch.stack([1 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy)], -1),
            torch.stack([z, 1 / fy, -cy / fy], -1), torch.stack([z, z, o], -1)]
    return torch.stack(rows, -2)


class LiftSplat(nn.Module):
    """Per-pixel depth distributions lift image features into the short BEV grid."""

    def __init__(self, tc: TrainConfig, bev_size: int, bev_res: float) -> None:
        super().__init__()
        self.register_buffer("depths", torch.arange(tc.depth_min_m, tc.depth_max_m + 1e-6, tc.depth_step_m), persistent=False)
        self.D = len(self.depths)
        self.C = tc.image_channels
        if tc.image_backbone == "efficientnet_b0":
            self.backbone: nn.Module = EfficientNetFPN(tc.fpn_channels)
        else:
            self.backbone = SmallCNN(max(16, tc.image_channels // 2))
        self.head = nn.Conv2d(self.backbone.out_channels, self.D + self.C, 1)
        self.bev_size, self.bev_res = bev_size, bev_res
        self.chunk_mb = tc.bev_pool_chunk_mb

    def forward(self, images: torch.Tensor, K: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
        B, N, _, H, W = images.shape
        f = self.head(self.backbone(normalize_images(images.flatten(0, 1))))
        h, w = f.shape[-2:]
        # pooled in float32 whatever the autocast: sums of thousands of features per cell
        depth = f[:, : self.D].float().softmax(1).flatten(2)  # (BN, D, hw)
        feat = f[:, self.D :].float().flatten(2).transpose(1, 2)  # (BN, hw, C)
        # pixel centres of the feature map in input-image pixels (ROS convention)
        u = (torch.arange(w, device=f.device, dtype=torch.float32) + 0.5) * (W / w) - 0.5
        v = (torch.arange(h, device=f.device, dtype=torch.float32) + 0.5) * (H / h) - 0.5
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        pix = torch.stack([uu, vv, torch.ones_like(uu)], -1).reshape(-1, 3)  # (hw, 3)
        rays = torch.einsum("bij,pj->bpi", _inverse_K(K.flatten(0, 1).float()), pix)  # (BN, hw, 3), z = 1
        pts = rays[:, None] * self.depths[None, :, None, None]  # (BN, D, hw, 3)
        Tf = T.flatten(0, 1).float()
        pts = torch.einsum("bij,bdpj->bdpi", Tf[:, :3, :3], pts) + Tf[:, None, None, :3, 3]
        S = self.bev_size
        ix, iy = cell_index(pts[..., 0], pts[..., 1], S, self.bev_res)
        ok = ix >= 0
        bidx = torch.arange(B, device=f.device).repeat_interleave(N)[:, None, None]
        n_cells = B * S * S
        cell = torch.where(ok, (bidx * S + ix) * S + iy, torch.full_like(ix, n_cells))
        bev = bev_pool(depth, feat, cell, n_cells, self.chunk_mb)
        return bev.view(B, S, S, self.C).permute(0, 3, 1, 2)


def centre_half(x: torch.Tensor) -> torch.Tensor:
    """Return the centre half (per axis) of the maps ``x`` (..., S, S): the micro range's
    part of the short grid. For S a multiple of 4 a slice, else resampled bilinearly at
    S // 2 cells over exactly the centre half (S = 250 at the paper's sizes)."""
    S = x.shape[-1]
    if S % 4 == 0:
        return x[..., S // 4 : S - S // 4, S // 4 : S - S // 4]
    lead = x.shape[:-2]
    flat = x.reshape(-1, 1, S, S)
    theta = torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0]], dtype=flat.dtype, device=flat.device).expand(flat.shape[0], 2, 3)
    grid = F.affine_grid(theta, [flat.shape[0], 1, S // 2, S // 2], align_corners=False)
    return F.grid_sample(flat, grid, mode="bilinear", align_corners=False).reshape(*lead, S // 2, S // 2)


class GlobalContext(nn.Module):
    """Adds to every cell a feature of the whole map (mean-pooled, projected): the decoder
    then sees the context of the entire short grid, tens of metres beyond the last point."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.proj = nn.Sequential(nn.Linear(c, c), nn.ReLU(inplace=True), nn.Linear(c, c))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.proj(x.mean(dim=(2, 3)))[:, :, None, None]


def _risk_head(c: int) -> nn.Sequential:
    """A 3x3 layer then a linear 1x1 to the risk logit, starting at risk 1 %."""
    head = nn.Sequential(nn.Conv2d(c, c, 3, 1, 1, bias=False), nn.BatchNorm2d(c), nn.LeakyReLU(0.1, inplace=True), nn.Conv2d(c, 1, 1))
    nn.init.constant_(head[-1].bias, -4.6)
    return head


def _dilated(c: int, d: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c, c, 3, 1, d, dilation=d, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True))


def bev_grid(tc: TrainConfig, grids: GridsConfig) -> tuple[float, int]:
    """Return the edge length [m] and cells per side of the model's fused BEV features: the
    short grid at ``tc.short_size`` cells, or for a micro-only model (``tc.ranges``) only the
    micro grid's extent (its centre half) at the same cell size."""
    if tc.ranges == "micro":
        return grids.micro.length_m, (tc.short_size + 1) // 2
    return grids.short.length_m, tc.short_size


class MMLite(nn.Module):
    """The network: returns a dict of 'micro/elevation', 'micro/risk', 'short/...' maps
    (of the ranges ``tc.ranges`` names).

    Inputs fused on the BEV grid (``bev_grid``), each one switchable: Lift-Splat image
    features (``tc.cameras``), PointPillars features (``tc.points``), the raw min-z channel
    (value, validity) and the prior the heads correct (the smoothed min z filled
    everywhere, the distance to the nearest cell with points; ``tc.raw_elevation``; without
    them the heads predict the elevation itself). A four-level U-Net whose bottom (1/8 of
    the grid) has dilated convolutions and a global context feature, so a cell's receptive
    field spans the whole grid; the micro maps come from the centre crop of its inputs and
    top features (all of them for a micro-only network), upsampled and refined (Sec. III-D).
    """

    def __init__(self, tc: TrainConfig, bev_length_m: float, bev_size: int) -> None:
        super().__init__()
        self.tc = tc
        self.ranges = tc.predicted_ranges
        S = bev_size
        res = bev_length_m / S
        self.lift = LiftSplat(tc, S, res) if tc.cameras else None
        self.pillars = (PointPillars(tc.pillar_channels, S, res, tc.max_pillars_train, tc.max_pillars_test, tc.max_points_per_pillar)
                        if tc.points else None)
        cin = tc.image_channels * tc.cameras + tc.pillar_channels * tc.points + 4 * tc.raw_elevation
        c = tc.decoder_channels
        self.enc1 = ResBlock(cin, c)
        self.enc2 = nn.Sequential(_block(c, 2 * c, 2), ResBlock(2 * c, 2 * c))
        self.enc3 = nn.Sequential(_block(2 * c, 4 * c, 2), ResBlock(4 * c, 4 * c))
        self.enc4 = nn.Sequential(_block(4 * c, 4 * c, 2), _dilated(4 * c, 2), _dilated(4 * c, 4), GlobalContext(4 * c))
        self.up3 = ResBlock(4 * c + 4 * c, 4 * c)
        self.up2 = ResBlock(4 * c + 2 * c, 2 * c)
        self.up1 = ResBlock(2 * c + c, c)
        heads = []
        if "short" in self.ranges:
            self.short_head = nn.Conv2d(c, 1, 1)
            heads.append(self.short_head)
        if "micro" in self.ranges:
            self.micro = nn.Sequential(ResBlock(cin + c, c), ResBlock(c, c))
            self.micro_refine = ResBlock(c + 2 * tc.raw_elevation, c)
            self.micro_head = nn.Conv2d(c, 1, 1)
            heads.append(self.micro_head)
        # zero-initialised elevation heads: training starts from the filled min-z prior (or flat ground without it)
        for head in heads:
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)
        # risk heads of their own: a 1x1 layer right on ReLU features lost every positive
        # weight early (all cells "no risk") and then could not rise above its bias
        if "short" in self.ranges:
            self.short_risk = _risk_head(c)
        if "micro" in self.ranges:
            self.micro_risk = _risk_head(c)

    @staticmethod
    def _up(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Return the maps of a collated batch (``ShardDataset``'s keys); the optional key
        ``point_rand`` (B, P) holds the training's random priorities of the points, which pick
        the pillars' points (without it, the first points in order)."""
        pillars = self.pillars(batch["points"], batch["n_points"], batch.get("point_rand")) if self.pillars is not None else None
        return self.decode(batch, pillars)

    def decode(self, batch: dict[str, torch.Tensor], pillars: torch.Tensor | None) -> dict[str, torch.Tensor]:
        """Return the maps from the batch's images, grids and the PointPillars features (each
        only if the model takes it)."""
        parts = [self.lift(batch["images"], batch["K"], batch["T_target_cam"])] if self.lift is not None else []
        parts += [pillars] if pillars is not None else []
        parts += [batch["raw"], batch["prior"]] if self.tc.raw_elevation else []
        x = torch.cat(parts, 1)
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        e4 = self.enc4(e3)
        d3 = self.up3(torch.cat([self._up(e4, e3), e3], 1))
        d2 = self.up2(torch.cat([self._up(d3, e2), e2], 1))
        d1 = self.up1(torch.cat([self._up(d2, e1), e1], 1))
        out: dict[str, torch.Tensor] = {}
        if "short" in self.ranges:
            out.update(self._maps("short", torch.cat([self.short_head(d1), self.short_risk(d1)], 1), batch.get("prior")))
        if "micro" in self.ranges:
            f = torch.cat([x, d1], 1)
            m = self.micro(centre_half(f) if "short" in self.ranges else f)  # +-50 m of +-100 m, or the whole micro-only grid
            m = F.interpolate(m, size=(self.tc.micro_size, self.tc.micro_size), mode="bilinear", align_corners=False)
            m = self.micro_refine(torch.cat([m, batch["prior_micro"]], 1) if self.tc.raw_elevation else m)
            out.update(self._maps("micro", torch.cat([self.micro_head(m), self.micro_risk(m)], 1), batch.get("prior_micro")))
        return out

    def _maps(self, rng: str, head: torch.Tensor, prior: torch.Tensor | None) -> dict[str, torch.Tensor]:
        """Return range ``rng``'s maps from its heads' (B, 2, n, n) output: elevation (the
        prior corrected, or the head itself without the prior), risk and its logit."""
        elevation = prior[:, 0] + head[:, 0] if self.tc.raw_elevation else head[:, 0]
        return {f"{rng}/elevation": elevation, f"{rng}/risk": torch.sigmoid(head[:, 1]), f"{rng}/risk_logit": head[:, 1]}
