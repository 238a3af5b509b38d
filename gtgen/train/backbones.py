"""Image backbones of M&M-lite: EfficientNet-B0 with an FPN to 1/8 (the paper's, Sec. III-D),
and the small CNN of the CPU preset.

EfficientNet-B0 is written in plain torch with the module tree of torchvision's
``efficientnet_b0`` (``features.<stage>.<block>.block.<layer>...``), so the ImageNet state
dict people have (``torchvision.models.efficientnet_b0(weights="IMAGENET1K_V1").state_dict()``
saved with ``torch.save``) loads strictly from a local file, without torchvision: its
release beside the pinned torch does not import. The file must hold exactly torchvision's
keys: every ``features.*`` tensor is loaded, and the ImageNet classifier
(``classifier.1.weight`` / ``.bias``, 1000 classes) must be there with its shapes but is
not part of the network (M&M-lite never classifies, and DDP refuses parameters that get no
gradient). The paper's stages {5, 6, 8} are read as indices of torchvision's ``features`` list
(112 channels at 1/16, 192 at 1/32, 1280 at 1/32): 8 is that list's last entry.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from gtgen.errors import TrainError

# (expand ratio, kernel, stride, in channels, out channels, blocks) of features.1 .. features.7
_B0_STAGES = ((1, 3, 1, 32, 16, 1), (6, 3, 2, 16, 24, 2), (6, 5, 2, 24, 40, 2), (6, 3, 2, 40, 80, 3),
              (6, 5, 1, 80, 112, 3), (6, 5, 2, 112, 192, 4), (6, 3, 1, 192, 320, 1))
B0_FPN_STAGES = (5, 6, 8)
B0_STAGE_CHANNELS = {5: 112, 6: 192, 8: 1280}
# the ImageNet classifier's tensors in torchvision's file: checked, not loaded
B0_CLASSIFIER = {"classifier.1.weight": torch.empty(1000, 1280, device="meta"), "classifier.1.bias": torch.empty(1000, device="meta")}
_BN_EPS = 1e-3  # torchvision's EfficientNet (V1) batch norms


def _conv_bn_act(cin: int, cout: int, k: int, stride: int = 1, groups: int = 1, act: bool = True) -> nn.Sequential:
    """torchvision's ``Conv2dNormActivation``: keys ``0.weight`` (conv) and ``1.*`` (norm)."""
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, k, stride, (k - 1) // 2, groups=groups, bias=False),
                               nn.BatchNorm2d(cout, eps=_BN_EPS)]
    if act:
        layers.append(nn.SiLU(inplace=True))
    return nn.Sequential(*layers)


