"""Compare two zarr stores array by array: shapes, dtypes and values (NaN equals NaN).

    python scripts/compare_stores.py A.zarr B.zarr [--tol 1e-12] [--attrs] [--decode]

Prints one line per array (equal / max abs difference / missing) and exits 1 if any
array differs by more than ``--tol``. ``--attrs`` also lists the attribute keys whose
values differ. ``--decode`` reads CF packed arrays (``gtgen/storage/packing.py``) as the
floats they stand for and judges each against half its step (its ``scale_factor``)
instead of ``--tol``: a float dataset against a packed one. Useful after a refactor or a
speed-up that must not change outputs.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import zarr

from gtgen.storage.packing import packing_of


def arrays(group: zarr.Group, prefix: str = "") -> dict[str, zarr.Array]:
    """Return every array under ``group`` by its path."""
    out: dict[str, zarr.Array] = {}
    for name, node in group.members():
        path = f"{prefix}{name}"
        if isinstance(node, zarr.Array):
            out[path] = node
        else:
            out.update(arrays(node, path + "/"))
    return out


def _values(a: zarr.Array, decode: bool) -> tuple[np.ndarray, float]:
    """Return the values of ``a`` (as floats where packed and ``decode``) and their step (0: exact)."""
    pk = packing_of(a.attrs, a.dtype) if decode else None
    return (a[...], 0.0) if pk is None else (pk.unpack(a[...]), pk.scale_factor)


def compare(a: zarr.Array, b: zarr.Array, tol: float, decode: bool = False) -> tuple[bool, str]:
    """Return (same within ``tol``, or half the step of a packed array with ``decode``, a
    description) of two arrays."""
    (x, sa), (y, sb) = _values(a, decode), _values(b, decode)
    if x.shape != y.shape or (x.dtype != y.dtype and not (sa or sb)):
        return False, f"shape/dtype {a.shape} {a.dtype} vs {b.shape} {b.dtype}"
    step = max(sa, sb)
    if step:
        tol = step / 2 * 1.001  # rounding to the step, and float32's own rounding
    if x.dtype.kind in "fc":
        nan = np.isnan(x) != np.isnan(y)
        if nan.any():
            return False, f"NaN at {int(nan.sum())} different places"
        d = np.abs(np.where(np.isnan(x), 0, x) - np.where(np.isnan(y), 0, y))
        m = float(d.max()) if d.size else 0.0
        what = "equal" if m == 0 else f"max |diff| {m:.3g}"
        return m <= tol, what + (f" (step {step:g}: {m / step:.3f} steps)" if step and m else "")
    same = np.array_equal(x, y)
    return same, "equal" if same else f"{int((x != y).sum())} values differ"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--tol", type=float, default=0.0)
    ap.add_argument("--attrs", action="store_true")
    ap.add_argument("--decode", action="store_true", help="compare CF packed arrays as floats, within half their step")
    args = ap.parse_args()
    ga, gb = zarr.open_group(args.a, mode="r"), zarr.open_group(args.b, mode="r")
    A, B = arrays(ga), arrays(gb)
    bad = 0
    for path in sorted(set(A) | set(B)):
        if path not in A or path not in B:
            print(f"{path}: only in {'A' if path in A else 'B'}")
            bad += 1
            continue
        ok, what = compare(A[path], B[path], args.tol, args.decode)
        bad += not ok
        print(f"{path}: {what}")
    if args.attrs:
        aa, ab = ga.attrs.asdict(), gb.attrs.asdict()
        diff = sorted(k for k in set(aa) | set(ab) if aa.get(k) != ab.get(k))
        print(f"attributes that differ: {diff or 'none'}")
    print(f"{len(set(A) & set(B))} arrays compared, {bad} differ")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
