"""An index of a folder of DEM GeoTIFF tiles, and mosaicked window reads from it."""

from __future__ import annotations

import json
import logging
from collections import OrderedDict
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.errors import DemError, InputNotFoundError
from gtgen.runtime.output import write_atomic

log = logging.getLogger(__name__)

SUFFIXES = (".tif", ".tiff")
INDEX_VERSION = 2


@dataclass(frozen=True)
class Tile:
    """One tile's header: file, bounds in its CRS [m], CRS, nodata and pixel size [m], and
    the file's size [bytes] and mtime that the header cache is keyed on."""

    path: str
    left: float
    bottom: float
    right: float
    top: float
    crs: str
    nodata: float | None
    res: float
    file_bytes: int
    mtime_ns: int


def _read_header(path: Path) -> Tile:
    import rasterio

    try:
        with rasterio.open(path) as ds:
            if ds.crs is None:
                raise DemError(f"DEM tile '{path}' has no CRS; expected a projected CRS such as EPSG:26910")
            if not ds.crs.is_projected:
                raise DemError(f"DEM tile '{path}' has CRS {ds.crs.to_string()} which is not projected; expected metres (e.g. UTM)")
            b = ds.bounds
            res = abs(ds.transform.a)
            if abs(abs(ds.transform.e) - res) > 1e-6 * res or ds.transform.b or ds.transform.d:
                raise DemError(f"DEM tile '{path}' has non-square or rotated pixels; expected a north-up grid")
            return Tile(str(path), b.left, b.bottom, b.right, b.top, ds.crs.to_string(),
                        None if ds.nodata is None else float(ds.nodata), res, path.stat().st_size, path.stat().st_mtime_ns)
    except DemError:
        raise
    except Exception as err:  # noqa: BLE001 - rasterio raises many types on bad files
        raise DemError(f"DEM tile '{path}' cannot be read: {err}".splitlines()[0]) from err


class TileIndex:
    """The tiles of a DEM folder (one CRS), with a header cache beside the workspace."""

    def __init__(self, tiles: list[Tile]) -> None:
        if not tiles:
            raise DemError("the DEM folder has no GeoTIFF tiles")
        crs = {t.crs for t in tiles}
        if len(crs) > 1:
            raise DemError(f"DEM tiles are in several CRS {sorted(crs)}; expected one")
        self.tiles = tiles
        self.crs = tiles[0].crs
        self.res = min(t.res for t in tiles)
        self._open: OrderedDict[str, object] = OrderedDict()

    @classmethod
    def build(cls, folder: Path, cache: Path | None = None, update_cache: bool = True) -> TileIndex:
        """Return the index of ``folder``; headers are cached in ``cache`` (JSON) by size and
        mtime, rewritten unless ``update_cache`` is False (a worker reading what its stage wrote)."""
        if not folder.is_dir():
            raise InputNotFoundError(f"DEM folder '{folder}' does not exist; pass --dem DIR or set dem.dir")
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() in SUFFIXES)
        if not files:
            raise DemError(f"DEM folder '{folder}' has no .tif tiles")
        known: dict[str, Tile] = {}
        if cache is not None and cache.is_file():
            try:
                data = json.loads(cache.read_text())
                if data.get("version") == INDEX_VERSION:
                    known = {t["path"]: Tile(**t) for t in data["tiles"]}
            except (ValueError, KeyError, TypeError):
                known = {}
        tiles = []
        for f in files:
            st = f.stat()
            t = known.get(str(f))
            if t is None or t.file_bytes != st.st_size or t.mtime_ns != st.st_mtime_ns:
                t = _read_header(f)
            tiles.append(t)
        if cache is not None and update_cache:
            try:
                write_atomic(cache, json.dumps({"version": INDEX_VERSION, "tiles": [asdict(t) for t in tiles]}))
            except OSError as err:
                log.warning("cannot write the DEM index cache '%s': %s", cache, err)
        return cls(tiles)

    def bounds(self) -> tuple[float, float, float, float]:
        """Return the union bounds (left, bottom, right, top) of every tile."""
        return (min(t.left for t in self.tiles), min(t.bottom for t in self.tiles),
                max(t.right for t in self.tiles), max(t.top for t in self.tiles))

    def overlapping(self, left: float, bottom: float, right: float, top: float) -> list[Tile]:
        """Return the tiles that intersect the box."""
        return [t for t in self.tiles if t.left < right and t.right > left and t.bottom < top and t.top > bottom]

    def _dataset(self, path: str):
        import rasterio

        ds = self._open.get(path)
        if ds is None:
            ds = rasterio.open(path)
            self._open[path] = ds
            if len(self._open) > 16:
                self._open.popitem(last=False)[1].close()
        else:
            self._open.move_to_end(path)
        return ds

    def __enter__(self) -> TileIndex:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close every open tile."""
        for ds in self._open.values():
            ds.close()
        self._open.clear()

    def read(self, left: float, bottom: float, right: float, top: float) -> tuple[NDArray[np.float32], tuple[float, float, float]]:
        """Return the mosaic over the box (NaN where no tile or nodata) and (x0, y0, res) of
        its upper-left corner, rows running south. Only the needed windows are read."""
        from rasterio.windows import from_bounds

        res = self.res
        # the output grid is on the pixel lattice of the tiles (USGS tiles share one)
        ax, ay = self.tiles[0].left, self.tiles[0].top
        x0 = ax + np.floor((left - ax) / res) * res
        y0 = ay - np.floor((ay - top) / res) * res
        w = int(np.ceil((right - x0) / res))
        h = int(np.ceil((y0 - bottom) / res))
        out = np.full((h, w), np.nan, np.float32)
        for t in self.overlapping(x0, y0 - h * res, x0 + w * res, y0):
            ds = self._dataset(t.path)
            # the part of our grid this tile covers, in whole tile pixels
            l, b = max(x0, t.left), max(y0 - h * res, t.bottom)
            r, tp = min(x0 + w * res, t.right), min(y0, t.top)
            if r <= l or tp <= b:
                continue
            win = from_bounds(l, b, r, tp, transform=ds.transform).round_offsets().round_lengths()
            data = ds.read(1, window=win, masked=True).astype(np.float32).filled(np.nan)
            if t.res != res:
                raise DemError(f"DEM tiles mix pixel sizes ({t.res} m and {res} m); expected one")
            c0 = int(round((l - x0) / res))
            r0 = int(round((y0 - tp) / res))
            hh, ww = min(data.shape[0], h - r0), min(data.shape[1], w - c0)
            block = out[r0 : r0 + hh, c0 : c0 + ww]
            np.copyto(block, data[:hh, :ww], where=np.isnan(block))
        out[out < -1e4] = np.nan  # nodata spelled as a huge negative number without a nodata tag
        return out, (float(x0), float(y0), float(res))


def sample_bilinear(grid: NDArray[np.float32], origin: tuple[float, float, float], E: NDArray, N: NDArray) -> NDArray[np.float32]:
    """Return ``grid`` (rows south from y0, columns east from x0, pixel-is-area) bilinearly
    interpolated at (E, N); NaN outside or next to a NaN."""
    from scipy.ndimage import map_coordinates

    x0, y0, res = origin
    col = (np.asarray(E) - x0) / res - 0.5
    row = (y0 - np.asarray(N)) / res - 0.5
    out = map_coordinates(grid, [row.ravel(), col.ravel()], order=1, cval=np.nan, prefilter=False)
    return out.reshape(np.shape(E)).astype(np.float32)
