"""Small statistics the report's parts share."""

from __future__ import annotations

import numpy as np

from gtgen import codes

REGIONS = {code: codes.REGIONS[code] for code in codes.LABELLED}
# The paper's Tab. I: each region's share of the labelled cells [%], per range
PAPER_REGION_SHARE_PCT = {"micro": {"obs_pc": 33.3, "obs_f": 46.4, "unobs": 20.3},
                          "short": {"obs_pc": 18.5, "obs_f": 34.8, "unobs": 46.7}}
# The paper's grey "X-Racer at t" rows: Tab. I, elevation MAE [m] per region and the share
# of a region's labelled cells the stack predicts [%] (None: not printed); Tab. II, fatal
# risk (the F1 as printed there, and the share of cells with a risk [%])
PAPER_XRACER_AT_T = {
    "micro": {"mae_m": {"obs_pc": 0.217, "obs_f": 0.307, "unobs": 0.747}, "coverage_pct": {"obs_pc": None, "obs_f": 74.0, "unobs": 45.0},
              "risk": {"mse": 0.0056, "precision": 0.618, "recall": 0.541, "f1": 0.721, "coverage_pct": 70.0}},
    "short": {"mae_m": {"obs_pc": 0.225, "obs_f": 0.642, "unobs": 2.421}, "coverage_pct": {"obs_pc": None, "obs_f": 90.0, "unobs": 83.0},
              "risk": {"mse": 0.0110, "precision": 0.878, "recall": 0.537, "f1": 0.667, "coverage_pct": 90.0}},
}


def region_shares(coverage: dict[str, float]) -> dict[str, float | None]:
    """Return each labelled region's share of the labelled cells [%] from a coverage
    (every region's share of all cells, no_label included); None without labelled cells."""
    tot = sum(coverage.get(name, 0.0) for name in REGIONS.values())
    return {name: (round(100.0 * coverage.get(name, 0.0) / tot, 1) if tot else None) for name in REGIONS.values()}


def quantiles(x: np.ndarray) -> dict[str, float]:
    """Return min, 5th percentile, median and max of the finite values of ``x``."""
    x = x[np.isfinite(x)]
    if not len(x):
        return {}
    return {"min": round(float(x.min()), 4), "p05": round(float(np.quantile(x, 0.05)), 4),
            "median": round(float(np.median(x)), 4), "max": round(float(x.max()), 4)}
