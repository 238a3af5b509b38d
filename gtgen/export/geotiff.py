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

The export writes into its folder file by file, each atomically, and touches nothing
else there: a file of the same name is replaced only if gtgen wrote it (each COG carries
the signature in its TIFFTAG_SOFTWARE), unless ``overwrite``.
"""

from __future__ import annotations

import errno
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen.config import RANGES
from gtgen.errors import GtgenError
from gtgen.grids import xy_to_index
from gtgen.runtime.output import atomic_output, check_replace, lock, signature
from gtgen.runtime.progress import track
from gtgen.storage.dataset import DatasetStore

BLOCK = 16  # samples read at once (one shard): one zarr call per block, bounded memory
TILE = 2048  # mosaic tile edge [px]: the arrays of one tile are in memory at a time
GDAL_CACHE_MB = 128

# layer: (dtype, nodata)
LAYERS: dict[str, tuple[str, Any]] = {
    "elevation_m": ("float32", float("nan")),
    "risk": ("float32", float("nan")),
    "region": ("uint8", 0),
    "count": ("uint16", 0),
    "last_obs_s": ("float32", float("nan")),
    "dem_elevation_m": ("float32", float("nan")),
}


# layer: (whose pixels: label or dem, the dataset grid (kind, layer) per range, what each
# sample adds: "z" its placed base height (heights are relative to it), "t" its time after
# the drive's first)
SOURCES: dict[str, tuple[str, tuple[str, str], str | None]] = {
    "elevation_m": ("label", ("labels", "elevation_m"), "z"),
    "risk": ("label", ("labels", "risk"), None),
    "region": ("label", ("labels", "region"), None),
    "count": ("label", ("labels", "count"), None),
    "last_obs_s": ("label", ("labels", "last_dt_s"), "t"),
    "dem_elevation_m": ("dem", ("dem", "elevation_m"), "z"),
}


def stored_layers(ds: DatasetStore, r: str) -> list[str]:
    """Return the layers of range ``r`` whose grids the dataset stores (count, last_obs_s
    and dem_elevation_m are QA grids: only with ``shards.qa_ranges``)."""
    return [layer for layer, (_, (kind, name), _) in SOURCES.items() if ds.has_grid(kind, r, name)]


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


def _mosaic_grid(T: NDArray, length_m: float, res: float) -> tuple[float, float, int, int]:
    """Return (west, north, width, height) of the pixel grid covering every sample's
    footprint (centre +- the half diagonal)."""
    r = 0.5 * length_m * np.sqrt(2) + res
    e, n = T[:, 0, 3], T[:, 1, 3]
    west, east = np.floor((e.min() - r) / res) * res, np.ceil((e.max() + r) / res) * res
    south, north = np.floor((n.min() - r) / res) * res, np.ceil((n.max() + r) / res) * res
    return float(west), float(north), int(round((east - west) / res)), int(round((north - south) / res))


def _tiles(T: NDArray, ks: NDArray, west: float, north: float, width: int, height: int, res: float,
           length_m: float) -> list[tuple[int, int, int, int, NDArray]]:
    """Return the mosaic's tiles of ``TILE`` px that some sample's footprint touches: (row,
    col, height, width, those samples). Memory then scales with a tile, not with the
    drive's extent."""
    r = 0.5 * length_m * np.sqrt(2) + res
    e, n = T[ks, 0, 3], T[ks, 1, 3]
    out = []
    for r0 in range(0, height, TILE):
        for c0 in range(0, width, TILE):
            h, w = min(TILE, height - r0), min(TILE, width - c0)
            w0, n0 = west + c0 * res, north - r0 * res
            near = (e + r > w0) & (e - r < w0 + w * res) & (n - r < n0) & (n + r > n0 - h * res)
            if near.any():
                out.append((r0, c0, h, w, ks[near]))
    return out


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
    i, j = xy_to_index(x, y, size, res)
    return (slice(r0, r1), slice(c0, c1)), np.where(i >= 0, i * size + j, -1), (x * x + y * y).astype(np.float32)


def _blocks(ks: NDArray) -> list[NDArray]:
    """Return ``ks`` (ascending) in blocks of ``BLOCK``."""
    return [ks[a:a + BLOCK] for a in range(0, len(ks), BLOCK)]


