"""``gtgen train`` / ``gtgen eval``: the M&M-lite trainer and the paper's tables.

``train`` runs on the configured device and precision, in one process or under torchrun
(DDP, ``gtgen.train.distributed``); the sample order (``gtgen.train.sampler``), the mirror
draws, the pillar draws and the model's own randomness all depend on the seed and the step
only, so a resumed run continues exactly where an uninterrupted one would be.
"""

from __future__ import annotations

import contextlib
import logging
import random
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from gtgen import codes
from gtgen.config import GtgenConfig, TrainConfig, save_config
from gtgen.errors import ConfigError, GtgenError, TrainError
from gtgen.grids import nearest_filled
from gtgen.runtime.output import check_replace, lock, output_folder, owned, point_link, remove, write_json
from gtgen.runtime.progress import track
from gtgen.train import distributed as D
from gtgen.train.augment import mirror
from gtgen.train.checkpoint import load_checkpoint, save_checkpoint
from gtgen.train.data import ShardDataset
from gtgen.train.loss import total_loss
from gtgen.train.metrics import Consistency, ElevationMAE, RiskMetrics
from gtgen.train.model import MMLite, bev_grid
from gtgen.train.presets import preset_overrides  # noqa: F401  (re-exported: the CLI and users import it here)
from gtgen.train.sampler import StepBatchSampler

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
# the validation metric best.pt is chosen by (lower is better): the mean of the micro and
# short elevation MAE (of the ranges the model predicts) over all labelled cells of the val split [m]
BEST_METRIC = "total_mae_m"
# the files a run writes in its folder (beside tb/, where TensorBoard only adds event files)
RUN_FILES = ("gtgen-config.yaml", "ckpt.pt", "best.pt", "metrics.json", "train.csv", "val.csv")
CONFIG_FILE = RUN_FILES[0]
# the random streams of a step (with the seed and the step): the global batch's mirror and
# pillar draws (the same on every process), and the model's own (stochastic depth), per process
_MIRROR, _PILLARS, _MODEL = 1, 2, 3


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _step_seed(seed: int, step: int, stream: int, rank: int = 0) -> int:
    return int(np.random.SeedSequence([seed, step, stream, rank]).generate_state(1)[0])


def _collate(items: list[dict]) -> dict:
    return {k: torch.stack([it[k] for it in items]) for k in items[0]}


def _to(batch: dict, device: torch.device) -> dict:
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


@dataclass
class TrainResult:
    run_dir: Path
    steps: int
    first_loss: float
    last_loss: float
    seconds: float
    ckpt: Path
    rank: int = 0
    world: int = 1
    device: str = "cpu"
    precision: str = "32"
    samples_per_s: float = float("nan")
    data_wait_share: float = float("nan")
    peak_memory_mib: float | None = None
    best: dict | None = None
    parameters: dict[str, int] = field(default_factory=dict)
    latest_note: str | None = None  # why runs/latest was left as it is (None: it points at this run)


def _check_steps(max_steps: int | None) -> None:
    if max_steps is not None and max_steps < 1:
        raise ConfigError(f"--steps {max_steps}: expected at least 1 step")


def train(dataset: Path, run_dir: Path, cfg: GtgenConfig, resume: bool = False, max_steps: int | None = None,
          device: str | None = None, overwrite: bool = False) -> TrainResult:
    """Train M&M-lite on the train split of ``dataset``; checkpoints, curves and metrics go
    to ``run_dir`` (locked while training, so a second run into it stops with a one-line
    error). ``device`` overrides ``train.device``. Under torchrun every process calls this;
    rank 0 writes. A run that fails before its first checkpoint leaves no folder behind. A
    file of a run's name in ``run_dir`` that gtgen did not write stops the run before any
    work, unless ``overwrite``."""
    _check_steps(max_steps)
    tc = cfg.train if device is None else cfg.train.model_copy(update={"device": device})
    cfg = cfg.model_copy(update={"train": tc})
    procs = D.torchrun_env()
    dev = D.resolve_device(tc.device, procs)
    with D.process_group(procs, dev):
        return _train(dataset, run_dir, cfg, resume, max_steps, procs, dev, overwrite)


