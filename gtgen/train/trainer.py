"""``gtgen train`` / ``gtgen eval``: the M&M-lite trainer and the paper's tables."""

from __future__ import annotations

import logging
import random
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from gtgen.config import GtgenConfig, TrainConfig, save_config, stored_config
from gtgen.errors import ConfigError, TrainError
from gtgen.runtime.output import atomic_output, lock, signature, write_json
from gtgen.runtime.progress import track
from gtgen.train.augment import mirror
from gtgen.train.data import ShardDataset, nearest_filled
from gtgen.train.loss import total_loss
from gtgen.train.metrics import Consistency, ElevationMAE, RiskMetrics
from gtgen.train.model import MMLite
from gtgen.train.presets import preset_overrides  # noqa: F401  (re-exported: the CLI and users import it here)

log = logging.getLogger(__name__)

# the eval's elevation rows (JSON keys under "elevation"/<range>), in table order
EVAL_ROWS = {
    "model": "M&M-lite",
    "model_on_xracer_cells": "M&M-lite on X-Racer's cells",
    "model_on_raw_cells": "M&M-lite on the raw cells",
    "xracer": "X-Racer at t",
    "raw": "raw elevation (min z)",
    "raw_nearest": "raw min z, nearest-filled",
}
CKPT_VERSION = 4  # 2: heads correct a smoothed min-z prior; 3: the prior filled everywhere is an input, four-level U-Net;
# 4: the prior filled on a pyramid, the micro prior at the points grid's resolution, images as bytes


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _collate(items: list[dict]) -> dict:
    return {k: torch.stack([it[k] for it in items]) for k in items[0]}


def _to(batch: dict, device: str) -> dict:
    return {k: v.to(device) for k, v in batch.items()}


def build_model(tc: TrainConfig, data_cfg: GtgenConfig) -> MMLite:
    """Return a fresh model; loads ``backbone_weights`` into the image backbone if given.
    Raises ConfigError for grids the model cannot tile: it predicts the micro maps from the
    centre half of the short grid, and its encoder halves the short grid three times."""
    gm, gs = data_cfg.grids.micro, data_cfg.grids.short
    if abs(2 * gm.length_m - gs.length_m) > 1e-6:
        raise ConfigError(f"grids.micro spans {gm.length_m:g} m and grids.short {gs.length_m:g} m: M&M-lite predicts the micro maps "
                          f"from the centre half of the short grid, so the micro grid must span {gs.length_m / 2:g} m")
    if tc.short_size < 16 or tc.micro_size < 8:
        raise ConfigError(f"train.short_size {tc.short_size} / micro_size {tc.micro_size}: the model needs at least 16 short and 8 micro cells")
    model = MMLite(tc, gs.length_m)
    if tc.backbone_weights:
        p = Path(tc.backbone_weights)
        if not p.is_file():
            raise TrainError(f"backbone weights '{p}' do not exist (no weights are downloaded)")
        state = torch.load(p, map_location="cpu", weights_only=True)
        missing, unexpected = model.lift.backbone.load_state_dict(state, strict=False)
        log.info("backbone weights: %d missing, %d unexpected keys", len(missing), len(unexpected))
    # channels-last weights: oneDNN's convolutions run about 20 % faster on the tiny preset's
    # CPU training step (and it is the layout GPU tensor cores prefer)
    return model.to(memory_format=torch.channels_last)


@dataclass
class TrainResult:
    run_dir: Path
    steps: int
    first_loss: float
    last_loss: float
    seconds: float
    ckpt: Path


def _save(path: Path, payload: dict) -> None:
    with atomic_output(path) as tmp:
        torch.save(payload, tmp)