def _composite(m: _Mosaic, ds: DatasetStore, r: str, ks: NDArray, T: NDArray, size: int, res: float) -> None:
    """Pick for each pixel the nearest sample that labels it (and that has DEM there)."""
    for block in _blocks(ks):
        region = ds.grids("labels", r, "region", block)
        dem = ds.grids("dem", r, "elevation_m", block) if ds.has_grid("dem", r, "elevation_m") else None
        for n, k in enumerate(block):
            win, cell, d2 = _footprint(m, T[k], size, res)
            valid = {"label": region[n].ravel() > 0}
            if dem is not None:
                valid["dem"] = np.isfinite(dem[n].ravel())
            for kind, ok in valid.items():
                take = (cell >= 0) & ok[np.maximum(cell, 0)] & (d2 < m.best[kind][win])
                m.best[kind][win] = np.where(take, d2, m.best[kind][win])
                m.sample[kind][win] = np.where(take, k, m.sample[kind][win])
                m.cell[kind][win] = np.where(take, cell, m.cell[kind][win])


def _layers(m: _Mosaic, ds: DatasetStore, r: str, ks: NDArray, T: NDArray, t_s: NDArray) -> dict[str, NDArray]:
    """Gather each layer's mosaic from the samples the composite picked (``t_s``: each
    sample's time after the drive's first, [s]): the pixels are grouped by sample once (one
    sort), then each sample's arrays are read once."""
    layers = stored_layers(ds, r)
    out = {name: np.full((m.height, m.width), LAYERS[name][1], LAYERS[name][0]) for name in layers}
    flat = {name: a.reshape(-1) for name, a in out.items()}
    groups = {}
    for kind in ("label", "dem"):
        s = m.sample[kind].reshape(-1)
        pix = np.nonzero(s >= 0)[0]
        pix = pix[np.argsort(s[pix], kind="stable")]
        groups[kind] = (pix, np.searchsorted(s[pix], ks, "left"), np.searchsorted(s[pix], ks, "right"), m.cell[kind].reshape(-1))
    n = 0
    for block in _blocks(ks):
        arrays = {layer: ds.grids(SOURCES[layer][1][0], r, SOURCES[layer][1][1], block) for layer in layers}
        for b, k in enumerate(block):
            add = {None: 0, "z": T[k][2, 3], "t": float(t_s[k])}
            for layer in layers:
                kind, _, plus = SOURCES[layer]
                pix, lo, hi, cell = groups[kind]
                p = pix[lo[n]:hi[n]]
                flat[layer][p] = arrays[layer][b].ravel()[cell[p]] + add[plus]
            n += 1
    return out


def _open_bands(folder: Path, r: str, width: int, height: int, crs: str, transform: Any, layers: list[str]) -> dict[str, Any]:
    """Open one tiled GeoTIFF per layer in the scratch ``folder`` for writing window by
    window (empty blocks are not written); ``_to_cog`` turns each into a COG."""
    import rasterio

    out = {}
    for layer in layers:
        dtype, nodata = LAYERS[layer]
        ds = rasterio.open(folder / f"{r}.{layer}.tif", "w", driver="GTiff", width=width, height=height, count=1, dtype=dtype,
                           crs=crs, transform=transform, nodata=nodata, tiled=True, blockxsize=256, blockysize=256,
                           compress="DEFLATE", sparse_ok=True, BIGTIFF="IF_SAFER")
        ds.set_band_description(1, f"{r} {layer}")
        ds.update_tags(TIFFTAG_SOFTWARE=signature())
        out[layer] = ds
    return out


def _to_cog(src_path: Path, path: Path, overwrite: bool) -> None:
    """Copy a GeoTIFF into the Cloud-Optimized GeoTIFF ``path`` (deflate, 256 px tiles,
    overviews down to 256 px; averaged, or nearest for codes and counts), and remove the
    source. The COG is made beside the source (the scratch folder) and then moved or
    copied into place atomically, so that a full disk at ``path`` is an OSError, not a
    GDAL error in mid-file."""
    import rasterio
    from rasterio.shutil import copy as rio_copy

    cog = src_path.with_name(src_path.name + ".cog")
    with rasterio.open(src_path) as src:
        kind = np.dtype(src.dtypes[0]).kind
        rio_copy(src, str(cog), driver="COG", compress="DEFLATE", blocksize=256, overviews="AUTO", BIGTIFF="IF_SAFER",
                 overview_resampling="nearest" if kind in "ui" else "average")
    src_path.unlink()
    with atomic_output(path, overwrite, file=True) as tmp:
        try:
            os.replace(cog, tmp)
        except OSError as err:
            if err.errno != errno.EXDEV:
                raise
            shutil.copyfile(cog, tmp)
    cog.unlink(missing_ok=True)


def _write_error(path: Path, err: Exception) -> OSError:
    """Return GDAL's failure to write ``path`` as the OSError it is (ENOSPC on a full disk)."""
    where = path if path.is_dir() else path.parent
    full = "space" in str(err).lower() or (where.exists() and shutil.disk_usage(where).free < (1 << 20))
    return OSError(errno.ENOSPC if full else errno.EIO, f"{'no space left on the device' if full else err}", str(path))


