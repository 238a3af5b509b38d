"""The one way to open each kind of store, and the attributes every store carries."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gtgen.errors import StoreError
from gtgen.runtime.output import partial_path
from gtgen.storage.schema import DATASET, DRIVE, FUSED, DatasetAttrs, StoreFormat


def jsonable(obj: Any) -> Any:
    """Return ``obj`` with numpy scalars and paths turned into JSON types."""
    return json.loads(json.dumps(obj, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def store_attrs(fmt: StoreFormat, **attrs: Any) -> dict[str, Any]:
    """Return the attributes of a complete store of ``fmt`` with ``attrs`` (as JSON types)."""
    return jsonable({"store": fmt.kind, "version": fmt.version, "complete": True, **attrs})


def create_group(path: Path) -> Any:
    """Return a new, empty zarr group at ``path`` (a stage's partial output)."""
    import zarr

    return zarr.open_group(str(path), mode="w")


def open_store(path: Path, fmt: StoreFormat, mode: str = "r") -> Any:
    """Return the zarr group of a complete store of ``fmt`` at ``path``, or raise StoreError
    saying why not and which command makes one."""
    import zarr

    name = fmt.kind.removeprefix("gtgen-")
    if not path.exists():
        hint = " (a run that did not finish left only a .partial store)" if partial_path(path).exists() else ""
        raise StoreError(f"{name} store '{path}' does not exist{hint}; run '{fmt.made_by}' first")
    try:
        g = zarr.open_group(str(path), mode=mode)
    except Exception as err:  # noqa: BLE001 - zarr raises several types for non-stores
        raise StoreError(f"'{path}' is not a zarr store: {err}".splitlines()[0]) from err
    attrs = g.attrs.asdict()
    if attrs.get("store") != fmt.kind:
        raise StoreError(f"'{path}' is not a gtgen {name} store (store={attrs.get('store')!r}, expected {fmt.kind!r})")
    if attrs.get("version") != fmt.version:
        raise StoreError(f"{name} store '{path}' has version {attrs.get('version')}; this gtgen reads version {fmt.version}: "
                         f"re-run '{fmt.made_by}'")
    if not attrs.get("complete"):
        raise StoreError(f"{name} store '{path}' is incomplete; re-run '{fmt.made_by}'")
    return g


def open_drive(path: Path) -> Any:
    """Return the zarr group of a complete drive store."""
    return open_store(path, DRIVE)


def open_fused(path: Path) -> Any:
    """Return the zarr group of a complete fused store."""
    return open_store(path, FUSED)


@dataclass(frozen=True)
class DatasetInfo:
    """A dataset's sizes and its validated attributes."""

    path: Path
    n_samples: int
    micro: int
    short: int
    image_hw: tuple[int, int]
    attrs: DatasetAttrs


def open_dataset(path: Path) -> tuple[Any, DatasetInfo]:
    """Return (zarr group, info) of a complete dataset, or raise StoreError saying why not."""
    from pydantic import ValidationError

    g = open_store(path, DATASET)
    try:
        attrs = DatasetAttrs.model_validate(g.attrs.asdict())
    except ValidationError as err:
        raise StoreError(f"dataset '{path}' has attributes this gtgen does not read ({err.errors()[0]['loc']}); "
                         f"re-run '{DATASET.made_by}'") from err
    S = int(g["meta/t_ns"].shape[0])
    img = g["inputs/images"].shape
    return g, DatasetInfo(path, S, int(g["labels/micro/region"].shape[1]), int(g["labels/short/region"].shape[1]),
                          (int(img[2]), int(img[3])), attrs)


def read_rows(arr: Any, rows: Any) -> Any:
    """Return ``arr[rows]`` for sorted sample indices ``rows``, in one zarr call (a slice
    when they are consecutive): one call per block instead of one per sample, each of
    which costs about 2 ms of zarr's event loop."""
    import numpy as np

    rows = np.asarray(rows)
    if len(rows) and np.all(np.diff(rows) == 1):
        return arr[int(rows[0]):int(rows[-1]) + 1]
    return arr.get_orthogonal_selection((rows,))