def train(dataset: Path, run_dir: Path, cfg: GtgenConfig, resume: bool = False, max_steps: int | None = None) -> TrainResult:
    """Train M&M-lite on the train split of ``dataset``; checkpoints and metrics go to ``run_dir``
    (locked while training, so a second run into it stops with a one-line error)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    with lock(run_dir), lock(dataset, shared=True):
        return _train(dataset, run_dir, cfg, resume, max_steps)


def _train(dataset: Path, run_dir: Path, cfg: GtgenConfig, resume: bool, max_steps: int | None) -> TrainResult:
    tc = cfg.train
    seed_everything(tc.seed)
    ds = ShardDataset(dataset, tc, split="train")
    if len(ds) == 0:
        ds = ShardDataset(dataset, tc, split=None)
        log.warning("the train split is empty; training on every sample")
    model = build_model(tc, ds.data_cfg).to(tc.device)
    opt = torch.optim.Adam(model.parameters(), lr=tc.lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=tc.lr, total_steps=tc.steps)
    ckpt_path = run_dir / "ckpt.pt"
    step, history = _resume(ckpt_path, tc, model, opt, sched) if resume else (0, [])
    save_config(cfg, run_dir / "gtgen-config.yaml")
    g = torch.Generator()
    g.manual_seed(tc.seed + step)
    loader = DataLoader(ds, batch_size=tc.batch_size, shuffle=True, num_workers=tc.workers, collate_fn=_collate,
                        drop_last=len(ds) >= tc.batch_size, generator=g, persistent_workers=tc.workers > 0)
    end = tc.steps if max_steps is None else min(tc.steps, step + max_steps)
    t0 = time.perf_counter()
    model.train()

    def batches():
        while True:
            yield from loader

    it = batches()

    def status() -> str:
        return f"loss {history[-1]['total']:.4f}" if history else ""

    for _ in track(range(step, end), "train:", status=status):
        batch = _to(_augment(next(it), tc, step), tc.device)
        pred = model(batch)
        loss, parts = total_loss(pred, batch, tc)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        sched.step()
        step += 1
        history.append({"step": step, **parts, "lr": sched.get_last_lr()[0]})
        if step % tc.ckpt_every == 0 or step == end:
            _save(ckpt_path, {"written_by": signature(), "version": CKPT_VERSION, "preset": tc.preset, "train": tc.model_dump(mode="json"),
                              "data_config": ds.data_cfg.model_dump(mode="json"), "model": model.state_dict(),
                              "optim": opt.state_dict(), "sched": sched.state_dict(), "step": step, "history": history,
                              "torch_rng": torch.get_rng_state()})
    secs = time.perf_counter() - t0
    write_json(run_dir / "metrics.json", {"history": history, "seconds": secs}, indent=1)
    _link_latest(run_dir)
    first = history[0]["total"] if history else float("nan")
    return TrainResult(run_dir, step, first, history[-1]["total"] if history else float("nan"), secs, ckpt_path)


def _augment(batch: dict, tc: TrainConfig, step: int) -> dict:
    """Return the training batch with each sample mirrored left-right with probability
    ``tc.mirror_p``; the draw depends on the seed and the step only (a resumed run draws
    the same)."""
    if tc.mirror_p <= 0:
        return batch
    g = torch.Generator().manual_seed(tc.seed * 1_000_003 + step)
    return mirror(batch, torch.rand(len(batch["index"]), generator=g) < tc.mirror_p)


def _resume(ckpt_path: Path, tc: TrainConfig, model: MMLite, opt, sched) -> tuple[int, list]:
    """Load the run's checkpoint into the model, optimizer and schedule; return (step, history)."""
    if not ckpt_path.is_file():
        raise TrainError(f"--resume: no checkpoint at '{ckpt_path}'")
    state, _, _ = _load_ckpt(ckpt_path, tc)
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["optim"])
    sched.load_state_dict(state["sched"])
    torch.set_rng_state(state["torch_rng"])
    return state["step"], state["history"]


def _link_latest(run_dir: Path) -> None:
    """Point ``runs/latest`` at ``run_dir`` (unless a real folder of that name is there)."""
    latest = run_dir.parent / "latest"
    if latest.is_symlink() or not latest.exists():
        if latest.is_symlink():
            latest.unlink()
        latest.symlink_to(run_dir.name)


