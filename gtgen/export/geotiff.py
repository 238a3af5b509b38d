"""``gtgen export geotiff``: the labels and the aligned DEM as north-up Cloud-Optimized
GeoTIFFs in the dataset's CRS, for QGIS and any GIS.

Per drive and range, one mosaic per layer (``<drive>/<range>/<layer>.tif``), in the
drive's working CRS (``drives[i].crs``) at the range's resolution:

- ``elevation_m``: label heights in the DEM's vertical datum (label + the sample's
  placed base height, ``meta/T_crs_target[2, 3]``), so this mosaic minus the DEM is the
  label error;
- ``risk``, ``region`` (codes, 0 = none), ``count``;
- ``last_obs_s``: time of the cell's last observation, seconds after the drive's first
  sample;
- ``dem_elevation_m``: the aligned DEM the samples were filled from (same datum).

Each pixel takes the value of the sample whose vehicle was nearest to it among the
samples that label it (the DEM layer: that have DEM there): near the vehicle labels are
densest and freshest. The samples are placed by ``meta/T_crs_target`` (after ICP); a pixel
reads the cell whose footprint holds its centre. ``samples`` instead writes one raster per
sample (``samples/<k>/<range>/<layer>.tif``), the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen.config import RANGES, GtgenConfig
from gtgen.errors import GtgenError
from gtgen.runtime.output import stage_output
from gtgen.runtime.progress import track
from gtgen.storage.stores import open_dataset

# layer: (dtype, nodata)
LAYERS: dict[str, tuple[str, Any]] = {
    "elevation_m": ("float32", float("nan")),
    "risk": ("float32", float("nan")),
    "region": ("uint8", 0),
    "count": ("uint16", 0),
    "last_obs_s": ("float32", float("nan")),
    "dem_elevation_m": ("float32", float("nan")),
}


@dataclass
class ExportResult:
    """What an export wrote."""

    out: Path
    files: list[Path] = field(default_factory=list)
    samples: int = 0


@dataclass
class _Mosaic:
    """A north-up pixel grid: origin (west, north) [m], resolution, size; per pixel the
    distance to the nearest sample so far, and which sample and cell it reads."""

    west: float
    north: float
    res: float
    width: int
    height: int

    def __post_init__(self) -> None:
        shape = (self.height, self.width)
        self.best = {k: np.full(shape, np.inf, np.float32) for k in ("label", "dem")}
        self.sample = {k: np.full(shape, -1, np.int32) for k in ("label", "dem")}
        self.cell = {k: np.zeros(shape, np.int32) for k in ("label", "dem")}

    def transform(self) -> Any:
        from rasterio.transform import from_origin

        return from_origin(self.west, self.north, self.res, self.res)


def _mosaic_grid(T: NDArray, length_m: float, res: float) -> _Mosaic:
    """Return the pixel grid covering every sample's footprint (centre +- the half diagonal)."""
    r = 0.5 * length_m * np.sqrt(2) + res
    e, n = T[:, 0, 3], T[:, 1, 3]
    west, east = np.floor((e.min() - r) / res) * res, np.ceil((e.max() + r) / res) * res
    south, north = np.floor((n.min() - r) / res) * res, np.ceil((n.max() + r) / res) * res
    return _Mosaic(float(west), float(north), res, int(round((east - west) / res)), int(round((north - south) / res)))


def _footprint(m: _Mosaic, T: NDArray, size: int, res: float) -> tuple[tuple[slice, slice], NDArray, NDArray]:
    """Return the pixel window of a sample placed at ``T``, and per pixel of it the sample's
    cell index (flat, -1 outside the grid) and squared distance to the vehicle."""
    half = 0.5 * size * res
    r = half * np.sqrt(2)
    c0 = max(int(np.floor((T[0, 3] - r - m.west) / m.res)), 0)
    c1 = min(int(np.ceil((T[0, 3] + r - m.west) / m.res)), m.width)
    r0 = max(int(np.floor((m.north - (T[1, 3] + r)) / m.res)), 0)
    r1 = min(int(np.ceil((m.north - (T[1, 3] - r)) / m.res)), m.height)
    E = m.west + (np.arange(c0, c1) + 0.5) * m.res
    N = m.north - (np.arange(r0, r1) + 0.5) * m.res
    dE, dN = E[None, :] - T[0, 3], N[:, None] - T[1, 3]
    x = T[0, 0] * dE + T[1, 0] * dN  # R^T (p - t): the target frame is yaw-only in the CRS
    y = T[0, 1] * dE + T[1, 1] * dN
    i = np.floor((x + half) / res).astype(np.int64)
    j = np.floor((y + half) / res).astype(np.int64)
    inside = (i >= 0) & (i < size) & (j >= 0) & (j < size)
    return (slice(r0, r1), slice(c0, c1)), np.where(inside, i * size + j, -1), (x * x + y * y).astype(np.float32)


