"""M&M-lite: Lift-Splat image BEV + PointPillars + raw elevation -> hierarchical decoder.

Short maps come from a U-Net over the fused BEV features; the micro maps from the
centre crop (+-50 m) of the BEV and short features, upsampled (Sec. III-D).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gtgen.config import TrainConfig

IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)


def normalize_images(images: torch.Tensor) -> torch.Tensor:
    """Return uint8 RGB images (..., 3, h, w) as ImageNet-normalised float32 (on their device:
    the loader ships bytes, a quarter of the floats' size, and does no arithmetic)."""
    mean = images.new_tensor(IMAGE_MEAN, dtype=torch.float32)[:, None, None]
    std = images.new_tensor(IMAGE_STD, dtype=torch.float32)[:, None, None]
    return (images.float() * (1.0 / 255.0) - mean) / std


def _block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class ResBlock(nn.Module):
    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.a = _block(cin, cout)
        self.b = nn.Sequential(nn.Conv2d(cout, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout))
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.b(self.a(x)) + self.skip(x))


class ImageBackbone(nn.Module):
    """A small CNN to 1/8 resolution with an FPN-style merge of the last two scales."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.s1 = nn.Sequential(_block(3, c // 2, 2), _block(c // 2, c // 2))
        self.s2 = nn.Sequential(_block(c // 2, c, 2), ResBlock(c, c))
        self.s3 = nn.Sequential(_block(c, 2 * c, 2), ResBlock(2 * c, 2 * c))
        self.s4 = nn.Sequential(_block(2 * c, 2 * c, 2), ResBlock(2 * c, 2 * c))
        self.merge = ResBlock(4 * c, 2 * c)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x3 = self.s3(self.s2(self.s1(x)))
        x4 = F.interpolate(self.s4(x3), size=x3.shape[-2:], mode="bilinear", align_corners=False)
        return self.merge(torch.cat([x3, x4], 1))


class LiftSplat(nn.Module):
    """Per-pixel depth distributions lift image features into the short BEV grid."""

    def __init__(self, tc: TrainConfig, bev_size: int, bev_res: float) -> None:
        super().__init__()
        self.depths = torch.arange(tc.depth_min_m, tc.depth_max_m + 1e-6, tc.depth_step_m)
        self.D = len(self.depths)
        self.C = tc.image_channels
        cb = max(16, tc.image_channels // 2)
        self.backbone = ImageBackbone(cb)
        self.head = nn.Conv2d(2 * cb, self.D + self.C, 1)
        self.bev_size, self.bev_res = bev_size, bev_res

    def forward(self, images: torch.Tensor, K: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
        B, N, _, H, W = images.shape
        f = self.head(self.backbone(normalize_images(images.flatten(0, 1))))
        h, w = f.shape[-2:]
        depth = f[:, : self.D].softmax(1)
        feat = f[:, self.D :]
        # pixel centres of the feature map in input-image pixels (ROS convention)
        u = (torch.arange(w, device=f.device) + 0.5) * (W / w) - 0.5
        v = (torch.arange(h, device=f.device) + 0.5) * (H / h) - 0.5
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        pix = torch.stack([uu, vv, torch.ones_like(uu)], -1).reshape(-1, 3)  # (hw, 3)
        Kinv = torch.linalg.inv(K.flatten(0, 1))  # (BN, 3, 3)
        rays = torch.einsum("bij,pj->bpi", Kinv, pix)  # (BN, hw, 3), z = 1
        d = self.depths.to(f.device)
        pts = rays[:, None] * d[None, :, None, None]  # (BN, D, hw, 3)
        Tf = T.flatten(0, 1)
        pts = torch.einsum("bij,bdpj->bdpi", Tf[:, :3, :3], pts) + Tf[:, None, None, :3, 3]
        L = self.bev_size * self.bev_res
        ix = torch.floor((pts[..., 0] + L / 2) / self.bev_res).long()
        iy = torch.floor((pts[..., 1] + L / 2) / self.bev_res).long()
        ok = (ix >= 0) & (ix < self.bev_size) & (iy >= 0) & (iy < self.bev_size)
        bidx = torch.arange(B, device=f.device).repeat_interleave(N)[:, None, None].expand_as(ix)
        lin = (bidx * self.bev_size + ix) * self.bev_size + iy
        lifted = depth.flatten(2)[:, :, :, None] * feat.flatten(2).transpose(1, 2)[:, None]  # (BN, D, hw, C)
        bev = torch.zeros(B * self.bev_size * self.bev_size, self.C, device=f.device, dtype=f.dtype)
        bev.index_add_(0, lin[ok], lifted[ok])
        return bev.view(B, self.bev_size, self.bev_size, self.C).permute(0, 3, 1, 2)


class PointPillars(nn.Module):
    """A PointNet per pillar (max-pooled) scattered to the short BEV grid, then a 2D CNN."""

    def __init__(self, tc: TrainConfig, bev_size: int, bev_res: float) -> None:
        super().__init__()
        c = tc.pillar_channels
        self.pfn = nn.Sequential(nn.Linear(8, c), nn.LayerNorm(c), nn.ReLU())  # xyz, offset to pillar mean, offset to pillar centre
        self.cnn = nn.Sequential(ResBlock(c, c), ResBlock(c, c))
        self.bev_size, self.bev_res, self.C = bev_size, bev_res, c
        self.max_per_pillar = tc.max_points_per_pillar

    def forward(self, points: torch.Tensor, n_points: torch.Tensor) -> torch.Tensor:
        B, P, _ = points.shape
        S = self.bev_size
        L = S * self.bev_res
        valid = torch.arange(P, device=points.device)[None] < n_points[:, None]
        ix = torch.floor((points[..., 0] + L / 2) / self.bev_res).long()
        iy = torch.floor((points[..., 1] + L / 2) / self.bev_res).long()
        valid &= (ix >= 0) & (ix < S) & (iy >= 0) & (iy < S)
        lin = (torch.arange(B, device=points.device)[:, None] * S + ix) * S + iy
        lin = torch.where(valid, lin, torch.zeros_like(lin))
        flat, pts = lin[valid], points[valid]
        # at most max_per_pillar points per pillar: rank points within their pillar
        order = torch.argsort(flat, stable=True)
        sf = flat[order]
        first = torch.ones_like(sf, dtype=torch.bool)
        first[1:] = sf[1:] != sf[:-1]
        start = torch.cummax(torch.where(first, torch.arange(len(sf), device=sf.device), torch.zeros_like(sf)), 0).values
        keep = torch.zeros_like(flat, dtype=torch.bool)
        keep[order] = (torch.arange(len(sf), device=sf.device) - start) < self.max_per_pillar
        flat, pts = flat[keep], pts[keep]
        ncell = B * S * S
        cnt = torch.zeros(ncell, device=points.device).index_add_(0, flat, torch.ones_like(flat, dtype=points.dtype))
        mean = torch.zeros(ncell, 3, device=points.device).index_add_(0, flat, pts) / cnt.clamp(min=1)[:, None]
        cx = ((flat // S) % S).to(points.dtype) * self.bev_res - L / 2 + self.bev_res / 2
        cy = (flat % S).to(points.dtype) * self.bev_res - L / 2 + self.bev_res / 2
        feats = torch.cat([pts, pts - mean[flat], (pts[:, 0] - cx)[:, None], (pts[:, 1] - cy)[:, None]], 1)
        h = self.pfn(feats)
        bev = torch.zeros(ncell, self.C, device=points.device, dtype=h.dtype)
        if len(flat):
            bev = bev.scatter_reduce(0, flat[:, None].expand(-1, self.C), h, "amax", include_self=False)
        return self.cnn(bev.view(B, S, S, self.C).permute(0, 3, 1, 2))


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


class MMLite(nn.Module):
    """The network: returns a dict of 'micro/elevation', 'micro/risk', 'short/...' maps.

    Inputs fused on the short grid: Lift-Splat image features, PointPillars features, the
    raw min-z channel (value, validity) and the prior the heads correct (the smoothed min z
    filled everywhere, the distance to the nearest cell with points). A four-level U-Net
    whose bottom (1/8 of the grid) has dilated convolutions and a global context feature,
    so a cell's receptive field spans the whole short grid; the micro maps come from the
    centre crop of its inputs and top features, upsampled and refined (Sec. III-D).
    """

    def __init__(self, tc: TrainConfig, short_length_m: float) -> None:
        super().__init__()
        self.tc = tc
        S = tc.short_size
        res = short_length_m / S
        self.lift = LiftSplat(tc, S, res)
        self.pillars = PointPillars(tc, S, res)
        cin = tc.image_channels + tc.pillar_channels + 4
        c = tc.decoder_channels
        self.enc1 = ResBlock(cin, c)
        self.enc2 = nn.Sequential(_block(c, 2 * c, 2), ResBlock(2 * c, 2 * c))
        self.enc3 = nn.Sequential(_block(2 * c, 4 * c, 2), ResBlock(4 * c, 4 * c))
        self.enc4 = nn.Sequential(_block(4 * c, 4 * c, 2), _dilated(4 * c, 2), _dilated(4 * c, 4), GlobalContext(4 * c))
        self.up3 = ResBlock(4 * c + 4 * c, 4 * c)
        self.up2 = ResBlock(4 * c + 2 * c, 2 * c)
        self.up1 = ResBlock(2 * c + c, c)
        self.short_head = nn.Conv2d(c, 1, 1)
        self.micro = nn.Sequential(ResBlock(cin + c, c), ResBlock(c, c))
        self.micro_refine = ResBlock(c + 2, c)
        self.micro_head = nn.Conv2d(c, 1, 1)
        # zero-initialised elevation heads: training starts from the filled min-z prior
        for head in (self.short_head, self.micro_head):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)
        # risk heads of their own: a 1x1 layer right on ReLU features lost every positive
        # weight early (all cells "no risk") and then could not rise above its bias
        self.short_risk, self.micro_risk = _risk_head(c), _risk_head(c)

    @staticmethod
    def _up(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        x = torch.cat([
            self.lift(batch["images"], batch["K"], batch["T_target_cam"]),
            self.pillars(batch["points"], batch["n_points"]),
            batch["raw"],
            batch["prior"],
        ], 1)
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        e4 = self.enc4(e3)
        d3 = self.up3(torch.cat([self._up(e4, e3), e3], 1))
        d2 = self.up2(torch.cat([self._up(d3, e2), e2], 1))
        d1 = self.up1(torch.cat([self._up(d2, e1), e1], 1))
        s = torch.cat([self.short_head(d1), self.short_risk(d1)], 1)
        m = self.micro(centre_half(torch.cat([x, d1], 1)))  # +-50 m of +-100 m
        m = F.interpolate(m, size=(self.tc.micro_size, self.tc.micro_size), mode="bilinear", align_corners=False)
        m = self.micro_refine(torch.cat([m, batch["prior_micro"]], 1))
        m = torch.cat([self.micro_head(m), self.micro_risk(m)], 1)
        return {"short/elevation": batch["prior"][:, 0] + s[:, 0], "short/risk": torch.sigmoid(s[:, 1]), "short/risk_logit": s[:, 1],
                "micro/elevation": batch["prior_micro"][:, 0] + m[:, 0], "micro/risk": torch.sigmoid(m[:, 1]), "micro/risk_logit": m[:, 1]}
