"""The model presets ``gtgen train --preset NAME`` picks: layers over ``train`` in the config.

Defined here, in the package, so an installed gtgen has them; ``configs/presets/<name>.yaml``
mirrors each one for reading and for ``--config`` (a test keeps the two equal; regenerate
with ``python scripts/update_schema_doc.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gtgen.errors import ConfigError


@dataclass(frozen=True)
class Preset:
    """One preset: what it is for, and its ``train`` values."""

    doc: str
    train: dict[str, Any]
    # (constant, per sample) [GiB]: the peak RSS of one float32 training step on the CPU at
    # the preset's sizes is about constant + per sample x batch (gtgen/train/memory.py).
    # Measured with bench/train.py's whole-step script (PAPER_STEP, the preset named in it)
    # at two batches, 2026-12-05: paper 4.96 GiB at batch 1, 9.33 at batch 2 (batch 6 was
    # killed by the kernel at 21.5 GB); tiny 0.63 GiB at batch 2, 2.29 at batch 16
    memory_gib: tuple[float, float] | None = None


PRESETS: dict[str, Preset] = {
    "tiny": Preset(
        "CPU preset: 5 to 8 minutes on 2 cores (1000 steps of 0.3 to 0.5 s). Grids are coarser than the labels (labels\n"
        "are resampled by nearest cell centre): short 128 cells over +-100 m, micro 128 over +-50 m. Depth bins reach\n"
        "142 m, the short grid's corners, where nothing but the cameras sees at t. A small CNN image branch.\n"
        "Validates on 48 val samples every 250 steps (best.pt).",
        dict(micro_size=128, short_size=128, image_width=96, image_height=60, depth_min_m=2.0, depth_max_m=142.0,
             depth_step_m=4.0, image_channels=16, pillar_channels=16, max_points_per_pillar=16, decoder_channels=24,
             image_backbone="small_cnn", lr=0.002, steps=1000, batch_size=2, ckpt_every=250, val_every=250,
             val_max_samples=48, workers=0),
        memory_gib=(0.39, 0.119),
    ),
    "paper": Preset(
        "The paper's network and sizes (Sec. III-D): EfficientNet-B0 (ImageNet weights from a local file:\n"
        "train.backbone_weights) with an FPN over stages {5, 6, 8} to 1/8 of 640 x 396 images, depth bins 1..110 m\n"
        "every 0.8 m, 80 image channels; PointPillars of 0.8 m with 16 points per pillar, 32,000 / 64,000 pillars\n"
        "(train / test), 256 channels; micro 500 x 500 at 0.2 m, short 250 x 250 at 0.8 m; 19.5 M parameters in the\n"
        "paper, 20.2 M here; 16,000 Adam steps at 5e-4 with OneCycle, batch 6. Meant for GPUs (device auto, mixed\n"
        "precision there). gtgen's loss and augmentation defaults apply; configs/paper_faithful.yaml adds the paper's.",
        dict(micro_size=500, short_size=250, image_width=640, image_height=396, depth_min_m=1.0, depth_max_m=110.0,
             depth_step_m=0.8, image_channels=80, pillar_channels=256, max_points_per_pillar=16,
             max_pillars_train=32000, max_pillars_test=64000, decoder_channels=88, image_backbone="efficientnet_b0",
             fpn_channels=128, lr=0.0005, steps=16000, batch_size=6, ckpt_every=500, val_every=500, workers=4),
        memory_gib=(0.60, 4.37),
    ),
}


def preset_overrides(name: str) -> dict:
    """Return the config layer of preset ``name``, or raise ConfigError naming the presets."""
    if name not in PRESETS:
        raise ConfigError(f"preset {name!r} unknown; expected one of {sorted(PRESETS)}")
    return {"train": {**PRESETS[name].train, "preset": name}}


def preset_yaml(name: str) -> str:
    """Return the text of ``configs/presets/<name>.yaml``."""
    import yaml

    p = PRESETS[name]
    head = "".join(f"# {line}\n" for line in p.doc.splitlines())
    return head + yaml.safe_dump({"train": p.train}, sort_keys=False)