@contextlib.contextmanager
def _run_folder(run_dir: Path, ckpt: Path, overwrite: bool) -> Iterator[None]:
    """Hold the run folder's lock while the block runs (making the folder); if the block
    fails before the run's first checkpoint, remove the folders it made. A file of a run's
    name there must be gtgen's (unless ``overwrite``): the signed ones by their signature,
    the CSV curves by the signed config of the run they belong to."""
    new = not run_dir.exists()
    if run_dir.exists() and not run_dir.is_dir():
        raise TrainError(f"run folder '{run_dir}' is a file; choose another --run-dir")
    ours = owned(run_dir / CONFIG_FILE)
    for name in RUN_FILES:
        if not (ours and name.endswith(".csv")):
            check_replace(run_dir / name, overwrite)
    with output_folder(run_dir):  # the folders made for the run go if they are left empty
        try:
            with lock(run_dir):
                yield
        except BaseException:
            if new and not ckpt.exists():
                for p in list(run_dir.iterdir()):  # what the failed run wrote
                    remove(p)
            raise


def _datasets(dataset: Path, tc: TrainConfig) -> tuple[ShardDataset, ShardDataset | None]:
    """Return the train split (every sample outside test if it is empty) and the val split
    (None if empty). The test split (drives held out whole) is never trained on."""
    ds = ShardDataset(dataset, tc, split="train")
    if len(ds) == 0:
        ds = ShardDataset(dataset, tc, split=None)
        ds.indices = ds.indices[ds.store.meta("split")[ds.indices] != codes.TEST]
        if len(ds) == 0:
            raise TrainError(f"dataset '{dataset}' has only test samples (drives held out whole); nothing to train on")
        log.warning("the train split is empty; training on every sample outside the test split")
    val = ShardDataset(dataset, tc, split="val") if tc.val_every else None
    if val is not None and tc.val_max_samples is not None and len(val) > tc.val_max_samples:
        val.indices = val.indices[np.linspace(0, len(val) - 1, tc.val_max_samples).round().astype(np.int64)]
    return ds, (val if val is not None and len(val) else None)


def _train(dataset: Path, run_dir: Path, cfg: GtgenConfig, resume: bool, max_steps: int | None,
           procs: D.Processes, dev: torch.device, overwrite: bool) -> TrainResult:
    tc = cfg.train
    precision = D.resolve_precision(tc.precision, dev)
    seed_everything(tc.seed)
    ds, val = _datasets(dataset, tc)
    model = build_model(tc, ds.data_cfg).to(dev)
    counts = parameter_counts(model)
    ckpt_path = run_dir / "ckpt.pt"
    with contextlib.ExitStack() as stack:
        err = ""
        if procs.main:
            try:
                stack.enter_context(lock(dataset, shared=True))
                if resume and not ckpt_path.is_file():
                    raise TrainError(f"--resume: no checkpoint at '{ckpt_path}'")
                stack.enter_context(_run_folder(run_dir, ckpt_path, overwrite))
            except GtgenError as e:
                if procs.world == 1:
                    raise
                err = str(e)
        D.share_error(procs, err)
        state = load_checkpoint(ckpt_path, tc.preset)[0] if resume else None
        return _fit(ds, val, model, counts, cfg, run_dir, state, max_steps, procs, dev, precision, overwrite)


