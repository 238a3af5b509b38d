"""The network a config describes, and the batches it takes: ``build_model`` (with its
checks of the grids), its parameters per block, and batches stacked and moved to a device.
Shared by training (``trainer.py``) and evaluation (``evaluation.py``)."""

from __future__ import annotations

from pathlib import Path

import torch

from gtgen.config import GtgenConfig, TrainConfig
from gtgen.errors import ConfigError
from gtgen.train.model import MMLite, bev_grid


def collate(items: list[dict]) -> dict:
    """Return the samples ``items`` (dicts of tensors) stacked into a batch."""
    return {k: torch.stack([it[k] for it in items]) for k in items[0]}


def to_device(batch: dict, device: torch.device) -> dict:
    """Return ``batch`` on ``device``."""
    # non-blocking from pinned memory on CUDA: the copy overlaps the previous step's kernels
    return {k: v.to(device, non_blocking=device.type == "cuda") for k, v in batch.items()}


def build_model(tc: TrainConfig, data_cfg: GtgenConfig) -> MMLite:
    """Return a fresh model; loads ``backbone_weights`` into the EfficientNet-B0 if given.
    Raises ConfigError for grids the model cannot tile: its micro maps and their inputs come
    from the centre half of the short grid, and its encoder halves its BEV grid three times."""
    gm, gs = data_cfg.grids.micro, data_cfg.grids.short
    if "micro" in tc.predicted_ranges and abs(2 * gm.length_m - gs.length_m) > 1e-6:
        raise ConfigError(f"grids.micro spans {gm.length_m:g} m and grids.short {gs.length_m:g} m: M&M-lite takes the micro maps and "
                          f"their inputs from the centre half of the short grid, so the micro grid must span {gs.length_m / 2:g} m")
    bev_m, bev_cells = bev_grid(tc, data_cfg.grids)
    if bev_cells < 16 or tc.micro_size < 8:
        raise ConfigError(f"train.short_size {tc.short_size} / micro_size {tc.micro_size}: the model needs at least 16 BEV cells "
                          f"(the short size, or half of it for train.ranges: micro) and 8 micro cells")
    if tc.backbone_weights and (tc.image_backbone != "efficientnet_b0" or not tc.cameras):
        raise ConfigError(f"train.backbone_weights loads EfficientNet-B0 weights, but train.image_backbone is {tc.image_backbone!r}"
                          f"{'' if tc.cameras else ' and train.cameras is off'}; set image_backbone: efficientnet_b0 with cameras on "
                          "(the paper preset) or drop backbone_weights")
    model = MMLite(tc, bev_m, bev_cells)
    if tc.backbone_weights:
        from gtgen.train.backbones import load_backbone_weights

        load_backbone_weights(model.lift.backbone.net, Path(tc.backbone_weights))
    # channels-last weights: oneDNN's convolutions run about 20 % faster on the tiny preset's
    # CPU training step (and it is the layout GPU tensor cores prefer)
    return model.to(memory_format=torch.channels_last)


def parameter_counts(model: MMLite) -> dict[str, int]:
    """Return the model's parameters per block, in the paper's order (Sec. III-D)."""
    blocks = {
        "image backbone": ("lift.backbone.net.", *(f"lift.backbone.s{i}." for i in range(1, 5)), "lift.backbone.merge."),
        "image FPN": ("lift.backbone.lateral.", "lift.backbone.smooth."),
        "depth + feature head": ("lift.head.",),
        "PointPillars": ("pillars.",),
        "decoder, short (U-Net)": ("enc", "up", "short_"),
        "decoder, micro": ("micro",),
    }
    out = dict.fromkeys(blocks, 0)
    for name, p in model.named_parameters():
        block = next(b for b, prefixes in blocks.items() if name.startswith(prefixes))
        out[block] += p.numel()
    out["total"] = sum(out.values())
    return {k: v for k, v in out.items() if v or k == "total"}