def _load_ckpt(path: Path, tc: TrainConfig | None = None) -> tuple[dict, TrainConfig, GtgenConfig]:
    """Return a checkpoint's state with its validated train and data configs."""
    if not path.is_file():
        raise TrainError(f"checkpoint '{path}' does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # noqa: BLE001 - torch raises many types for bad files
        raise TrainError(f"checkpoint '{path}' cannot be read: {err}".splitlines()[0]) from err
    if not isinstance(state, dict) or state.get("version") != CKPT_VERSION:
        raise TrainError(f"'{path}' is not a gtgen checkpoint of version {CKPT_VERSION} (found {state.get('version') if isinstance(state, dict) else type(state).__name__!r}); retrain with this version")
    if tc is not None and state["preset"] != tc.preset:
        raise TrainError(f"checkpoint '{path}' is of preset {state['preset']!r}; expected {tc.preset!r}")
    from pydantic import ValidationError

    try:
        return state, TrainConfig.model_validate(state["train"]), stored_config(state["data_config"], f"checkpoint '{path}'")
    except (KeyError, ValidationError) as err:
        first = err.errors()[0] if isinstance(err, ValidationError) else {"loc": (str(err),), "msg": "missing"}
        where = ".".join(str(x) for x in first["loc"])
        raise TrainError(f"checkpoint '{path}' holds a config this gtgen does not accept ({where}: {first['msg']}); retrain with this version") from err


def evaluate(dataset: Path, ckpt: Path, preset: str | None = None, split: str | None = "val") -> dict:
    """Return the paper's tables for the checkpoint on ``split`` of ``dataset`` (None: all)."""
    state, tc, data_cfg = _load_ckpt(ckpt)
    if preset is not None and preset != state["preset"]:
        raise TrainError(f"checkpoint '{ckpt}' is of preset {state['preset']!r}, not {preset!r}")
    ds = ShardDataset(dataset, tc, split=split)
    used = split or "all"
    if len(ds) == 0:
        raise TrainError(f"dataset '{dataset}' has no {split!r} samples (its {ds.store.n_samples} samples are all in other splits); "
                         "evaluate with --split all, or build more drives")
    if abs(ds.data_cfg.grids.short.length_m - data_cfg.grids.short.length_m) > 1e-6:
        raise TrainError(f"checkpoint was trained on short grids of {data_cfg.grids.short.length_m} m; the dataset has {ds.data_cfg.grids.short.length_m} m")
    model = _trained_model(state, tc, data_cfg)
    clip = tc.elevation_clip_m
    acc = {r: {m: ElevationMAE() for m in EVAL_ROWS} for r in ("micro", "short")}
    risk = {r: {m: RiskMetrics(tc.fatal_risk) for m in ("model", "xracer")} for r in ("micro", "short")}
    cons = Consistency()
    loader = DataLoader(ds, batch_size=max(1, tc.batch_size), shuffle=False, num_workers=0, collate_fn=_collate)
    with torch.no_grad():
        for batch in track(loader, "eval: batches"):
            pred = model(batch)
            for r in ("micro", "short"):
                lab = batch[f"{r}/elevation"].numpy() * clip
                reg = batch[f"{r}/region"].numpy()
                pe = pred[f"{r}/elevation"].numpy() * clip
                raw = batch[f"{r}/raw_elevation"].numpy()
                xr = batch[f"{r}/xr_elevation"].numpy()
                acc[r]["model"].add(pe, lab, reg)
                # like for like with the stack and with the raw grid: only where each has a value
                acc[r]["model_on_xracer_cells"].add(np.where(np.isfinite(xr), pe, np.nan), lab, reg)
                acc[r]["model_on_raw_cells"].add(np.where(np.isfinite(raw), pe, np.nan), lab, reg)
                acc[r]["xracer"].add(xr, lab, reg)
                acc[r]["raw"].add(raw, lab, reg)
                acc[r]["raw_nearest"].add(np.stack([nearest_filled(x) for x in raw]), lab, reg)
                risk[r]["model"].add(pred[f"{r}/risk"].numpy(), batch[f"{r}/risk"].numpy())
                risk[r]["xracer"].add(batch[f"{r}/xr_risk"].numpy(), batch[f"{r}/risk"].numpy())
            cons.add(pred["micro/elevation"].numpy() * clip, pred["short/elevation"].numpy() * clip)
    return {
        "split": used, "samples": len(ds), "preset": state["preset"], "step": state["step"],
        "elevation": {r: {m: a.table() for m, a in acc[r].items()} for r in acc},
        "risk": {r: {m: v.table() for m, v in risk[r].items()} for r in risk},
        "consistency_mae_m": cons.value(),
        "grid": {"micro_size": tc.micro_size, "short_size": tc.short_size},
    }


def evaluate_seeds(dataset: Path, ckpts: list[Path], split: str | None = "val") -> dict:
    """Evaluate each checkpoint (one per training seed) and return the first's layout with
    every metric replaced by its mean over the checkpoints, plus ``spread``: the same
    layout with the standard deviations (None where any checkpoint has none), and ``runs``:
    each checkpoint's own result."""
    runs = [evaluate(dataset, c, None, split) for c in ckpts]
    if len({r["preset"] for r in runs}) > 1:
        raise TrainError(f"checkpoints of several presets: {sorted({r['preset'] for r in runs})}; evaluate one preset's seeds together")
    out = _reduce(runs, np.mean)
    out["spread"] = _reduce(runs, lambda v: np.std(v, ddof=1) if len(v) > 1 else 0.0)
    out["runs"] = [{"ckpt": str(c), **r} for c, r in zip(ckpts, runs)]
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


def _trained_model(state: dict, tc: TrainConfig, data_cfg: GtgenConfig) -> MMLite:
    """Return the checkpoint's model in eval mode."""
    model = build_model(tc.model_copy(update={"backbone_weights": None}), data_cfg)
    model.load_state_dict(state["model"])
    return model.eval()


def predict_sample(dataset: Path, ckpt: Path, index: int) -> dict[str, np.ndarray]:
    """Return the model's maps for dataset sample ``index`` (elevation in metres)."""
    state, tc, data_cfg = _load_ckpt(ckpt)
    model = _trained_model(state, tc, data_cfg)
    ds = ShardDataset(dataset, tc)
    pos = np.nonzero(ds.indices == index)[0]
    if not len(pos):
        raise TrainError(f"sample {index} is not in the dataset (0..{ds.store.n_samples - 1})")
    with torch.no_grad():
        pred = model(_collate([ds[int(pos[0])]]))
    return {k: v[0].numpy() * (tc.elevation_clip_m if k.endswith("elevation") else 1.0) for k, v in pred.items()}