def _fit(ds: ShardDataset, val: ShardDataset | None, model: MMLite, counts: dict[str, int], cfg: GtgenConfig, run_dir: Path,
         state: dict | None, max_steps: int | None, procs: D.Processes, dev: torch.device, precision: str,
         overwrite: bool) -> TrainResult:
    """The training loop: every process steps, rank 0 logs, validates and checkpoints
    (replacing the user's files of a run's name only with ``overwrite``)."""
    tc = cfg.train
    if tc.sync_batchnorm and procs.world > 1 and dev.type == "cuda":
        model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
    opt = torch.optim.Adam(model.parameters(), lr=tc.lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=tc.lr, total_steps=tc.steps)
    scaler = torch.amp.GradScaler(dev.type, enabled=precision == "16-mixed")
    step, history, best = 0, [], {"step": None, BEST_METRIC: None}
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optim"])
        sched.load_state_dict(state["sched"])
        scaler.load_state_dict(state["scaler"])
        step, history, best = state["step"], state["history"], state["best"]
    if step >= tc.steps:
        raise TrainError(f"run '{run_dir}' has trained all {tc.steps} steps of its schedule; nothing to resume")
    end = tc.steps if max_steps is None else min(tc.steps, step + max_steps)
    net: torch.nn.Module = model
    if procs.world > 1:
        from torch.nn.parallel import DistributedDataParallel

        net = DistributedDataParallel(model, device_ids=[dev.index] if dev.type == "cuda" else None)
    sampler = StepBatchSampler(len(ds), tc.batch_size, tc.seed, step, procs.rank, procs.world)
    loader = DataLoader(ds, batch_sampler=sampler, num_workers=tc.workers, collate_fn=_collate,
                        pin_memory=dev.type == "cuda", persistent_workers=tc.workers > 0)
    curves = None
    if procs.main:
        save_config(cfg, run_dir / CONFIG_FILE, overwrite)
        from gtgen.train.curves import Curves

        curves = Curves(run_dir, step if state is not None else None)
    count = _global_count(procs)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    model.train()
    it = iter(loader)
    waits, busy, first = [], [], None

    def status() -> str:
        return f"loss {history[-1]['total']:.4f}" if history else ""

    t_start = time.perf_counter()
    try:
        for _ in track(range(step, end), "train:", status=status):
            t0 = time.perf_counter()
            batch = next(it)
            t1 = time.perf_counter()
            batch = _to(_augment(batch, tc, step, procs.rank, sampler.used), dev)
            torch.manual_seed(_step_seed(tc.seed, step, _MODEL, procs.rank))
            with D.autocast(dev, precision):
                pred = net(batch)
            loss, parts = total_loss({k: v.float() for k, v in pred.items()}, batch, tc, count)
            opt.zero_grad(set_to_none=True)
            scaler.scale(loss).backward()
            scaler.unscale_(opt)
            torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
            scaler.step(opt)
            scaler.update()
            sched.step()
            step += 1
            parts = _mean_parts(parts, procs, dev)
            t2 = time.perf_counter()
            waits.append(t1 - t0)
            busy.append(t2 - t1)
            first = parts["total"] if first is None else first
            row = {**parts, "lr": sched.get_last_lr()[0], "data_s": t1 - t0, "step_s": t2 - t1}
            history.append({"step": step, **row})
            if curves is not None:
                curves.log("train", step, row)
            if val is not None and (step % tc.val_every == 0 or step == end):
                if procs.main:
                    best = _validate(model, val, tc, dev, precision, step, curves, best, run_dir / "best.pt",
                                     lambda step=step, best=best: _payload(model, opt, sched, scaler, step, history, best, cfg, ds), overwrite)
                D.barrier(procs)
            if procs.main and (step % tc.ckpt_every == 0 or step == end):
                save_checkpoint(run_dir / "ckpt.pt", _payload(model, opt, sched, scaler, step, history, best, cfg, ds), overwrite)
    finally:
        if curves is not None:
            curves.close()
    secs = time.perf_counter() - t_start
    n = len(busy)
    peak = torch.cuda.max_memory_allocated(dev) / 2**20 if dev.type == "cuda" else None
    res = TrainResult(run_dir, step, first if first is not None else float("nan"), history[-1]["total"] if history else float("nan"),
                      secs, run_dir / "ckpt.pt", procs.rank, procs.world, str(dev), precision,
                      samples_per_s=n * tc.batch_size / max(sum(waits) + sum(busy), 1e-9),
                      data_wait_share=sum(waits) / max(sum(waits) + sum(busy), 1e-9), peak_memory_mib=peak,
                      best=best if best["step"] is not None else None, parameters=counts)
    if procs.main:
        write_json(run_dir / "metrics.json", {
            "history": history, "seconds": secs, "device": str(dev), "precision": precision, "processes": procs.world,
            "samples_per_s": res.samples_per_s, "data_wait_share": res.data_wait_share, "peak_memory_mib": peak,
            "best": res.best, "best_metric": BEST_METRIC, "parameters": counts}, overwrite, indent=1)
        res.latest_note = _link_latest(run_dir)
    return res


