"""``gtgen train``: the M&M-lite trainer (the paper's tables: ``gtgen.train.evaluation``).

``train`` runs on the configured device and precision, in one process or under torchrun
(DDP, ``gtgen.train.distributed``); the sample order (``gtgen.train.sampler``), the mirror
draws, the pillar draws and the model's own randomness all depend on the seed and the step
only, so a resumed run continues exactly where an uninterrupted one would be. A run folder
records the dataset it was trained on, and is resumed only on it (``gtgen.train.runs``).
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
from gtgen.errors import ConfigError, GtgenError, RankError, TrainError
from gtgen.runtime.output import check_replace, lock, output_folder, owned, point_link, remove, write_json
from gtgen.runtime.progress import track
from gtgen.storage.dataset import DatasetStore
from gtgen.train import distributed as D
from gtgen.train.augment import mirror
from gtgen.train.checkpoint import load_checkpoint, save_checkpoint
from gtgen.train.data import ShardDataset, for_dataset
from gtgen.train.evaluation import (  # EVAL_ROWS and the evaluations re-exported: the CLI, scripts and users import them here
    BEST_METRIC,
    EVAL_ROWS,  # noqa: F401
    evaluate,  # noqa: F401
    evaluate_seeds,  # noqa: F401
    mean_and_spread,  # noqa: F401
    predict_sample,  # noqa: F401
    run_eval,
)
from gtgen.train.loss import total_loss
from gtgen.train.memory import check_memory
from gtgen.train.model import MMLite
from gtgen.train.network import build_model, parameter_counts, to_device  # build_model re-exported too
from gtgen.train.network import collate as _collate
from gtgen.train.presets import preset_overrides  # noqa: F401  (re-exported)
from gtgen.train.runs import METRICS, check_resume, dataset_record
from gtgen.train.sampler import StepBatchSampler

log = logging.getLogger(__name__)

# the files a run writes in its folder (beside tb/, where TensorBoard only adds event files)
RUN_FILES = ("gtgen-config.yaml", "ckpt.pt", "best.pt", METRICS, "train.csv", "val.csv")
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
    tc = for_dataset(tc, DatasetStore(dataset).cameras, str(dataset))
    cfg = cfg.model_copy(update={"train": tc})
    procs = D.torchrun_env()
    dev = D.resolve_device(tc.device, procs)
    try:  # before any work: the kernel kills a run that does not fit
        check_memory(tc, dev, D.resolve_precision(tc.precision, dev), procs.world)
    except TrainError as err:  # every process finds the same: rank 0 reports it
        raise (err if procs.main else RankError(str(err))) from None
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
    (None if empty), without the evaluation's baselines (the loss and the validation read
    neither). The test split (drives held out whole) is never trained on."""
    ds = ShardDataset(dataset, tc, split="train", baselines=False)
    if len(ds) == 0:
        ds = ShardDataset(dataset, tc, split=None, baselines=False)
        ds.indices = ds.indices[ds.store.meta("split")[ds.indices] != codes.TEST]
        if len(ds) == 0:
            raise TrainError(f"dataset '{dataset}' has only test samples (drives held out whole); nothing to train on")
        log.warning("the train split is empty; training on every sample outside the test split")
    val = ShardDataset(dataset, tc, split="val", baselines=False) if tc.val_every else None
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
        if state is not None:
            try:
                check_resume(state, ds.store, run_dir)
            except TrainError as err:  # every process finds the same: rank 0 reports it
                raise (err if procs.main else RankError(str(err))) from None
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
            batch = to_device(_augment(batch, tc, step, procs.rank, sampler.used), dev)
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
        write_json(run_dir / METRICS, {
            "dataset": dataset_record(ds.store), "history": history, "seconds": secs, "device": str(dev), "precision": precision, "processes": procs.world,
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
    return {"preset": tc.preset, "train": tc.model_dump(mode="json"), "data_config": ds.data_cfg.model_dump(mode="json"), "cameras": ds.store.cameras,
            "model": model.state_dict(), "optim": opt.state_dict(), "sched": sched.state_dict(), "scaler": scaler.state_dict(),
            "step": step, "history": history, "best": best, "dataset": dataset_record(ds.store)}


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
        res = run_eval(model, val, tc, dev, precision, baselines=False)
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


def _link_latest(run_dir: Path) -> str | None:
    """Point ``runs/latest`` at ``run_dir`` unless something of the user's is there (a
    folder, a file, a symlink to anything but a run folder gtgen wrote); return why not."""
    return point_link(run_dir.parent / "latest", run_dir, lambda p: owned(p / CONFIG_FILE))


