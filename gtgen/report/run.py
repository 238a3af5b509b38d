"""``gtgen report``: a dataset card and QA figures; label error against synth truth."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gtgen import codes
from gtgen.config import RANGES, stored_config
from gtgen.report.figures import figures, signal_figure
from gtgen.report.labels import label_errors
from gtgen.report.rejections import rejection_truth
from gtgen.report.stats import quantiles
from gtgen.storage.stores import open_dataset


@dataclass
class Report:
    """Numbers of the dataset card (also written as JSON beside the figures)."""

    card: dict = field(default_factory=dict)
    truth: dict = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)


def _coverage(g, r: str, idx: np.ndarray) -> dict[str, float]:
    counts = np.zeros(len(codes.REGIONS), np.int64)
    for k in idx:
        counts += np.bincount(g[f"labels/{r}/region"][int(k)].ravel(), minlength=len(codes.REGIONS))
    tot = max(int(counts.sum()), 1)
    return {codes.REGIONS[i]: counts[i] / tot for i in codes.REGIONS}


def build_report(dataset: Path, out_dir: Path, max_truth_samples: int = 40) -> Report:
    """Return the report of ``dataset`` and write its JSON and PNG figures into ``out_dir``."""
    import json

    g, info = open_dataset(dataset)
    attrs = info.attrs
    S = info.n_samples
    rep = Report()
    rej_reason = g["rejected/reason"][:]
    fit = g["meta/icp_fitness"][:] if S else np.zeros(0)
    rfit = g["rejected/icp_fitness"][:]
    idx = np.unique(np.linspace(0, S - 1, min(S, max_truth_samples)).astype(int)) if S else np.zeros(0, int)
    split = g["meta/split"][:] if S else np.zeros(0)
    rep.card = {
        "dataset": str(dataset),
        "samples_kept": S,
        "samples_kept_by_odometry": int(np.isnan(fit).sum()),  # over set-aside tiles, no ICP (dem.carry_over_m)
        "samples_rejected": {codes.reason_name(c): int((rej_reason == c).sum()) for c in np.unique(rej_reason)},
        "split": {name: int((split == code).sum()) for code, name in codes.SPLITS.items()},
        "coverage": {r: {k: round(float(v), 4) for k, v in _coverage(g, r, idx).items()} for r in RANGES} if S else {},
        "icp_fitness": quantiles(np.concatenate([fit, rfit[np.isfinite(rfit)]])),
        "icp_rmse_m": quantiles(g["meta/icp_rmse_m"][:]) if S else {},
        "alignment": attrs.drives[0].alignment if len(attrs.drives) == 1 else {},
    }
    bag_paths = [b.path for d in attrs.drives for b in d.bags]
    from gtgen.synth.truth import Truth

    truth = Truth.find(bag_paths)
    cfg = stored_config(attrs.config, f"dataset '{dataset}'")
    if truth is not None and S:
        rep.truth = label_errors(g, cfg, truth, idx)
    if truth is not None:
        rep.truth["rejections"] = rejection_truth(g, cfg, truth, attrs)
    out_dir.mkdir(parents=True, exist_ok=True)
    rep.figures = figures(g, rep, out_dir, fit, rfit, rej_reason) + [signal_figure(g, cfg.dem, out_dir)]
    (out_dir / "report.json").write_text(json.dumps({"card": rep.card, "truth": rep.truth}, indent=2, default=float))
    return rep