def _global_count(procs: D.Processes):
    """Return the loss's count reduction: the global count over the processes under DDP."""
    if procs.world == 1:
        from gtgen.train.loss import _local

        return _local

    def count(n: torch.Tensor) -> torch.Tensor:
        import torch.distributed as dist

        g = n.detach().clone()
        dist.all_reduce(g)
        return g.clamp(min=1) / procs.world

    return count


def _mean_parts(parts: dict[str, float], procs: D.Processes, dev: torch.device) -> dict[str, float]:
    """Return the step's loss parts of the global batch: under DDP each process holds its
    share of the global mean, so their mean over the processes."""
    if procs.world == 1:
        return parts
    v = D.mean_over(procs, torch.tensor(list(parts.values()), dtype=torch.float64, device=dev if dev.type == "cuda" else "cpu"))
    return dict(zip(parts, (float(x) for x in v.cpu())))


def _payload(model: MMLite, opt, sched, scaler, step: int, history: list, best: dict, cfg: GtgenConfig, ds: ShardDataset) -> dict:
    tc = cfg.train
    return {"preset": tc.preset, "train": tc.model_dump(mode="json"), "data_config": ds.data_cfg.model_dump(mode="json"),
            "model": model.state_dict(), "optim": opt.state_dict(), "sched": sched.state_dict(), "scaler": scaler.state_dict(),
            "step": step, "history": history, "best": best}


def _augment(batch: dict, tc: TrainConfig, step: int, rank: int, global_batch: int) -> dict:
    """Return the training batch with each sample mirrored left-right with probability
    ``tc.mirror_p`` and the random priorities of its points (PointPillars' draw). Both are
    drawn for the whole global batch from the seed and the step, and each process takes its
    slice: a resumed run, and any number of processes, draw what one uninterrupted process
    draws."""
    B = len(batch["index"])
    sl = slice(rank * B, (rank + 1) * B)
    out = dict(batch)
    if tc.mirror_p > 0:
        g = torch.Generator().manual_seed(_step_seed(tc.seed, step, _MIRROR))
        out = mirror(out, (torch.rand(global_batch, generator=g) < tc.mirror_p)[sl])
    if "points" in batch:
        g = torch.Generator().manual_seed(_step_seed(tc.seed, step, _PILLARS))
        out["point_rand"] = torch.rand(global_batch, batch["points"].shape[1], generator=g)[sl]
    return out


def _validate(model: MMLite, val: ShardDataset, tc: TrainConfig, dev: torch.device, precision: str, step: int, curves, best: dict,
              best_path: Path, payload, overwrite: bool) -> dict:
    """Validate on ``val``, log it, and save ``best.pt`` when ``BEST_METRIC`` improves;
    return the best so far."""
    model.eval()
    try:
        res = _run_eval(model, val, tc, dev, precision, baselines=False)
    finally:
        model.train()
    row = {"loss": res["loss"], BEST_METRIC: res[BEST_METRIC]}
    for r in tc.predicted_ranges:
        for reg, v in res["elevation"][r]["model"].items():
            row[f"{r}/mae_{reg}_m"] = float("nan") if v["mae_m"] is None else v["mae_m"]
        f1 = res["risk"][r]["model"]["f1"]
        row[f"{r}/risk_f1"] = float("nan") if f1 is None else f1
    if curves is not None:
        curves.log("val", step, row)
    metric = row[BEST_METRIC]
    if np.isfinite(metric) and (best[BEST_METRIC] is None or metric < best[BEST_METRIC]):
        best = {"step": step, BEST_METRIC: metric}
        p = payload()
        p["best"] = best
        save_checkpoint(best_path, p, overwrite)
    return best


