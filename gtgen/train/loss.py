"""The paper's loss (Sec. III-D): risk MSE (or a fatal-weighted MSE or cross-entropy),
weighted Smooth-L1 elevation, consistency."""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from gtgen import codes
from gtgen.config import TrainConfig
from gtgen.train.model import centre_half

Count = Callable[[torch.Tensor], torch.Tensor]


def _local(n: torch.Tensor) -> torch.Tensor:
    return n.clamp(min=1)


def _masked_mean(x: torch.Tensor, m: torch.Tensor, count: Count = _local) -> torch.Tensor:
    """Return the sum of ``x`` over the mask ``m`` divided by ``count(m.sum())``: this batch's
    mean (at least 1 cell), or under DDP the share of the global batch's mean this process
    contributes (``count`` returns the global count over the number of processes, and DDP
    averages the gradients: their mean is the global mean's)."""
    return (x * m).sum() / count(m.sum())


def risk_loss(pred: dict, rng: str, label: torch.Tensor, tc: TrainConfig, count: Count = _local) -> torch.Tensor:
    """Return the risk loss of range ``rng``: the paper's MSE (``mse``), the MSE with the
    fatal cells (label >= ``fatal_risk``) weighted ``risk_fatal_weight`` times
    (``weighted_mse``), or the binary cross-entropy of the predicted risk against the risk
    label, fatal cells weighted alike (``weighted_bce``). Fatal cells are under 1 % of the
    labelled cells: under plain MSE predicting "no risk" everywhere is nearly optimal, and
    once the sigmoid saturates there its gradient vanishes; the cross-entropy's gradient
    (prediction minus label) does not."""
    ok = torch.isfinite(label)
    y = torch.nan_to_num(label)
    w = ok.float()
    if tc.risk_loss != "mse":
        w = w * (1.0 + (tc.risk_fatal_weight - 1.0) * (y >= tc.fatal_risk).float())
    if tc.risk_loss == "weighted_bce":
        return _masked_mean(F.binary_cross_entropy_with_logits(pred[f"{rng}/risk_logit"], y, reduction="none"), w, count)
    return _masked_mean((pred[f"{rng}/risk"] - y) ** 2, w, count)


def range_losses(pred: dict, batch: dict, rng: str, tc: TrainConfig, count: Count = _local) -> tuple[torch.Tensor, torch.Tensor]:
    """Return (risk loss, elevation loss) of one range; elevations in scaled units."""
    beta = tc.elevation_beta_m / tc.elevation_clip_m
    el = batch[f"{rng}/elevation"]
    reg = batch[f"{rng}/region"]
    sl1 = F.smooth_l1_loss(pred[f"{rng}/elevation"], torch.nan_to_num(el), reduction="none", beta=beta)
    have = torch.isfinite(el).float()
    obs = ((reg == codes.OBS_PC) | (reg == codes.OBS_F)).float() * have
    unobs = (reg == codes.UNOBS).float() * have
    return (risk_loss(pred, rng, batch[f"{rng}/risk"], tc, count),
            _masked_mean(sl1, obs, count) + tc.alpha * _masked_mean(sl1, unobs, count))


def consistency(pred: dict, beta: float = 1.0) -> torch.Tensor:
    """Smooth-L1 between the micro elevation pooled to short cells and the short centre crop."""
    crop = centre_half(pred["short/elevation"])
    m = F.adaptive_avg_pool2d(pred["micro/elevation"][:, None], crop.shape[-2:])[:, 0]
    return F.smooth_l1_loss(m, crop, beta=beta)


def total_loss(pred: dict, batch: dict, tc: TrainConfig, count: Count = _local) -> tuple[torch.Tensor, dict[str, float]]:
    """Return the weighted total and its parts (for logging) over the ranges the model
    predicts (``tc.ranges``), the consistency term only with both; ``count`` as in
    ``_masked_mean`` (the consistency term is a plain mean: every sample has the same cells)."""
    parts = {}
    ranges = tc.predicted_ranges
    total = torch.zeros((), device=pred[f"{ranges[0]}/elevation"].device)
    for rng in ranges:
        lt, le = range_losses(pred, batch, rng, tc, count)
        parts[f"{rng}/trav"], parts[f"{rng}/ele"] = float(lt.detach()), float(le.detach())
        total = total + tc.mu * lt + tc.lam * le
    if len(ranges) == 2:
        lc = consistency(pred, tc.elevation_beta_m / tc.elevation_clip_m)
        parts["cons"] = float(lc.detach())
        total = total + tc.gamma * lc
    parts["total"] = float(total.detach())
    return total, parts
