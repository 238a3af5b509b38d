"""The paper's evaluation (Tab. I / II), accumulated over batches; empty sets are n/a."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from gtgen import codes

REGIONS = {**{codes.REGIONS[c]: (c,) for c in codes.LABELLED}, "total": codes.LABELLED}


@dataclass
class ElevationMAE:
    """Sum of |error| and counts per region, plus the cells a method predicts at all."""

    abs_sum: dict[str, float] = field(default_factory=lambda: {k: 0.0 for k in REGIONS})
    n: dict[str, int] = field(default_factory=lambda: {k: 0 for k in REGIONS})
    n_label: dict[str, int] = field(default_factory=lambda: {k: 0 for k in REGIONS})

    def add(self, pred_m: NDArray, label_m: NDArray, region: NDArray) -> None:
        """Accumulate where the label exists; NaN predictions count against coverage only."""
        lab = np.isfinite(label_m)
        have = lab & np.isfinite(pred_m)
        for name, cs in REGIONS.items():
            m = np.isin(region, cs)
            self.n_label[name] += int((m & lab).sum())
            sel = m & have
            self.n[name] += int(sel.sum())
            self.abs_sum[name] += float(np.abs(pred_m[sel] - label_m[sel]).sum())

    def table(self) -> dict[str, dict[str, float | None]]:
        """Return per region: MAE [m] (None when no cell), coverage [%] of its labelled cells
        and its share [%] of all labelled cells (the paper's Tab. I header)."""
        total = self.n_label["total"]
        return {
            k: {"mae_m": (self.abs_sum[k] / self.n[k]) if self.n[k] else None,
                "coverage_pct": (100.0 * self.n[k] / self.n_label[k]) if self.n_label[k] else None,
                "share_pct": (100.0 * self.n_label[k] / total) if total else None}
            for k in REGIONS
        }


@dataclass
class RiskMetrics:
    """Risk MSE and precision / recall / F1 of the fatal class (risk >= threshold)."""

    threshold: float
    sq: float = 0.0
    n: int = 0
    tp: int = 0
    fp: int = 0
    fn: int = 0
    n_label: int = 0

    def add(self, pred: NDArray, label: NDArray) -> None:
        lab = np.isfinite(label)
        m = lab & np.isfinite(pred)
        self.n_label += int(lab.sum())
        self.sq += float(((pred[m] - label[m]) ** 2).sum())
        self.n += int(m.sum())
        p, t = pred[m] >= self.threshold, label[m] >= self.threshold
        self.tp += int((p & t).sum())
        self.fp += int((p & ~t).sum())
        self.fn += int((~p & t).sum())

    def table(self) -> dict[str, float | None]:
        prec = self.tp / (self.tp + self.fp) if self.tp + self.fp else None
        rec = self.tp / (self.tp + self.fn) if self.tp + self.fn else None
        f1 = 2 * prec * rec / (prec + rec) if prec is not None and rec is not None and prec + rec > 0 else None
        return {"mse": self.sq / self.n if self.n else None, "precision": prec, "recall": rec, "f1": f1,
                "coverage_pct": 100.0 * self.n / self.n_label if self.n_label else None}


@dataclass
class Consistency:
    """MAE between the micro elevation pooled to short cells and the short centre crop [m]."""

    abs_sum: float = 0.0
    n: int = 0

    def add(self, micro_m: NDArray, short_m: NDArray) -> None:
        import torch

        from gtgen.train.model import centre_half

        crop = centre_half(torch.from_numpy(np.ascontiguousarray(short_m, np.float64))).numpy()
        f = micro_m.shape[-1] / crop.shape[-1]
        if f != int(f):
            from scipy.ndimage import zoom

            pooled = zoom(micro_m, (1,) * (micro_m.ndim - 2) + (crop.shape[-2] / micro_m.shape[-2], crop.shape[-1] / micro_m.shape[-1]), order=1)
        else:
            f = int(f)
            pooled = micro_m.reshape(*micro_m.shape[:-2], crop.shape[-2], f, crop.shape[-1], f).mean(axis=(-3, -1))
        self.abs_sum += float(np.abs(pooled - crop).sum())
        self.n += int(crop.size)

    def value(self) -> float | None:
        return self.abs_sum / self.n if self.n else None