class SqueezeExcitation(nn.Module):
    def __init__(self, c: int, squeeze: int) -> None:
        super().__init__()
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.fc1 = nn.Conv2d(c, squeeze, 1)
        self.fc2 = nn.Conv2d(squeeze, c, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(self.fc2(F.silu(self.fc1(self.avgpool(x)))))


class MBConv(nn.Module):
    """An inverted residual block with squeeze-excitation and stochastic depth (per sample)."""

    def __init__(self, expand: int, k: int, stride: int, cin: int, cout: int, drop_p: float) -> None:
        super().__init__()
        mid = cin * expand
        layers: list[nn.Module] = [] if mid == cin else [_conv_bn_act(cin, mid, 1)]
        layers += [_conv_bn_act(mid, mid, k, stride, groups=mid), SqueezeExcitation(mid, max(1, cin // 4)),
                   _conv_bn_act(mid, cout, 1, act=False)]
        self.block = nn.Sequential(*layers)
        self.residual = stride == 1 and cin == cout
        self.drop_p = drop_p

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.block(x)
        if not self.residual:
            return y
        if self.training and self.drop_p > 0:
            keep = torch.empty((y.shape[0],) + (1,) * (y.dim() - 1), dtype=y.dtype, device=y.device).bernoulli_(1 - self.drop_p)
            y = y * keep / (1 - self.drop_p)
        return y + x


class EfficientNetB0(nn.Module):
    """torchvision's ``efficientnet_b0`` without its classifier (same modules, same
    state-dict keys); ``forward`` returns the outputs of the ``features`` stages named in
    ``stages``."""

    def __init__(self, stochastic_depth_p: float = 0.2) -> None:
        super().__init__()
        total = sum(s[-1] for s in _B0_STAGES)
        layers: list[nn.Module] = [_conv_bn_act(3, 32, 3, 2)]
        i = 0
        for expand, k, stride, cin, cout, n in _B0_STAGES:
            blocks = []
            for j in range(n):
                blocks.append(MBConv(expand, k, stride if j == 0 else 1, cin if j == 0 else cout, cout, stochastic_depth_p * i / total))
                i += 1
            layers.append(nn.Sequential(*blocks))
        layers.append(_conv_bn_act(320, 1280, 1))
        self.features = nn.Sequential(*layers)
        for m in self.modules():  # torchvision's initialisation
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor, stages: tuple[int, ...] = B0_FPN_STAGES) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in stages:
                out.append(x)
            if i >= max(stages):
                break
        return out


class EfficientNetFPN(nn.Module):
    """EfficientNet-B0, then an FPN over its stages {5, 6, 8} (1/16, 1/32, 1/32) merged top
    down and brought to 1/8 of the input: the paper's image branch."""

    def __init__(self, out_channels: int) -> None:
        super().__init__()
        self.net = EfficientNetB0()
        self.lateral = nn.ModuleList([nn.Conv2d(B0_STAGE_CHANNELS[s], out_channels, 1) for s in B0_FPN_STAGES])
        self.smooth = nn.Sequential(nn.Conv2d(out_channels, out_channels, 3, 1, 1, bias=False), nn.BatchNorm2d(out_channels), nn.ReLU(inplace=True))
        self.out_channels = out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        H, W = x.shape[-2:]
        feats = [lat(f) for lat, f in zip(self.lateral, self.net(x))]
        top = feats[-1]
        for f in reversed(feats[:-1]):  # coarse to fine: upsample, add the lateral
            top = f + F.interpolate(top, size=f.shape[-2:], mode="bilinear", align_corners=False)
        eighth = (-(-H // 8), -(-W // 8))
        return self.smooth(F.interpolate(top, size=eighth, mode="bilinear", align_corners=False))


def load_backbone_weights(net: EfficientNetB0, path: Path) -> None:
    """Load a torchvision-format ``efficientnet_b0`` state dict from ``path`` into ``net``,
    strictly. Raises TrainError (one line) for a missing or unreadable file, and for a state
    dict with missing, unexpected or misshapen keys (naming the first few of each)."""
    if not path.is_file():
        raise TrainError(f"backbone weights '{path}' do not exist (no weights are downloaded; save torchvision's efficientnet_b0 state dict there)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:  # no torch file, or one of other objects than tensors (a pickled module)
        raise TrainError(f"backbone weights '{path}' are not a state dict of tensors saved by torch.save; save torchvision's "
                         "efficientnet_b0 weights as torch.save(model.state_dict(), path)") from err
    except Exception as err:  # noqa: BLE001 - torch raises many types for bad files
        raise TrainError(f"backbone weights '{path}' cannot be read: {err}".splitlines()[0]) from err
    for wrapper in ("state_dict", "model"):  # training scripts often save {"model": state_dict}
        if isinstance(state, dict) and isinstance(state.get(wrapper), dict):
            state = state[wrapper]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise TrainError(f"backbone weights '{path}' hold no state dict (a mapping of names to tensors)")
    own = {**net.state_dict(), **B0_CLASSIFIER}
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    shaped = [f"{k} {tuple(state[k].shape)} (expected {tuple(v.shape)})" for k, v in own.items() if k in state and state[k].shape != v.shape]

    def few(keys: list[str]) -> str:
        return ", ".join(keys[:4]) + (f" and {len(keys) - 4} more" if len(keys) > 4 else "")

    if missing or unexpected or shaped:
        parts = [f"{len(missing)} missing keys ({few(missing)})" if missing else "",
                 f"{len(unexpected)} unexpected keys ({few(unexpected)})" if unexpected else "",
                 f"{len(shaped)} keys of another shape ({few(shaped)})" if shaped else ""]
        raise TrainError(f"backbone weights '{path}' are not torchvision's efficientnet_b0 state dict: "
                         + "; ".join(p for p in parts if p))
    net.load_state_dict({k: v for k, v in state.items() if k not in B0_CLASSIFIER}, strict=True)


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


class SmallCNN(nn.Module):
    """A small CNN to 1/8 resolution with an FPN-style merge of the last two scales (the
    tiny preset's image branch)."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.s1 = nn.Sequential(_block(3, c // 2, 2), _block(c // 2, c // 2))
        self.s2 = nn.Sequential(_block(c // 2, c, 2), ResBlock(c, c))
        self.s3 = nn.Sequential(_block(c, 2 * c, 2), ResBlock(2 * c, 2 * c))
        self.s4 = nn.Sequential(_block(2 * c, 2 * c, 2), ResBlock(2 * c, 2 * c))
        self.merge = ResBlock(4 * c, 2 * c)
        self.out_channels = 2 * c

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x3 = self.s3(self.s2(self.s1(x)))
        x4 = F.interpolate(self.s4(x3), size=x3.shape[-2:], mode="bilinear", align_corners=False)
        return self.merge(torch.cat([x3, x4], 1))
