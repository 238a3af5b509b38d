"""``gtgen report``: a dataset card and QA figures; label error against synth truth."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gtgen import codes
from gtgen.config import RANGES
from gtgen.errors import GtgenError
from gtgen.report.figures import FIGURES, figures, signal_figure
from gtgen.report.labels import LabelErrors
from gtgen.report.rejections import rejection_truth
from gtgen.report.stats import PAPER_REGION_SHARE_PCT, quantiles, region_shares
from gtgen.report.xracer import xracer_at_t
from gtgen.runtime.output import check_replace, write_json
from gtgen.storage.dataset import DatasetStore

REPORT_JSON = "report.json"
XRACER_SAMPLES = 400  # samples (evenly spread) the X-Racer-at-t rows are measured on


@dataclass
class Report:
    """Numbers of the dataset card (also written as JSON beside the figures)."""

    card: dict = field(default_factory=dict)
    truth: dict = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)


def _coverage(ds: DatasetStore, r: str, idx: np.ndarray) -> dict[str, float]:
    counts = np.zeros(len(codes.REGIONS), np.int64)
    region = ds.grid("labels", r, "region")
    for k in idx:
        counts += np.bincount(region[int(k)].ravel(), minlength=len(codes.REGIONS))
    tot = max(int(counts.sum()), 1)
    return {codes.REGIONS[i]: counts[i] / tot for i in codes.REGIONS}


def _spread(idx: np.ndarray, n: int) -> np.ndarray:
    """Return at most ``n`` of the sample indices ``idx``, evenly spread."""
    return idx[np.unique(np.linspace(0, len(idx) - 1, min(len(idx), n)).astype(int))] if len(idx) else idx


def build_report(dataset: Path, out_dir: Path, max_truth_samples: int = 40, overwrite: bool = False) -> Report:
    """Return the report of ``dataset`` and write its JSON and PNG figures into ``out_dir``.

    On synthetic drives, each drive's labels and placements are judged against its own
    truth (``truth/`` beside its bags), over at most ``max_truth_samples`` samples in all."""
    from gtgen.synth.truth import Truth

    if out_dir.exists() and not out_dir.is_dir():
        raise GtgenError(f"output '{out_dir}' is a file; the report writes report.json and its figures into a folder")
    for name in (*FIGURES, REPORT_JSON):  # before any work: nothing of the user's is replaced
        check_replace(out_dir / name, overwrite)
    ds = DatasetStore(dataset)
    S = ds.n_samples
    rep = Report()
    rej_reason = ds.rejected("reason")
    fit = ds.meta("icp_fitness")
    rfit = ds.rejected("icp_fitness")
    placed = np.isfinite(ds.meta("T_crs_target")[:, 0, 0])  # a drive without a DEM places none
    idx = _spread(np.arange(S), max_truth_samples)
    split = ds.meta("split")
    rep.card = {
        "dataset": str(dataset),
        "samples_kept": S,
        "samples_kept_by_odometry": int((np.isnan(fit) & placed).sum()),  # over set-aside tiles, no ICP (dem.carry_over_m)
        "samples_rejected": {codes.reason_name(c): int((rej_reason == c).sum()) for c in np.unique(rej_reason)},
        "split": {name: int((split == code).sum()) for code, name in codes.SPLITS.items()},
        "split_by_drive": _split_by_drive(ds, split),
        "image_bytes_per_sample": _image_bytes(ds),
        "scan_input": _scan_input(ds),
        "coverage": {r: {k: round(float(v), 4) for k, v in _coverage(ds, r, idx).items()} for r in RANGES} if S else {},
        "icp_fitness": quantiles(np.concatenate([fit, rfit[np.isfinite(rfit)]])),
        "icp_rmse_m": quantiles(ds.meta("icp_rmse_m")),
        "alignment": ds.info.drives[0].alignment if len(ds.info.drives) == 1 else {},
    }
    if S:  # the regions' shares of the labelled cells [%], beside the paper's (Tab. I)
        rep.card["region_share_pct"] = {r: region_shares(rep.card["coverage"][r]) for r in RANGES}
        rep.card["paper_region_share_pct"] = PAPER_REGION_SHARE_PCT
        rep.card["xracer_at_t"] = xracer_at_t(ds, _spread(np.arange(S), XRACER_SAMPLES), ds.config.train.fatal_risk)
    if S and not placed.any():  # dem-align --no-dem: the unobserved cells stay unlabelled
        none = {r: 100 * rep.card["coverage"][r][codes.REGIONS[codes.NO_LABEL]] for r in RANGES}
        rep.card["dem"] = f"no DEM: {none['micro']:.1f} % (micro) / {none['short']:.1f} % (short) of the cells unlabelled"
    truths = {d: t for d, entry in enumerate(ds.info.drives) if (t := Truth.find([b.path for b in entry.bags])) is not None}
    cfg = ds.config
    if truths and S:
        drive = ds.meta("drive")
        errors = LabelErrors()
        per_drive = max(1, max_truth_samples // len(truths))
        for d, truth in truths.items():
            errors.add(ds, cfg, truth, _spread(np.nonzero(drive == d)[0], per_drive))
        rep.truth = errors.table()
        rep.truth["drives_with_truth"] = [ds.info.drives[d].name for d in truths]
    placed_drives = {d: t for d, t in truths.items() if ds.info.drives[d].crs}  # a drive without a DEM has no placements to judge
    if placed_drives:
        rep.truth["rejections"] = rejection_truth(ds, cfg, placed_drives)
    rep.figures = figures(ds, rep, out_dir, fit, rfit, rej_reason, overwrite) + [signal_figure(ds, cfg.dem, out_dir, overwrite)]
    write_json(out_dir / REPORT_JSON, {"card": rep.card, "truth": rep.truth}, overwrite, indent=2, default=float)
    return rep


def _split_by_drive(ds: DatasetStore, split: np.ndarray) -> dict[str, dict[str, int]]:
    """Return {drive name: {split name: samples}} (every split named, zeros included)."""
    drive = ds.meta("drive")
    return {entry.name: {name: int(((drive == d) & (split == code)).sum()) for code, name in codes.SPLITS.items()}
            for d, entry in enumerate(ds.info.drives)}


def _scan_input(ds: DatasetStore) -> dict[str, float]:
    """Return what the N-scan input holds: the samples with no scan point, and the median
    points of a sample's 1 and N newest scans (empty without raw scans)."""
    if not ds.has_scans or not ds.n_samples:
        return {}
    c = ds.scan_counts()
    return {"samples_without_scans": int((c[:, -1] == 0).sum()), "median_points_newest": float(np.median(c[:, 0])),
            f"median_points_{c.shape[1]}_scans": float(np.median(c[:, -1]))}


def _image_bytes(ds: DatasetStore) -> float:
    """Return the mean bytes of a sample's stored JPEG files (of all its cameras)."""
    if not ds.n_samples or not ds.cameras:
        return 0.0
    return round(float(ds.jpeg_bytes().sum(axis=1).mean()), 1)