def _run_eval(model: MMLite, ds: ShardDataset, tc: TrainConfig, dev: torch.device, precision: str, baselines: bool = True,
              progress: str | None = None) -> dict:
    """Return the paper's tables of ``model`` (in eval mode) on ``ds``, batched on ``dev``, for
    the ranges it predicts (the consistency only with both); with ``baselines`` also the
    X-Racer and raw rows; plus the loss."""
    clip = tc.elevation_clip_m
    ranges = tc.predicted_ranges
    rows = EVAL_ROWS if baselines else {"model": EVAL_ROWS["model"]}
    acc = {r: {m: ElevationMAE() for m in rows} for r in ranges}
    risk = {r: {m: RiskMetrics(tc.fatal_risk) for m in (("model", "xracer") if baselines else ("model",))} for r in ranges}
    cons = Consistency()
    loss_sum, n = 0.0, 0
    loader = DataLoader(ds, batch_size=max(1, tc.batch_size), shuffle=False, num_workers=tc.workers, collate_fn=_collate,
                        pin_memory=dev.type == "cuda")
    batches = track(loader, progress) if progress else loader
    with torch.no_grad():
        for cpu in batches:
            batch = _to(cpu, dev)
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


def _link_latest(run_dir: Path) -> str | None:
    """Point ``runs/latest`` at ``run_dir`` unless something of the user's is there (a
    folder, a file, a symlink to anything but a run folder gtgen wrote); return why not."""
    return point_link(run_dir.parent / "latest", run_dir, lambda p: owned(p / CONFIG_FILE))


def evaluate(dataset: Path, ckpt: Path, preset: str | None = None, split: str | None = "val", device: str | None = None,
             baselines: bool = True) -> dict:
    """Return the paper's tables for the checkpoint on ``split`` of ``dataset`` (None: all),
    computed on ``device`` (default ``auto``: CUDA when present), batched, with the
    checkpoint's loader workers and precision: the rows of the ranges the model predicts
    (``ranges``), with the X-Racer and raw rows unless ``baselines`` is off."""
    state, tc, data_cfg = load_checkpoint(ckpt)
    if preset is not None and preset != state["preset"]:
        raise TrainError(f"checkpoint '{ckpt}' is of preset {state['preset']!r}, not {preset!r}")
    ds = ShardDataset(dataset, tc, split=split)
    used = split or "all"
    if len(ds) == 0:
        raise TrainError(f"dataset '{dataset}' has no {split!r} samples (its {ds.store.n_samples} samples are all in other splits); "
                         "evaluate with --split all, or build more drives")
    if abs(ds.data_cfg.grids.short.length_m - data_cfg.grids.short.length_m) > 1e-6:
        raise TrainError(f"checkpoint was trained on short grids of {data_cfg.grids.short.length_m} m; the dataset has {ds.data_cfg.grids.short.length_m} m")
    dev = D.resolve_device(device or "auto")
    model = _trained_model(state, tc, data_cfg).to(dev)
    t0 = time.perf_counter()
    res = _run_eval(model, ds, tc, dev, D.resolve_precision(tc.precision, dev), baselines, progress="eval: batches")
    secs = time.perf_counter() - t0
    return {
        "split": used, "samples": len(ds), "preset": state["preset"], "step": state["step"], "ranges": list(tc.predicted_ranges),
        "elevation": res["elevation"], "risk": res["risk"], "consistency_mae_m": res["consistency_mae_m"],
        "grid": {"micro_size": tc.micro_size, "short_size": tc.short_size},
        "device": str(dev), "seconds_per_sample": secs / len(ds),
    }


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


def _trained_model(state: dict, tc: TrainConfig, data_cfg: GtgenConfig) -> MMLite:
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
    model = _trained_model(state, tc, data_cfg).to(dev)
    ds = ShardDataset(dataset, tc)
    pos = np.nonzero(ds.indices == index)[0]
    if not len(pos):
        raise TrainError(f"sample {index} is not in the dataset (0..{ds.store.n_samples - 1})")
    with torch.no_grad(), D.autocast(dev, D.resolve_precision(tc.precision, dev)):
        pred = model(_to(_collate([ds[int(pos[0])]]), dev))
    return {k: v[0].float().cpu().numpy() * (tc.elevation_clip_m if k.endswith("elevation") else 1.0) for k, v in pred.items()}
