"""The paper's loss (Sec. III-D): risk MSE, weighted Smooth-L1 elevation, consistency."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from gtgen import codes
from gtgen.config import TrainConfig


def _masked_mean(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    return (x * m).sum() / m.sum().clamp(min=1)


def range_losses(pred: dict, batch: dict, rng: str, alpha: float, beta: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Return (risk MSE, elevation loss) of one range; elevations (and ``beta``) in scaled units."""
    risk_lbl = batch[f"{rng}/risk"]
    rm = torch.isfinite(risk_lbl).float()
    l_trav = _masked_mean((pred[f"{rng}/risk"] - torch.nan_to_num(risk_lbl)) ** 2, rm)
    el = batch[f"{rng}/elevation"]
    reg = batch[f"{rng}/region"]
    sl1 = F.smooth_l1_loss(pred[f"{rng}/elevation"], torch.nan_to_num(el), reduction="none", beta=beta)
    obs = ((reg == codes.OBS_PC) | (reg == codes.OBS_F)).float() * torch.isfinite(el).float()
    unobs = (reg == codes.UNOBS).float() * torch.isfinite(el).float()
    return l_trav, _masked_mean(sl1, obs) + alpha * _masked_mean(sl1, unobs)


def consistency(pred: dict, beta: float = 1.0) -> torch.Tensor:
    """Smooth-L1 between the micro elevation pooled to short cells and the short centre crop."""
    s = pred["short/elevation"]
    S = s.shape[-1]
    crop = s[:, S // 4 : S - S // 4, S // 4 : S - S // 4]
    m = F.adaptive_avg_pool2d(pred["micro/elevation"][:, None], crop.shape[-2:])[:, 0]
    return F.smooth_l1_loss(m, crop, beta=beta)


def total_loss(pred: dict, batch: dict, tc: TrainConfig) -> tuple[torch.Tensor, dict[str, float]]:
    """Return the weighted total and its parts (for logging)."""
    parts = {}
    total = torch.zeros((), device=pred["short/elevation"].device)
    beta = tc.elevation_beta_m / tc.elevation_clip_m
    for rng in ("micro", "short"):
        lt, le = range_losses(pred, batch, rng, tc.alpha, beta)
        parts[f"{rng}/trav"], parts[f"{rng}/ele"] = float(lt.detach()), float(le.detach())
        total = total + tc.mu * lt + tc.lam * le
    lc = consistency(pred, beta)
    parts["cons"] = float(lc.detach())
    total = total + tc.gamma * lc
    parts["total"] = float(total.detach())
    return total, parts
