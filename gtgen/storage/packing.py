"""CF packed integers: how the dataset stores its float grids and points.

Contract (the CF conventions' packed data, section 8.1, as xarray's ``decode_cf`` reads
it): an array stored as integers whose attributes hold ``scale_factor``, ``add_offset``
and ``_FillValue`` holds ``value = stored * scale_factor + add_offset``, and NaN where
``stored == _FillValue``. The zarr ``fill_value`` of such an array is the same sentinel,
so a chunk never written reads as NaN too. gtgen's readers (``storage/stores.py``) unpack
through :func:`packing_of` of the array's attributes; xarray (``xr.open_zarr``) does it
by itself, and zarr-python users apply the three attributes.

Why: the labels are accurate to about 5 cm, but float32 grids keep noise in their low
mantissa bits that zstd cannot compress. Integers at a stated step (``shards.precision``:
1 mm elevations, 1/1000 risk and confidence, 1 ms times, 1 cm points) lose nothing a
user can see and compress several-fold (``bench/bytes.py``).

Values beyond the integer range of the step are refused (:class:`PackingError`, naming
the array, the value and the setting to coarsen), never clipped: a clipped label is a
silently wrong label. Infinities are refused the same way.

Oracle: ``tests/test_packing.py`` (round trips within half a step of the float values,
NaN, range errors, xarray and zarr-python against gtgen's readers).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen.errors import GtgenError

CF_KEYS = ("scale_factor", "add_offset", "_FillValue")


class PackingError(GtgenError, ValueError):
    """A value cannot be stored at its array's step (out of the integer range, or infinite)."""


def fill_of(dtype: Any) -> int:
    """Return the sentinel that stands for NaN in packed ``dtype``: its minimum if signed,
    its maximum if unsigned (a value no packed step reaches)."""
    info = np.iinfo(np.dtype(dtype))
    return int(info.min if info.min < 0 else info.max)


@dataclass(frozen=True)
class Packing:
    """Floats stored as ``dtype`` integers of ``scale_factor`` steps from ``add_offset``."""

    dtype: str
    scale_factor: float
    add_offset: float = 0.0
    setting: str = ""  # the config key of the step, named in errors

    @property
    def fill(self) -> int:
        """The stored value of NaN (``_FillValue``)."""
        return fill_of(self.dtype)

    def attrs(self) -> dict[str, Any]:
        """Return the CF attributes of an array packed so."""
        return {"scale_factor": float(self.scale_factor), "add_offset": float(self.add_offset), "_FillValue": self.fill}

    def limits(self) -> tuple[float, float]:
        """Return the lowest and highest value that can be stored [the array's units]."""
        info = np.iinfo(np.dtype(self.dtype))
        lo, hi = (int(info.min) + 1, int(info.max)) if info.min < 0 else (0, int(info.max) - 1)
        return lo * self.scale_factor + self.add_offset, hi * self.scale_factor + self.add_offset

    def pack(self, values: Any, name: str = "") -> NDArray:
        """Return ``values`` as the stored integers (NaN -> ``_FillValue``, the rest rounded
        to the nearest step); raise PackingError for a value out of range or infinite."""
        v = np.asarray(values, np.float64)
        q = np.asarray(v - self.add_offset)  # in place from here: one temporary a grid, not five
        q /= self.scale_factor
        np.rint(q, out=q)
        info = np.iinfo(np.dtype(self.dtype))
        lo, hi = (int(info.min) + 1, int(info.max)) if info.min < 0 else (0, int(info.max) - 1)
        nan = np.isnan(v)
        fits = q >= lo
        fits &= q <= hi
        fits |= nan
        if not fits.all():
            bad = ~fits
            worst = float(v[bad].flat[np.argmax(np.abs(v[bad]).flat)])
            a, b = self.limits()
            raise PackingError(f"array '{name}': value {worst:g} cannot be stored at a step of {self.scale_factor:g} "
                               f"as {self.dtype} (range {a:g} .. {b:g}); coarsen {self.setting or 'the step'}")
        q[nan] = self.fill
        return q.astype(self.dtype)

    def unpack(self, stored: Any, dtype: Any = np.float32) -> NDArray:
        """Return the floats of ``stored`` integers (``_FillValue`` -> NaN) as ``dtype``."""
        s = np.asarray(stored)
        out = s.astype(np.float64) * self.scale_factor + self.add_offset
        out[s == self.fill] = np.nan
        return out.astype(dtype, copy=False)


def packing_of(attrs: Any, dtype: Any) -> Packing | None:
    """Return the packing an array's attributes state (None: not packed)."""
    if "scale_factor" not in attrs or np.dtype(dtype).kind not in "iu":
        return None
    if int(attrs.get("_FillValue", fill_of(dtype))) != fill_of(dtype):
        raise PackingError(f"_FillValue {attrs.get('_FillValue')} of a packed {np.dtype(dtype)} array is not gtgen's {fill_of(dtype)}")
    return Packing(str(np.dtype(dtype)), float(attrs["scale_factor"]), float(attrs.get("add_offset", 0.0)))


def packing_for(spec: Any, precision: Any) -> Packing | None:
    """Return how array ``spec`` (an ``ArraySpec``) is stored at the steps of
    ``precision`` (``shards.precision``); None for an array stored as it is."""
    if not spec.packed:
        return None
    return Packing(spec.dtype, float(getattr(precision, spec.packed)), 0.0, f"shards.precision.{spec.packed}")
