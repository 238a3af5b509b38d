"""The fused-label store written by ``gtgen fuse`` (Zarr v3), defined once here."""

from __future__ import annotations

from gtgen.config import RANGES
from gtgen.format import ArraySpec, find

FUSED_STORE = "gtgen-fused"
FUSED_VERSION = 1

FUSED_ARRAYS: list[ArraySpec] = [
    ArraySpec("samples/reason", "uint8", "(S,)", "code", "-", "-", "0 = fused, else why not (gtgen.reasons)"),
]
for _r in RANGES:
    _f = "vehicle frame at t"
    FUSED_ARRAYS += [
        ArraySpec(f"fused/{_r}/elevation_m", "float32", "(S, n, n)", "m, rel. base z at t", _f, "NaN", "mean elevation of confident observations in the window"),
        ArraySpec(f"fused/{_r}/confidence", "float32", "(S, n, n)", "0..1", _f, "NaN", "max confidence in the window"),
        ArraySpec(f"fused/{_r}/risk", "float32", "(S, n, n)", "0..1", _f, "NaN", "latest risk with confidence >= risk_min_conf"),
        ArraySpec(f"fused/{_r}/count", "uint16", "(S, n, n)", "maps", _f, "0", "observations averaged into the elevation"),
        ArraySpec(f"fused/{_r}/last_dt_s", "float32", "(S, n, n)", "s, rel. t", _f, "NaN", "stamp of the last observation minus t"),
        ArraySpec(f"fused/{_r}/region", "uint8", "(S, n, n)", "code", _f, "0", "1 observed past/current, 2 observed future, 3 unobserved"),
        ArraySpec(f"xracer/{_r}/elevation_m", "float32", "(S, n, n)", "m, rel. base z at t", _f, "NaN", "X-Racer map at t (latest stamped <= t), resampled"),
        ArraySpec(f"xracer/{_r}/risk", "float32", "(S, n, n)", "0..1", _f, "NaN", "X-Racer risk at t"),
        ArraySpec(f"xracer/{_r}/confidence", "float32", "(S, n, n)", "0..1", _f, "NaN", "X-Racer confidence at t"),
    ]


def spec(path: str) -> ArraySpec:
    """Return the spec of fused-store array ``path``."""
    return find(FUSED_ARRAYS, path)
