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


PRESETS: dict[str, Preset] = {
    "tiny": Preset(
        "CPU preset: 5 to 8 minutes on 2 cores (1000 steps of 0.3 to 0.5 s). Grids are coarser than the labels (labels\n"
        "are resampled by nearest cell centre): short 128 cells over +-100 m, micro 128 over +-50 m. Depth bins reach\n"
        "142 m, the short grid's corners, where nothing but the cameras sees at t.",
        dict(micro_size=128, short_size=128, image_width=96, image_height=60, depth_min_m=2.0, depth_max_m=142.0,
             depth_step_m=4.0, image_channels=16, pillar_channels=16, max_points_per_pillar=16, decoder_channels=24,
             lr=0.002, steps=1000, batch_size=2, ckpt_every=250, workers=0),
    ),
    "paper": Preset(
        "The paper's sizes (Sec. III-D): micro 500 x 500 at 0.2 m, short 250 x 250 at 0.8 m,\n"
        "640 x 396 images, depth bins 1..110 m every 0.8 m, 80 image and 256 pillar channels,\n"
        "16,000 Adam steps at 5e-4 with OneCycle. Meant for a GPU: set train.device: cuda.",
        dict(micro_size=500, short_size=250, image_width=640, image_height=396, depth_min_m=1.0, depth_max_m=110.0,
             depth_step_m=0.8, image_channels=80, pillar_channels=256, max_points_per_pillar=16, decoder_channels=128,
             lr=0.0005, steps=16000, batch_size=4, ckpt_every=500, workers=4),
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
