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
images                    (B, C, 3, H, W) uint8  RGB bytes of the C cameras the model was trained
                                                on, in their order (``OnnxResult.cameras``; the
                                                graph normalises them: ImageNet mean and std)
K                         (B, C, 3, 3) float32   intrinsics at H x W [px]
T_target_cam              (B, C, 4, 4) float32   target <- camera optical frame [m]
pillar_points             (n, 3) float32         picked voxel points, target frame [m]
pillar_cells              (n,) int64             their cells: b * S^2 + ix * S + iy
raw                       (B, 2, S, S) float32   min z / elevation_clip_m (0 where none), validity
prior, prior_micro        (B, 2, S|M, S|M)       filled smoothed min z (scaled), distance to points
========================  ====================  ==============================================

Outputs (``OUTPUTS``): ``micro_elevation``, ``micro_risk`` (B, M, M) and ``short_elevation``,
``short_risk`` (B, S, S); elevations scaled (multiply by ``elevation_clip_m`` for metres),
risk 0..1. Grids are indexed (x, y), x forward, cell 0 at the most negative coordinate.

A model that leaves inputs out or predicts one range (``train.cameras``, ``points``,
``raw_elevation``, ``ranges``) has only the inputs and outputs it uses, in this order
(``graph_inputs``, ``graph_outputs``); for a micro-only model S is its BEV grid's size
(``gtgen.train.model.bev_grid``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from gtgen.config import CAMERAS
from gtgen.runtime.output import atomic_output, signature

INPUTS = ("images", "K", "T_target_cam", "pillar_points", "pillar_cells", "raw", "prior", "prior_micro")
OUTPUTS = ("micro_elevation", "micro_risk", "short_elevation", "short_risk")
OPSET = 18  # ScatterElements with a max reduction (the pillars' max-pool)


def graph_inputs(tc) -> tuple[str, ...]:
    """Return the names of the graph's inputs for a model of ``TrainConfig`` ``tc``."""
    used = {"images": tc.cameras, "K": tc.cameras, "T_target_cam": tc.cameras, "pillar_points": tc.points, "pillar_cells": tc.points,
            "raw": tc.raw_elevation, "prior": tc.raw_elevation, "prior_micro": tc.raw_elevation and "micro" in tc.predicted_ranges}
    return tuple(n for n in INPUTS if used[n])


def graph_outputs(tc) -> tuple[str, ...]:
    """Return the names of the graph's outputs for a model of ``TrainConfig`` ``tc``."""
    return tuple(n for n in OUTPUTS if n.split("_")[0] in tc.predicted_ranges)


class Deployable(nn.Module):
    """The model with the ONNX graph's inputs and outputs (``graph_inputs``, ``graph_outputs``)."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model
        self.inputs, self.outputs = graph_inputs(model.tc), graph_outputs(model.tc)

    def forward(self, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        named = dict(zip(self.inputs, args))
        grids = [named[n] for n in ("images", "raw") if n in named]
        feats = None
        if self.model.pillars is not None:  # the batch size from an input that has one (a points-only graph: 1)
            feats = self.model.pillars.encode(named["pillar_points"], named["pillar_cells"], grids[0].shape[0] if grids else 1)
        out = self.model.decode(named, feats)
        return tuple(out[k.replace("_", "/", 1)] for k in self.outputs)


def deploy_inputs(model: nn.Module, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
    """Return the graph's inputs for a collated ``ShardDataset`` batch (the testing pillars)."""
    named = dict(batch)
    pp = model.pillars
    if pp is not None:
        from gtgen.train.pillars import pillarize

        named["pillar_points"], named["pillar_cells"] = pillarize(batch["points"], batch["n_points"], pp.bev_size, pp.bev_res,
                                                                  pp.caps[1], pp.per_pillar)
    return tuple(named[n] for n in graph_inputs(model.tc))


@dataclass
class OnnxResult:
    out: Path
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    preset: str
    step: int
    cameras: list[str]  # the order of the images input's cameras


def example_inputs(tc, bev_size: int, n_points: int = 1000, cameras: int = 4) -> tuple[torch.Tensor, ...]:
    """Return graph inputs (``graph_inputs``) of the right shapes and types for ``tc``, a BEV
    grid of ``bev_size`` cells and ``cameras`` cameras (batch 1; the values do not matter to
    the graph: it has no branch on data)."""
    H, W, S, M, C = tc.image_height, tc.image_width, bev_size, tc.micro_size, cameras
    K = torch.tensor([[W / 2, 0.0, W / 2 - 0.5], [0.0, W / 2, H / 2 - 0.5], [0.0, 0.0, 1.0]]).expand(1, C, 3, 3)
    g = torch.Generator().manual_seed(0)
    every = {"images": torch.randint(0, 256, (1, C, 3, H, W), dtype=torch.uint8, generator=g), "K": K.contiguous(),
             "T_target_cam": torch.eye(4).expand(1, C, 4, 4).contiguous(), "pillar_points": torch.randn(n_points, 3, generator=g),
             "pillar_cells": torch.randint(0, S * S, (n_points,), generator=g), "raw": torch.zeros(1, 2, S, S),
             "prior": torch.zeros(1, 2, S, S), "prior_micro": torch.zeros(1, 2, M, M)}
    return tuple(every[n] for n in graph_inputs(tc))


def export_onnx(ckpt: Path, out: Path, overwrite: bool = False) -> OnnxResult:
    """Write the checkpoint's network to ``out`` as ONNX (opset ``OPSET``; batch 1, the
    number of pillar points free), through torch's TorchScript-based exporter (a second, not
    minutes, for this graph). The model's ``doc_string`` carries gtgen's signature (a later
    export may replace the file; anything else there only with ``overwrite``)."""
    from gtgen.train.checkpoint import load_checkpoint
    from gtgen.train.evaluation import trained_model
    from gtgen.train.model import bev_grid

    state, tc, data_cfg = load_checkpoint(ckpt)
    model = trained_model(state, tc, data_cfg).requires_grad_(False)
    cameras = list(state.get("cameras", CAMERAS)) if tc.cameras else []
    args = example_inputs(tc, bev_grid(tc, data_cfg.grids)[1], cameras=len(cameras))
    net = Deployable(model).eval()
    with atomic_output(out, overwrite, file=True) as tmp, torch.no_grad(), warnings.catch_warnings():
        # the tracer warns of every Python branch on a shape: the graph is for these shapes
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        torch.onnx.export(net, args, str(tmp), dynamo=False, opset_version=OPSET, input_names=list(net.inputs),
                          output_names=list(net.outputs),
                          dynamic_axes={n: {0: "n"} for n in ("pillar_points", "pillar_cells") if n in net.inputs})
        import onnx

        m = onnx.load(str(tmp))
        m.producer_name, m.doc_string = "gtgen", signature()
        onnx.save(m, str(tmp))
    return OnnxResult(out, net.inputs, net.outputs, state["preset"], state["step"], cameras)
