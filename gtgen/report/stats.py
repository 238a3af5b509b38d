"""Small statistics the report's parts share."""

from __future__ import annotations

import numpy as np

from gtgen import codes

REGIONS = {code: codes.REGIONS[code] for code in codes.LABELLED}


def quantiles(x: np.ndarray) -> dict[str, float]:
    """Return min, 5th percentile, median and max of the finite values of ``x``."""
    x = x[np.isfinite(x)]
    if not len(x):
        return {}
    return {"min": round(float(x.min()), 4), "p05": round(float(np.quantile(x, 0.05)), 4),
            "median": round(float(np.median(x)), 4), "max": round(float(x.max()), 4)}
