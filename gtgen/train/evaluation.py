"""``gtgen eval``: the paper's tables (Tab. I / II metrics, per region) of a checkpoint on a
dataset, the mean and spread over seeds, and one sample's prediction (``gtgen viz --ckpt``).

The tables hold the model's rows (on all labelled cells, on X-Racer's and on the raw grid's
cells: like for like) and the baselines' (X-Racer at t, the raw min-z grid, and that grid
nearest-filled to every cell); the result records the dataset it was computed on
(``train.runs``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from gtgen.config import CAMERAS, GtgenConfig, TrainConfig
from gtgen.errors import TrainError
from gtgen.grids import nearest_filled
from gtgen.runtime.progress import track
from gtgen.storage.dataset import DatasetStore
from gtgen.train import distributed as D
from gtgen.train.checkpoint import load_checkpoint
from gtgen.train.data import ShardDataset, camera_mismatch
from gtgen.train.loss import total_loss
from gtgen.train.metrics import Consistency, ElevationMAE, RiskMetrics
from gtgen.train.model import MMLite
from gtgen.train.network import build_model, collate, to_device
from gtgen.train.runs import dataset_record

# the eval's elevation rows (JSON keys under "elevation"/<range>), in table order
EVAL_ROWS = {
    "model": "M&M-lite",
    "model_on_xracer_cells": "M&M-lite on X-Racer's cells",
    "model_on_raw_cells": "M&M-lite on the raw cells",
    "xracer": "X-Racer at t",
    "raw": "raw elevation (min z)",
    "raw_nearest": "raw min z, nearest-filled",
}


# the validation metric best.pt is chosen by (lower is better): the mean of the micro and
# short elevation MAE (of the ranges the model predicts) over all labelled cells of the val split [m]
BEST_METRIC = "total_mae_m"


def run_eval(model: MMLite, ds: ShardDataset, tc: TrainConfig, dev: torch.device, precision: str, baselines: bool = True,
              progress: str | None = None) -> dict:
    """Return the paper's tables of ``model`` (in eval mode) on ``ds``, batched on ``dev``, for
    the ranges it predicts (the consistency only with both); with ``baselines`` also the
    X-Racer and raw rows (read from ``ds``: made with its ``baselines`` on); plus the loss."""
    if baselines and not ds.baselines:
        raise ValueError("run_eval: the baseline rows need a ShardDataset made with baselines=True")
    clip = tc.elevation_clip_m
    ranges = tc.predicted_ranges
    rows = EVAL_ROWS if baselines else {"model": EVAL_ROWS["model"]}
    acc = {r: {m: ElevationMAE() for m in rows} for r in ranges}
    risk = {r: {m: RiskMetrics(tc.fatal_risk) for m in (("model", "xracer") if baselines else ("model",))} for r in ranges}
    cons = Consistency()
    loss_sum, n = 0.0, 0
    loader = DataLoader(ds, batch_size=max(1, tc.batch_size), shuffle=False, num_workers=tc.workers, collate_fn=collate,
                        pin_memory=dev.type == "cuda")
    batches = track(loader, progress) if progress else loader
    with torch.no_grad():
        for cpu in batches:
            batch = to_device(cpu, dev)
            with D.autocast(dev, precision):
                out = model(batch)
            out = {k: v.float() for k, v in out.items()}
            loss, _ = total_loss(out, batch, tc)
            B = len(cpu["index"])
            loss_sum += float(loss) * B
            n += B
            pred = {k: v.cpu().numpy() for k, v in out.items()}
            for r in ranges:
                lab = cpu[f"{r}/elevation"].numpy() * clip
                reg = cpu[f"{r}/region"].numpy()
                pe = pred[f"{r}/elevation"] * clip
                acc[r]["model"].add(pe, lab, reg)
                risk[r]["model"].add(pred[f"{r}/risk"], cpu[f"{r}/risk"].numpy())
                if not baselines:
                    continue
                raw = cpu[f"{r}/raw_elevation"].numpy()
                xr = cpu[f"{r}/xr_elevation"].numpy()
                # like for like with the stack and with the raw grid: only where each has a value
                acc[r]["model_on_xracer_cells"].add(np.where(np.isfinite(xr), pe, np.nan), lab, reg)
                acc[r]["model_on_raw_cells"].add(np.where(np.isfinite(raw), pe, np.nan), lab, reg)
                acc[r]["xracer"].add(xr, lab, reg)
                acc[r]["raw"].add(raw, lab, reg)
                acc[r]["raw_nearest"].add(np.stack([nearest_filled(x) for x in raw]), lab, reg)
                risk[r]["xracer"].add(cpu[f"{r}/xr_risk"].numpy(), cpu[f"{r}/risk"].numpy())
            if len(ranges) == 2:
                cons.add(pred["micro/elevation"] * clip, pred["short/elevation"] * clip)
    elevation = {r: {m: a.table() for m, a in acc[r].items()} for r in acc}
    totals = [elevation[r]["model"]["total"]["mae_m"] for r in ranges]
    return {"elevation": elevation, "risk": {r: {m: v.table() for m, v in risk[r].items()} for r in risk},
            "consistency_mae_m": cons.value(), "loss": loss_sum / max(n, 1),
            BEST_METRIC: float(np.mean(totals)) if all(t is not None for t in totals) else float("nan")}


def evaluate(dataset: Path, ckpt: Path, preset: str | None = None, split: str | None = "val", device: str | None = None,
             baselines: bool = True) -> dict:
    """Return the paper's tables for the checkpoint on ``split`` of ``dataset`` (None: all),
    computed on ``device`` (default ``auto``: CUDA when present), batched, with the
    checkpoint's loader workers and precision: the rows of the ranges the model predicts
    (``ranges``), with the X-Racer and raw rows unless ``baselines`` is off."""
    state, tc, data_cfg = load_checkpoint(ckpt)
    if preset is not None and preset != state["preset"]:
        raise TrainError(f"checkpoint '{ckpt}' is of preset {state['preset']!r}, not {preset!r}")
    ds = _eval_dataset(dataset, ckpt, state, tc, split, baselines)
    used = split or "all"
    if len(ds) == 0:
        raise TrainError(f"dataset '{dataset}' has no {split!r} samples (its {ds.store.n_samples} samples are all in other splits); "
                         "evaluate with --split all, or build more drives")
    if abs(ds.data_cfg.grids.short.length_m - data_cfg.grids.short.length_m) > 1e-6:
        raise TrainError(f"checkpoint was trained on short grids of {data_cfg.grids.short.length_m} m; the dataset has {ds.data_cfg.grids.short.length_m} m")
    dev = D.resolve_device(device or "auto")
    model = trained_model(state, tc, data_cfg).to(dev)
    t0 = time.perf_counter()
    res = run_eval(model, ds, tc, dev, D.resolve_precision(tc.precision, dev), baselines, progress="eval: batches")
    secs = time.perf_counter() - t0
    return {
        "dataset": dataset_record(ds.store), "split": used, "samples": len(ds), "preset": state["preset"], "step": state["step"], "ranges": list(tc.predicted_ranges),
        "elevation": res["elevation"], "risk": res["risk"], "consistency_mae_m": res["consistency_mae_m"],
        "grid": {"micro_size": tc.micro_size, "short_size": tc.short_size},
        "device": str(dev), "seconds_per_sample": secs / len(ds),
    }


def _eval_dataset(dataset: Path, ckpt: Path, state: dict, tc: TrainConfig, split: str | None, baselines: bool = True) -> ShardDataset:
    """Return the samples of ``split`` of ``dataset`` as the checkpoint's model reads them;
    raise TrainError when its image branch was trained on other cameras than the dataset's."""
    if tc.cameras:
        err = camera_mismatch(list(state.get("cameras", CAMERAS)), DatasetStore(dataset).cameras, ckpt, dataset)
        if err is not None:
            raise err
    return ShardDataset(dataset, tc, split=split, baselines=baselines)


