"""The stack's own map at t against the labels: the paper's grey "X-Racer at t" rows of
Tab. I (elevation MAE and coverage per region) and Tab. II (fatal risk), per range.

The same measure as ``gtgen eval``'s xracer row (``gtgen.train.metrics``), but on every
sample of the dataset and without a model, so the dataset card can say how far the
stack it was made from errs like the paper's X-Racer (labels unclipped here; the eval
clips them to +-``train.elevation_clip_m``, which moves no cell of a drive's relief).
"""

from __future__ import annotations

import numpy as np

from gtgen.config import RANGES
from gtgen.report.stats import PAPER_XRACER_AT_T
from gtgen.storage.dataset import DatasetStore
from gtgen.train.metrics import ElevationMAE, RiskMetrics


def xracer_at_t(ds: DatasetStore, idx: np.ndarray, fatal_risk: float) -> dict:
    """Return per range the X-Racer-at-t elevation rows (``elevation``: per region MAE [m],
    coverage and share [%]) and fatal-risk row (``risk``: MSE, precision, recall, F1,
    coverage [%]) over samples ``idx``, with the paper's numbers under ``paper``."""
    out: dict = {}
    for r in RANGES:
        elev, risk = ElevationMAE(), RiskMetrics(fatal_risk)
        lab_e, lab_r, reg = ds.grid("labels", r, "elevation_m"), ds.grid("labels", r, "risk"), ds.grid("labels", r, "region")
        xr_e, xr_r = ds.grid("xracer", r, "elevation_m"), ds.grid("xracer", r, "risk")
        for k in idx:
            k = int(k)
            elev.add(xr_e[k], lab_e[k], reg[k])
            risk.add(xr_r[k], lab_r[k])
        out[r] = {"elevation": _rounded(elev.table()), "risk": _rounded(risk.table())}
    out["paper"] = PAPER_XRACER_AT_T
    return out


def _rounded(table: dict) -> dict:
    """Return ``table`` with its numbers rounded to 4 decimals (None kept)."""
    return {k: _rounded(v) if isinstance(v, dict) else (None if v is None else round(float(v), 4)) for k, v in table.items()}
