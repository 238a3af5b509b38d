"""Small statistics the report's parts share."""

from __future__ import annotations

import numpy as np

from gtgen import codes

REGIONS = {code: codes.REGIONS[code] for code in codes.LABELLED}
# The paper's Tab. I: each region's share of the labelled cells [%], per range
PAPER_REGION_SHARE_PCT = {"micro": {"obs_pc": 33.3, "obs_f": 46.4, "unobs": 20.3},
                          "short": {"obs_pc": 18.5, "obs_f": 34.8, "unobs": 46.7}}


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