def evaluate_seeds(dataset: Path, ckpts: list[Path], split: str | None = "val", device: str | None = None) -> dict:
    """Evaluate each checkpoint (one per training seed) and return the first's layout with
    every metric replaced by its mean over the checkpoints, plus ``spread``: the same
    layout with the standard deviations (None where any checkpoint has none), and ``runs``:
    each checkpoint's own result."""
    runs = [evaluate(dataset, c, None, split, device) for c in ckpts]
    if len({r["preset"] for r in runs}) > 1:
        raise TrainError(f"checkpoints of several presets: {sorted({r['preset'] for r in runs})}; evaluate one preset's seeds together")
    if len({tuple(r["ranges"]) for r in runs}) > 1:
        raise TrainError(f"checkpoints predicting other ranges: {sorted({'+'.join(r['ranges']) for r in runs})}; evaluate one model's seeds together")
    out = mean_and_spread(runs)
    out["runs"] = [{"ckpt": str(c), **r} for c, r in zip(ckpts, runs)]
    return out


def mean_and_spread(results: list[dict]) -> dict:
    """Return ``results[0]``'s layout with every metric replaced by its mean over the results,
    plus ``spread``: the same layout with the standard deviations (0 for one result; None
    where any result has none)."""
    out = _reduce(results, np.mean)
    out["spread"] = _reduce(results, lambda v: np.std(v, ddof=1) if len(v) > 1 else 0.0)
    return out


def _reduce(results: list, fn):
    """Return ``results[0]``'s nested layout with each numeric leaf reduced over the results."""
    first = results[0]
    if isinstance(first, dict):
        return {k: _reduce([r[k] for r in results], fn) for k in first}
    if (isinstance(first, (int, float)) and not isinstance(first, bool)) or first is None:
        if any(r is None for r in results):
            return None
        v = float(fn(np.array(results, np.float64)))
        return int(v) if all(isinstance(r, int) for r in results) and v.is_integer() else v  # counts stay integers
    return first


def trained_model(state: dict, tc: TrainConfig, data_cfg: GtgenConfig) -> MMLite:
    """Return the checkpoint's model in eval mode. Raises TrainError (one line) when its
    weights do not fit the model its config describes."""
    model = build_model(tc.model_copy(update={"backbone_weights": None}), data_cfg)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as err:  # torch lists every mismatch, one per line after a heading
        lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
        raise TrainError(f"checkpoint's weights do not fit its model ({lines[-1] if lines else err}); retrain with this version") from err
    return model.eval()


def predict_sample(dataset: Path, ckpt: Path, index: int, device: str | None = None) -> dict[str, np.ndarray]:
    """Return the model's maps for dataset sample ``index`` (elevation in metres), computed
    on ``device`` (default ``auto``)."""
    state, tc, data_cfg = load_checkpoint(ckpt)
    dev = D.resolve_device(device or "auto")
    model = trained_model(state, tc, data_cfg).to(dev)
    ds = _eval_dataset(dataset, ckpt, state, tc, None)
    pos = np.nonzero(ds.indices == index)[0]
    if not len(pos):
        raise TrainError(f"sample {index} is not in the dataset (0..{ds.store.n_samples - 1})")
    with torch.no_grad(), D.autocast(dev, D.resolve_precision(tc.precision, dev)):
        pred = model(to_device(collate([ds[int(pos[0])]]), dev))
    return {k: v[0].float().cpu().numpy() * (tc.elevation_clip_m if k.endswith("elevation") else 1.0) for k, v in pred.items()}