def _composite(m: _Mosaic, g: Any, r: str, ks: NDArray, T: NDArray, size: int, res: float) -> None:
    """Pick for each pixel the nearest sample that labels it (and that has DEM there)."""
    for k in track(ks, f"export geotiff: {r} placement"):
        win, cell, d2 = _footprint(m, T[k], size, res)
        valid = {"label": g[f"labels/{r}/region"][k].ravel() > 0, "dem": np.isfinite(g[f"dem/{r}/elevation_m"][k].ravel())}
        for kind, ok in valid.items():
            take = (cell >= 0) & ok[np.maximum(cell, 0)] & (d2 < m.best[kind][win])
            m.best[kind][win] = np.where(take, d2, m.best[kind][win])
            m.sample[kind][win] = np.where(take, k, m.sample[kind][win])
            m.cell[kind][win] = np.where(take, cell, m.cell[kind][win])


def _layers(m: _Mosaic, g: Any, r: str, ks: NDArray, T: NDArray, t0_ns: int) -> dict[str, NDArray]:
    """Gather each layer's mosaic from the samples the composite picked."""
    out = {name: np.full((m.height, m.width), nodata, dtype) for name, (dtype, nodata) in LAYERS.items()}
    t_ns = g["meta/t_ns"][:]
    for k in track(ks, f"export geotiff: {r} layers"):
        for kind in ("label", "dem"):
            sel = m.sample[kind] == k
            if not sel.any():
                continue
            cells = m.cell[kind][sel]
            z = T[k][2, 3]  # the placed base height: label heights are relative to it
            if kind == "dem":
                out["dem_elevation_m"][sel] = g[f"dem/{r}/elevation_m"][k].ravel()[cells] + z
                continue
            out["elevation_m"][sel] = g[f"labels/{r}/elevation_m"][k].ravel()[cells] + z
            out["risk"][sel] = g[f"labels/{r}/risk"][k].ravel()[cells]
            out["region"][sel] = g[f"labels/{r}/region"][k].ravel()[cells]
            out["count"][sel] = g[f"labels/{r}/count"][k].ravel()[cells]
            out["last_obs_s"][sel] = g[f"labels/{r}/last_dt_s"][k].ravel()[cells] + (int(t_ns[k]) - t0_ns) * 1e-9
    return out


def write_cog(path: Path, band: NDArray, crs: str, transform: Any, nodata: Any, description: str) -> None:
    """Write one band as a Cloud-Optimized GeoTIFF (deflate, 512 px tiles, overviews down
    to 512 px; averaged, or nearest for codes and counts)."""
    from rasterio.io import MemoryFile
    from rasterio.shutil import copy as rio_copy

    profile = {"driver": "GTiff", "width": band.shape[1], "height": band.shape[0], "count": 1, "dtype": band.dtype.name,
               "crs": crs, "transform": transform, "nodata": nodata}
    path.parent.mkdir(parents=True, exist_ok=True)
    with MemoryFile() as mem:
        with mem.open(**profile) as ds:
            ds.write(band, 1)
            ds.set_band_description(1, description)
        with mem.open() as src:
            rio_copy(src, str(path), driver="COG", compress="DEFLATE", blocksize=256, overviews="AUTO",
                     overview_resampling="nearest" if band.dtype.kind in "ui" else "average")


def export_geotiff(dataset: Path, out: Path, samples: list[int] | None = None) -> ExportResult:
    """Write the GeoTIFFs of ``dataset`` into the folder ``out`` (atomically): per drive and
    range the mosaics, or with ``samples`` one raster set per listed sample."""
    g, info = open_dataset(dataset)
    if info.n_samples == 0:
        raise GtgenError(f"dataset '{dataset}' has no samples; nothing to export")
    cfg = GtgenConfig.model_validate(info.attrs.config)
    T = g["meta/T_crs_target"][:]
    drive = g["meta/drive"][:]
    t_ns = g["meta/t_ns"][:]
    if samples is not None:
        bad = [k for k in samples if not 0 <= k < info.n_samples]
        if bad:
            raise GtgenError(f"--samples {bad[0]} is not a sample of '{dataset}' (0..{info.n_samples - 1})")
    res = ExportResult(out)
    with stage_output(out, reads=[dataset]) as tmp:
        groups = [(f"samples/{k}", np.array([k])) for k in samples] if samples is not None else \
                 [(d.name or f"drive{i}", np.nonzero(drive == i)[0]) for i, d in enumerate(info.attrs.drives)]
        for name, ks in groups:
            if not len(ks):
                continue
            crs = info.attrs.drives[int(drive[ks[0]])].crs
            t0 = int(t_ns[np.nonzero(drive == drive[ks[0]])[0]].min())
            for r in RANGES:
                gr = cfg.grids.get(r)
                m = _mosaic_grid(T[ks], gr.length_m, gr.resolution_m)
                _composite(m, g, r, ks, T, gr.size, gr.resolution_m)
                for layer, band in _layers(m, g, r, ks, T, t0).items():
                    path = tmp / name / r / f"{layer}.tif"
                    write_cog(path, band, crs, m.transform(), LAYERS[layer][1], f"{r} {layer}")
                    res.files.append(out / path.relative_to(tmp))
            res.samples += len(ks)
    return res
