"""Training-time augmentation: the left-right mirror of a whole sample.

Reflecting the world across the vehicle's x axis (y -> -y in the target frame) gives
another drive that could have happened: the valley on the other side, the same ground
ahead. Every input and label of the sample is mirrored consistently, so the model sees
twice the geometry of a drive without any label changing meaning:

- grids ``(.., n, n)`` indexed (x, y) with cell centres symmetric about 0: flipped along y;
- voxel points: y negated;
- cameras: each image flipped left-right, the principal point reflected (``cx -> W - 1 -
  cx``, ROS pixel centres), and the camera's pose ``T_target_cam -> M T_target_cam Mc`` with
  ``M = diag(1, -1, 1)`` in the target frame and ``Mc = diag(-1, 1, 1)`` in the optical frame
  (still a rotation: two reflections). Each camera becomes its own mirror image in place, a
  camera that could have been there, so any rig works: the network treats its cameras
  alike (one backbone, features splatted by their geometry), and no camera need be
  another's twin (the left one of a symmetric rig lands where the right one was).

Mirroring keeps "ahead" ahead (a rotation would not), and the future-observed region of a
drive lies ahead of the vehicle.
"""

from __future__ import annotations

import torch

# the batch keys that are (x, y) grids in the last two dimensions
GRID_KEYS = ("raw", "prior", "prior_micro") + tuple(
    f"{r}/{k}" for r in ("micro", "short") for k in ("elevation", "risk", "region", "xr_elevation", "xr_risk", "raw_elevation"))


def mirror(batch: dict[str, torch.Tensor], which: torch.Tensor) -> dict[str, torch.Tensor]:
    """Return ``batch`` (collated, leading sample axis) with the samples where ``which``
    (bool, (B,)) is true mirrored left-right; the others, and keys it does not know
    (``index``, ``n_points``), unchanged. The input tensors are not modified."""
    if not bool(which.any()):
        return batch
    out = dict(batch)

    def sel(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return torch.where(which.view(-1, *([1] * (x.dim() - 1))), y, x)

    for k in GRID_KEYS:
        if k in batch:
            out[k] = sel(batch[k], batch[k].flip(-1))
    if "points" in batch:
        out["points"] = sel(batch["points"], batch["points"] * batch["points"].new_tensor([1.0, -1.0, 1.0]))
    if "images" in batch:
        W = batch["images"].shape[-1]
        out["images"] = sel(batch["images"], batch["images"].flip(-1))
        if "K" in batch:
            K = batch["K"].clone()
            K[..., 0, 2] = (W - 1) - K[..., 0, 2]
            out["K"] = sel(batch["K"], K)
    if "T_target_cam" in batch:
        T = batch["T_target_cam"]
        M = torch.diag(T.new_tensor([1.0, -1.0, 1.0, 1.0]))
        Mc = torch.diag(T.new_tensor([-1.0, 1.0, 1.0, 1.0]))
        out["T_target_cam"] = sel(batch["T_target_cam"], M @ T @ Mc)
    return out
