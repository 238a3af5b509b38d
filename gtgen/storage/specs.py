"""Array specifications: the one way gtgen declares an on-disk array.

Each store format (``gtgen/storage/schema.py``) is a list of :class:`ArraySpec`;
``data_schema.md`` mirrors those lists and a test checks that they agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ArraySpec:
    """One array: path in the store, dtype, shape (symbols), units, frame, fill, meaning."""

    path: str
    dtype: str
    shape: str
    units: str
    frame: str
    fill: str
    doc: str
    # the ``shards.precision`` key whose step the values are stored at as CF packed
    # integers of ``dtype`` (``storage/packing.py``); "" for an array stored as it is
    packed: str = ""
    # the codec of its chunks (``storage/codecs.py``'s CODECS) when not packed: "lz4" for
    # the intermediate stores' float grids, read once by the next stage
    codec: str = "zstd"

    def fill_value(self) -> object:
        """Return the fill value as a Python object for zarr (a packed array's NaN sentinel)."""
        if self.packed:
            from gtgen.storage.packing import fill_of

            return fill_of(self.dtype)
        if self.fill == "NaN":
            return float("nan")
        if self.fill in ("-", ""):
            return 0
        return np.dtype(self.dtype).type(float(self.fill) if "float" in self.dtype else int(self.fill)).item()

    def axes(self) -> list[str]:
        """Return the shape's symbols, e.g. ['S', 'n_m', 'n_m']."""
        return [d.strip() for d in self.shape.strip("()").split(",") if d.strip()]


def find(specs: list[ArraySpec], path: str) -> ArraySpec:
    """Return the spec of array ``path`` in ``specs``."""
    for s in specs:
        if s.path == path:
            return s
    raise KeyError(path)


def row_shape(s: ArraySpec, dims: dict[str, int]) -> tuple[int, ...]:
    """Return one row's shape (all axes but the first) of ``s``; ``dims`` gives the symbols."""
    return tuple(int(dims[d]) if d in dims else int(d) for d in s.axes()[1:])


def markdown_table(specs: list[ArraySpec]) -> str:
    """Return ``specs`` as the markdown table used in data_schema.md."""
    rows = ["| array | dtype | shape | units | frame | fill | meaning |", "|---|---|---|---|---|---|---|"]
    rows += [f"| `{s.path}` | {s.dtype} | {s.shape} | {s.units} | {s.frame} | {s.fill} | {s.doc} |" for s in specs]
    return "\n".join(rows)


def dimension_names(spec: ArraySpec) -> list[str]:
    """Return xarray-friendly dimension names of ``spec`` (from its shape symbols)."""
    leaf = spec.path.rsplit("/", 1)[-1]
    if leaf in ("x_m", "y_m", "sample"):  # a dimension coordinate: named as its dimension
        return [leaf]
    named = {"S": "sample", "R": "rejected", "P": "point", "H": "row", "W": "col", "S + 1": "sample_edge", "C": "camera"}
    out: list[str] = []
    grid_axes = iter(("x_m", "y_m"))
    for i, sym in enumerate(spec.axes()):
        if sym in named:
            out.append(named[sym])
        elif sym.startswith("n_") or sym in ("n", "nx", "ny"):
            out.append(next(grid_axes))
        else:
            out.append(f"{leaf}_{i}")
    return out