def export_geotiff(dataset: Path, out: Path, samples: list[int] | None = None, overwrite: bool = False) -> ExportResult:
    """Write the GeoTIFFs of ``dataset`` into the folder ``out``, each file atomically and
    nothing else touched: per drive and range the mosaics, or with ``samples`` one raster
    set per listed sample."""
    import tempfile

    import rasterio
    import rasterio.errors

    ds = DatasetStore(dataset)
    if ds.n_samples == 0:
        raise GtgenError(f"dataset '{dataset}' has no samples; nothing to export")
    if out.exists() and not out.is_dir():
        raise GtgenError(f"output '{out}' is a file; export geotiff writes into a folder")
    cfg = ds.config
    T, drive, t_ns = ds.meta("T_crs_target"), ds.meta("drive"), ds.meta("t_ns")
    if samples is not None:
        bad = [k for k in samples if not 0 <= k < ds.n_samples]
        if bad:
            raise GtgenError(f"--samples {bad[0]} is not a sample of '{dataset}' (0..{ds.n_samples - 1})")
    groups = [(f"samples/{k}", np.array([k])) for k in samples] if samples is not None else \
             [(d.name or f"drive{i}", np.nonzero(drive == i)[0]) for i, d in enumerate(ds.info.drives)]
    unplaced = sorted({ds.info.drives[int(drive[k])].name for _, ks in groups for k in ks if not ds.info.drives[int(drive[k])].crs})
    if unplaced:
        raise GtgenError(f"drive(s) {unplaced} of '{dataset}' have no georeference (built without a DEM: --no-dem), so there is no "
                         "map to export them into; export geotiff needs drives placed on a DEM (export mcap plays any dataset)")
    files = [out / name / r / f"{layer}.tif" for name, ks in groups if len(ks) for r in RANGES for layer in stored_layers(ds, r)]
    for f in files:  # before any work: nothing of the user's is replaced
        check_replace(f, overwrite)
    res = ExportResult(out)
    made = not out.exists()
    # GDAL caches up to 5 % of the machine's memory by default; a fixed cache keeps the
    # export's memory bounded
    with lock(out), lock(dataset, shared=True), rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB), \
            tempfile.TemporaryDirectory(prefix="gtgen-geotiff-") as scratch:
        try:
            for name, ks in groups:
                if not len(ks):
                    continue
                d = int(drive[ks[0]])
                t_s = (t_ns - t_ns[drive == d].min()) * 1e-9  # after the drive's first sample
                for r in RANGES:
                    folder = out / name / r
                    _write_mosaic(Path(scratch), folder, ds, r, cfg.grids.get(r), ks, T, t_s, ds.info.drives[d].crs, overwrite)
                    res.files += [folder / f"{layer}.tif" for layer in stored_layers(ds, r)]
                res.samples += len(ks)
        except BaseException as err:
            # GDAL reports a full disk as an I/O error of its own
            mapped = _write_error(out, err) if isinstance(err, rasterio.errors.RasterioError) else None
            if made:  # a folder made for this export holds only what it wrote
                shutil.rmtree(out, ignore_errors=True)
            if mapped is not None:
                raise mapped from err
            raise
    return res


def _write_mosaic(scratch: Path, folder: Path, ds: DatasetStore, r: str, gr: Any, ks: NDArray, T: NDArray, t_s: NDArray,
                  crs: str, overwrite: bool) -> None:
    """Write the COGs of range ``r`` for samples ``ks`` into ``folder``, tile by tile (the
    tiled GeoTIFFs in ``scratch`` first)."""
    from rasterio.transform import from_origin
    from rasterio.windows import Window

    res_m = gr.resolution_m
    west, north, width, height = _mosaic_grid(T[ks], gr.length_m, res_m)
    bands = _open_bands(scratch, r, width, height, crs, from_origin(west, north, res_m, res_m), stored_layers(ds, r))
    try:
        for r0, c0, h, w, near in track(_tiles(T, ks, west, north, width, height, res_m, gr.length_m), f"export geotiff: {r}"):
            m = _Mosaic(west + c0 * res_m, north - r0 * res_m, res_m, w, h)
            _composite(m, ds, r, near, T, gr.size, res_m)
            used = np.unique(np.concatenate([s[s >= 0] for s in m.sample.values()]))
            if len(used):
                for layer, band in _layers(m, ds, r, used, T, t_s).items():
                    bands[layer].write(band, 1, window=Window(c0, r0, w, h))
    finally:
        for b in bands.values():
            b.close()
    for layer in stored_layers(ds, r):
        _to_cog(scratch / f"{r}.{layer}.tif", folder / f"{layer}.tif", overwrite)
