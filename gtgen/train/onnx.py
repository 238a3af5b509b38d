"""``gtgen export onnx``: a trained M&M-lite as one ONNX graph, for onnxruntime or TensorRT
in a ROS node.

The graph is the network from the pillars on: the caller picks the voxel points the way
``gtgen.train.pillars.pillarize`` does (cells of the short grid, at most
``max_points_per_pillar`` first points per pillar, ``max_pillars_test`` pillars) and
computes the raw and prior grids as ``gtgen.train.data.ShardDataset`` does. Inputs, for a
batch of B samples (``INPUTS``; S / M = the checkpoint's short / micro size, H x W its
image size, n the number of picked points):

========================  ====================  ==============================================
input                     shape, dtype          meaning
========================  ====================  ==============================================
images                    (B, 4, 3, H, W) uint8  RGB bytes of the cameras front, left, right,
                                                back (the graph normalises them: ImageNet mean
                                                and std)
K                         (B, 4, 3, 3) float32   intrinsics at H x W [px]
T_target_cam              (B, 4, 4, 4) float32   target <- camera optical frame [m]
pillar_points             (n, 3) float32         picked voxel points, target frame [m]
pillar_cells              (n,) int64             their cells: b * S^2 + ix * S + iy
raw                       (B, 2, S, S) float32   min z / elevation_clip_m (0 where none), validity
prior, prior_micro        (B, 2, S|M, S|M)       filled smoothed min z (scaled), distance to points
========================  ====================  ==============================================

Outputs (``OUTPUTS``): ``micro_elevation``, ``micro_risk`` (B, M, M) and ``short_elevation``,
``short_risk`` (B, S, S); elevations scaled (multiply by ``elevation_clip_m`` for metres),
risk 0..1. Grids are indexed (x, y), x forward, cell 0 at the most negative coordinate.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from gtgen.runtime.output import atomic_output, signature

INPUTS = ("images", "K", "T_target_cam", "pillar_points", "pillar_cells", "raw", "prior", "prior_micro")
OUTPUTS = ("micro_elevation", "micro_risk", "short_elevation", "short_risk")
OPSET = 18  # ScatterElements with a max reduction (the pillars' max-pool)


class Deployable(nn.Module):
    """The model with the ONNX graph's inputs and outputs (``INPUTS``, ``OUTPUTS``)."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, images, K, T_target_cam, pillar_points, pillar_cells, raw, prior, prior_micro):  # noqa: N803
        feats = self.model.pillars.encode(pillar_points, pillar_cells, images.shape[0])
        out = self.model.decode({"images": images, "K": K, "T_target_cam": T_target_cam, "raw": raw, "prior": prior,
                                 "prior_micro": prior_micro}, feats)
        return tuple(out[k.replace("_", "/", 1)] for k in OUTPUTS)


def deploy_inputs(model: nn.Module, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
    """Return the graph's inputs for a collated ``ShardDataset`` batch (the testing pillars)."""
    from gtgen.train.pillars import pillarize

    pp = model.pillars
    pts, cells = pillarize(batch["points"], batch["n_points"], pp.bev_size, pp.bev_res, pp.caps[1], pp.per_pillar)
    return (batch["images"], batch["K"], batch["T_target_cam"], pts, cells, batch["raw"], batch["prior"], batch["prior_micro"])


@dataclass
class OnnxResult:
    out: Path
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    preset: str
    step: int


def example_inputs(tc, n_points: int = 1000) -> tuple[torch.Tensor, ...]:
    """Return graph inputs of the right shapes and types for ``tc`` (batch 1; the values
    do not matter to the graph: it has no branch on data)."""
    H, W, S, M = tc.image_height, tc.image_width, tc.short_size, tc.micro_size
    K = torch.tensor([[W / 2, 0.0, W / 2 - 0.5], [0.0, W / 2, H / 2 - 0.5], [0.0, 0.0, 1.0]]).expand(1, 4, 3, 3)
    g = torch.Generator().manual_seed(0)
    return (torch.randint(0, 256, (1, 4, 3, H, W), dtype=torch.uint8, generator=g), K.contiguous(), torch.eye(4).expand(1, 4, 4, 4).contiguous(),
            torch.randn(n_points, 3, generator=g), torch.randint(0, S * S, (n_points,), generator=g), torch.zeros(1, 2, S, S),
            torch.zeros(1, 2, S, S), torch.zeros(1, 2, M, M))


def export_onnx(ckpt: Path, out: Path, overwrite: bool = False) -> OnnxResult:
    """Write the checkpoint's network to ``out`` as ONNX (opset ``OPSET``; batch 1, the
    number of pillar points free), through torch's TorchScript-based exporter (a second, not
    minutes, for this graph). The model's ``doc_string`` carries gtgen's signature (a later
    export may replace the file; anything else there only with ``overwrite``)."""
    from gtgen.train.checkpoint import load_checkpoint
    from gtgen.train.trainer import _trained_model

    state, tc, data_cfg = load_checkpoint(ckpt)
    model = _trained_model(state, tc, data_cfg).requires_grad_(False)
    args = example_inputs(tc)
    net = Deployable(model).eval()
    with atomic_output(out, overwrite) as tmp, torch.no_grad(), warnings.catch_warnings():
        # the tracer warns of every Python branch on a shape: the graph is for these shapes
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        torch.onnx.export(net, args, str(tmp), dynamo=False, opset_version=OPSET, input_names=list(INPUTS), output_names=list(OUTPUTS),
                          dynamic_axes={"pillar_points": {0: "n"}, "pillar_cells": {0: "n"}})
        import onnx

        m = onnx.load(str(tmp))
        m.producer_name, m.doc_string = "gtgen", signature()
        onnx.save(m, str(tmp))
    return OnnxResult(out, INPUTS, OUTPUTS, state["preset"], state["step"])
