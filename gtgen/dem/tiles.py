"""DEM tiles read as one mosaic in one working CRS (``TileIndex.working_crs``).

``DemMosaic`` reads a window in that CRS: tiles in another CRS (or not float32, or not
north-up) through rasterio's ``WarpedVRT`` (bilinear) onto the working lattice, mosaicked
by ``rasterio.merge.merge``; heights in feet or other vertical units are converted to
metres. A tile found shifted (``TileOffset``, measured by dem-align) is read put back: its
content from (E + dx, N + dy), bilinearly, less dz. The tiles themselves: ``gtgen.dem.index``.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from gtgen.dem.borders import MIN_SIDE_SHARE, BorderSide
from gtgen.dem.index import TileIndex
from gtgen.errors import DemError


class DemSource(Protocol):
    """What DEM placement and filling need from a DEM, in one working CRS (metres): heights
    and their validity in a window, and which tile each point's height comes from (for
    judging tiles and setting them aside). ``DemMosaic`` is one; another source (a VRT
    over HTTP, a point-cloud DEM) is one class with these members."""

    crs: str
    exclude: frozenset[int]
    offsets: dict[int, TileOffset]

    @property
    def tile_names(self) -> list[str]:
        """Each tile's identity (its path), by tile index."""

    def bounds(self) -> tuple[float, float, float, float]:
        """Return the union bounds (left, bottom, right, top) of the tiles."""

    def read(self, left: float, bottom: float, right: float, top: float) -> tuple[NDArray[np.float32], tuple[float, float, float]]:
        """Return heights [m] over the box (NaN: none) and (x0, y0, res) of the upper-left corner, rows running south."""

    def tile_of(self, E: NDArray, N: NDArray) -> NDArray[np.int64]:
        """Return the tile index of each point, -1 outside every tile."""

    def tile_bounds(self, i: int) -> tuple[float, float, float, float]:
        """Return where tile ``i`` is read (left, bottom, right, top), put back if it is."""

    def border_sides(self, i: int, max_gap_m: float, without: frozenset[int] = frozenset(),
                     offsets: dict[int, TileOffset] | None = None) -> list[BorderSide]:
        """Return the sides of tile ``i`` that have a neighbour (not one of ``without``; the
        neighbours read put back by ``offsets`` too), as ``gtgen.dem.borders`` reads them."""

    def without(self, tiles: frozenset[int]) -> DemSource:
        """Return the same source without ``tiles`` (this one is closed)."""

    def adjusted(self, tiles: frozenset[int], offsets: dict[int, TileOffset] | None) -> DemSource:
        """Return the same source without ``tiles`` either and with ``offsets`` put back
        (these alone; None: this one's); this one is closed."""

    def close(self) -> None:
        """Release open files."""


@dataclass(frozen=True)
class TileOffset:
    """Where a tile's content lies against the ground [m, working CRS]: the tile shows at
    (E + dx, N + dy) the ground of (E, N), dz higher. Reading it put back subtracts this."""

    dx: float
    dy: float
    dz: float


@dataclass(frozen=True)
class DemRef:
    """What opens the same mosaic in another process: the DEM source, the header cache,
    the working CRS and the tiles set aside."""

    source: str
    cache: str | None
    crs: str
    exclude: frozenset[int] = frozenset()
    offsets: tuple[tuple[int, TileOffset], ...] = ()  # tiles read put back

    def open(self) -> DemMosaic:
        """Return the mosaic (reading the header cache, never rewriting it)."""
        index = TileIndex.build(Path(self.source), cache=Path(self.cache) if self.cache else None, update_cache=False)
        return DemMosaic(index, self.crs, self.exclude, dict(self.offsets))


PAGE = 256  # pixels a side of the pages DemMosaic.read assembles windows from (256 m at 1 m)
PAGES = 24  # pages kept (6 MB): a sample's windows (at most 220 m a side at the default grids) and the next samples'


class DemMosaic:
    """Mosaicked reads of a TileIndex in the working CRS ``crs``, on one pixel lattice (a ``DemSource``)."""

    def __init__(self, index: TileIndex, crs: str, exclude: frozenset[int] = frozenset(),
                 offsets: dict[int, TileOffset] | None = None) -> None:
        """``exclude``: indices of tiles not to read (tiles judged wrong by dem-align);
        ``offsets``: tiles read put back (shifted tiles, see ``TileOffset``)."""
        from pyproj import CRS
        from rasterio.warp import transform_bounds

        self.index, self.crs, self.exclude = index, crs, frozenset(exclude)
        self.offsets: dict[int, TileOffset] = dict(offsets or {})
        work = CRS.from_user_input(crs)
        self._bounds, self._raw_bounds, res = [], [], []  # where tiles are read (put back), where their files say
        for t in index.tiles:
            same = CRS.from_wkt(t.crs) == work
            b = (t.left, t.bottom, t.right, t.top) if same else transform_bounds(t.crs, crs, t.left, t.bottom, t.right, t.top, densify_pts=21)
            self._raw_bounds.append(b)
            o = self.offsets.get(len(self._bounds))
            self._bounds.append(b if o is None else (b[0] - o.dx, b[1] - o.dy, b[2] - o.dx, b[3] - o.dy))
            n_x = max(1, round((t.right - t.left) / t.res_x))
            res.append((b[2] - b[0]) / n_x)
        self.res = float(min(res))
        anchor = next((t for t, b in zip(index.tiles, self._raw_bounds) if CRS.from_wkt(t.crs) == work and t.direct), None)
        self._anchor = (anchor.left, anchor.top) if anchor else (0.0, 0.0)
        self._same = [CRS.from_wkt(t.crs) == work for t in index.tiles]
        self._open: OrderedDict[int, Any] = OrderedDict()
        self._pages: OrderedDict[tuple[int, int], NDArray[np.float32]] = OrderedDict()  # read() pages, newest last

    @property
    def tile_names(self) -> list[str]:
        """Each tile's GDAL path, by tile index."""
        return [t.path for t in self.index.tiles]

    def without(self, tiles: frozenset[int]) -> DemMosaic:
        """Return the mosaic without ``tiles`` (this one is closed)."""
        return self.adjusted(tiles, None)

    def adjusted(self, tiles: frozenset[int], offsets: dict[int, TileOffset] | None) -> DemMosaic:
        """Return the mosaic without ``tiles`` either and with ``offsets`` put back (these
        alone; None: this one's); this one is closed."""
        self.close()
        return DemMosaic(self.index, self.crs, self.exclude | tiles, self.offsets if offsets is None else offsets)

    def bounds(self) -> tuple[float, float, float, float]:
        """Return the union bounds (left, bottom, right, top) of every tile in the working CRS."""
        b = np.array(self._bounds)
        return float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())

    def tile_bounds(self, i: int) -> tuple[float, float, float, float]:
        """Return where tile ``i`` is read in the working CRS (left, bottom, right, top), put back if it is."""
        return self._bounds[i]

    def tile_of(self, E: NDArray, N: NDArray) -> NDArray[np.int64]:
        """Return the index of the tile each point (working CRS) lies in (the first one where
        tiles overlap), -1 outside every tile."""
        out = np.full(np.shape(E), -1, np.int64)
        for i, (l, b, r, t) in enumerate(self._bounds):
            out[(out < 0) & (E >= l) & (E < r) & (N > b) & (N <= t)] = i
        return out

    def _dataset(self, i: int) -> Any:
        """Return tile ``i`` as a float32 north-up dataset on the working lattice."""
        ds = self._open.get(i)
        if ds is not None:
            self._open.move_to_end(i)
            return ds
        import rasterio
        from affine import Affine
        from rasterio.enums import Resampling
        from rasterio.vrt import WarpedVRT

        t = self.index.tiles[i]
        src = rasterio.open(t.path)
        if self._same[i] and t.direct and abs(t.res_x - self.res) < 1e-9 * self.res and abs(t.res_y - self.res) < 1e-9 * self.res:
            ds = (src,)
        else:
            b = self._raw_bounds[i]
            x0, y0 = self._snap(b[0], b[3])
            w = int(np.ceil((b[2] - x0) / self.res)) + 1
            h = int(np.ceil((y0 - b[1]) / self.res)) + 1
            vrt = WarpedVRT(src, crs=self.crs, transform=Affine(self.res, 0, x0, 0, -self.res, y0), width=w, height=h,
                            resampling=Resampling.bilinear, dtype="float32", nodata=np.nan, src_nodata=t.nodata, tolerance=0.01)
            ds = (vrt, src)
        self._open[i] = ds
        if len(self._open) > 16:
            for d in self._open.popitem(last=False)[1]:
                d.close()
        return ds

    def _snap(self, left: float, top: float) -> tuple[float, float]:
        ax, ay = self._anchor
        return ax + np.floor((left - ax) / self.res) * self.res, ay - np.floor((ay - top) / self.res) * self.res

    def close(self) -> None:
        """Close every open tile."""
        for ds in self._open.values():
            for d in ds:
                d.close()
        self._open.clear()

    def __enter__(self) -> DemMosaic:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def read(self, left: float, bottom: float, right: float, top: float) -> tuple[NDArray[np.float32], tuple[float, float, float]]:
        """Return the mosaic over the box, heights in metres (NaN where no tile or nodata),
        and (x0, y0, res) of its upper-left corner, rows running south.

        Assembled from pages of ``PAGE`` pixels on the mosaic's lattice, each read once
        (``read_direct``) and kept while the last ``PAGES`` pages are: consecutive samples
        read overlapping windows, and a page costs one merge instead of one per sample.
        Every pixel equals ``read_direct``'s over the same box (its oracle): bit for bit,
        but for a tile both reprojected and put back (float32 rounding, about 2e-5 m)."""
        res = self.res
        x0, y0 = self._snap(left, top)
        w, h = int(np.ceil((right - x0) / res)), int(np.ceil((y0 - bottom) / res))
        ax, ay = self._anchor
        c0, r0 = int(round((x0 - ax) / res)), int(round((ay - y0) / res))  # the box's first column and row on the lattice
        out = np.empty((h, w), np.float32)
        for pr in range(r0 // PAGE, (r0 + h - 1) // PAGE + 1):
            for pc in range(c0 // PAGE, (c0 + w - 1) // PAGE + 1):
                page = self._page(pr, pc)
                a0, a1 = max(r0, pr * PAGE), min(r0 + h, (pr + 1) * PAGE)
                b0, b1 = max(c0, pc * PAGE), min(c0 + w, (pc + 1) * PAGE)
                out[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = page[a0 - pr * PAGE:a1 - pr * PAGE, b0 - pc * PAGE:b1 - pc * PAGE]
        return out, (float(x0), float(y0), float(res))

    def _page(self, pr: int, pc: int) -> NDArray[np.float32]:
        """Return page (pr, pc) of the lattice (``PAGE`` x ``PAGE`` pixels), read once."""
        cache = self._pages
        page = cache.get((pr, pc))
        if page is None:
            ax, ay, res = *self._anchor, self.res
            left, top = ax + pc * PAGE * res, ay - pr * PAGE * res
            page = self.read_direct(left + 0.25 * res, top - PAGE * res, left + PAGE * res, top - 0.25 * res)[0]
            cache[(pr, pc)] = page
            if len(cache) > PAGES:
                cache.popitem(last=False)
        else:
            cache.move_to_end((pr, pc))
        return page

    def read_direct(self, left: float, bottom: float, right: float, top: float) -> tuple[NDArray[np.float32], tuple[float, float, float]]:
        """:meth:`read` by merging the tiles over the box itself (pages are read so; the oracle)."""
        res = self.res
        x0, y0 = self._snap(left, top)
        w, h = int(np.ceil((right - x0) / res)), int(np.ceil((y0 - bottom) / res))
        out = np.full((h, w), np.nan, np.float32)
        box = (x0, y0 - h * res, x0 + w * res, y0)
        hits = [i for i, b in enumerate(self._bounds)
                if i not in self.exclude and b[0] < box[2] and b[2] > box[0] and b[1] < box[3] and b[3] > box[1]]
        plain = [i for i in hits if i not in self.offsets]
        for scale in sorted({self.index.tiles[i].z_to_m for i in plain}):
            data = self._merge([i for i in plain if self.index.tiles[i].z_to_m == scale], box)
            grid = data[0, :h, :w].astype(np.float32) * np.float32(scale)
            np.copyto(out, grid, where=np.isnan(out))
        for i in hits:
            if i in self.offsets:
                np.copyto(out, self._read_put_back(i, box, h, w), where=np.isnan(out))
        out[out < -1e4] = np.nan  # nodata spelled as a huge negative number without a nodata tag
        return out, (float(x0), float(y0), float(res))

    def _merge(self, tiles: list[int], box: tuple[float, float, float, float]) -> NDArray:
        """Return ``rasterio.merge.merge`` of ``tiles`` over ``box`` on the lattice (bands,
        rows, columns; NaN where none); DemError naming the tile whose file cannot be read."""
        from rasterio.errors import RasterioError
        from rasterio.merge import merge

        try:
            return merge([self._dataset(i)[0] for i in tiles], bounds=box, res=self.res, nodata=np.nan, dtype="float32")[0]
        except RasterioError as err:
            bad = next((i for i in tiles if not _reads(self._dataset(i)[0], box)), tiles[0])
            raise DemError(f"DEM tile '{self.index.tiles[bad].path}' cannot be read: the file is damaged or cut short; "
                           "replace it, or move it out of the DEM folder") from err

    def border_sides(self, i: int, max_gap_m: float, without: frozenset[int] = frozenset(),
                     offsets: dict[int, TileOffset] | None = None) -> list[BorderSide]:
        """Return the sides of tile ``i`` (as its file places it) that have a neighbour along
        a quarter of them or more (tiles set aside and ``without`` are no neighbours; the
        others are read put back where they are, and by ``offsets`` too): the tile's two
        edge pixel lines and the neighbours' first two beyond, within ``max_gap_m`` of its
        edge (tiles whose files leave a gap between them)."""
        offsets = {k: v for k, v in {**self.offsets, **(offsets or {})}.items() if k != i}
        alone = DemMosaic(self.index, self.crs, frozenset(range(len(self.index.tiles))) - {i})
        others = DemMosaic(self.index, self.crs, self.exclude | without | {i}, offsets)
        try:
            l, b, r, t = alone._bounds[i]
            res = self.res
            far = int(np.ceil(max_gap_m / res))
            out = []
            for (x0, y0, x1, y1), axis, (nx, ny) in (((l, b, l, t), 1, (-1, 0)), ((r, b, r, t), 1, (1, 0)),
                                                      ((l, b, r, b), 0, (0, -1)), ((l, t, r, t), 0, (0, 1))):
                n = max(int(round(np.hypot(x1 - x0, y1 - y0) / res)), 1)
                u = (np.arange(n) + 0.5) * res
                E, N = x0 + (u if axis == 0 else 0.0), y0 + (u if axis == 1 else 0.0)
                pad = (far + 3) * res
                box = (min(x0, x1) - pad, min(y0, y1) - pad, max(x0, x1) + pad, max(y0, y1) + pad)
                ga, oa = alone.read(*box)
                go, oo = others.read(*box)
                hi1, hi2 = (_nearest(ga, oa, E - nx * d * res, N - ny * d * res) for d in (0.5, 1.5))
                for k in range(far + 1):  # the neighbours' first lines beyond the edge
                    ho1, ho2 = (_nearest(go, oo, E + nx * (d + k) * res, N + ny * (d + k) * res) for d in (0.5, 1.5))
                    if np.isfinite(ho1 + ho2 + hi1 + hi2).mean() >= MIN_SIDE_SHARE:
                        out.append(BorderSide(u, axis, nx + ny, hi1.astype(np.float64), hi2.astype(np.float64),
                                              ho1.astype(np.float64), ho2.astype(np.float64), res, k * res))
                        break
            return out
        finally:
            alone.close()
            others.close()

    def _read_put_back(self, i: int, box: tuple[float, float, float, float], h: int, w: int) -> NDArray[np.float32]:
        """Return tile ``i`` put back on the (h, w) pixels of ``box``: its content at the
        pixel centres moved by the offset, bilinear, less dz (NaN off the tile)."""
        o, res = self.offsets[i], self.res
        l, b, r, t = _put_back_box(box, o, res)
        sx, sy = self._snap(l, t)
        sw, sh = int(np.ceil((r - sx) / res)), int(np.ceil((sy - b) / res))
        data = self._merge([i], (sx, sy - sh * res, sx + sw * res, sy))
        grid = data[0, :sh, :sw].astype(np.float32) * np.float32(self.index.tiles[i].z_to_m)
        grid[grid < -1e4] = np.nan
        E = box[0] + (np.arange(w) + 0.5) * res + o.dx
        N = box[3] - (np.arange(h) + 0.5) * res + o.dy
        return sample_bilinear(grid, (sx, sy, res), E[None, :], N[:, None]) - np.float32(o.dz)


def _reads(ds: Any, box: tuple[float, float, float, float]) -> bool:
    """Whether dataset ``ds`` reads over ``box`` (to tell which tile of a failed merge is damaged)."""
    from rasterio.errors import RasterioError
    from rasterio.windows import from_bounds

    try:
        ds.read(1, window=from_bounds(*box, transform=ds.transform), boundless=False)
        return True
    except (RasterioError, ValueError):
        return False


def _put_back_box(box: tuple[float, float, float, float], o: TileOffset, res: float) -> tuple[float, float, float, float]:
    """Return ``box`` moved by the offset and grown by two pixels (what a put-back read needs)."""
    return box[0] + o.dx - 2 * res, box[1] + o.dy - 2 * res, box[2] + o.dx + 2 * res, box[3] + o.dy + 2 * res


def _nearest(grid: NDArray[np.float32], origin: tuple[float, float, float], E: NDArray, N: NDArray) -> NDArray[np.float32]:
    """Return the pixel of ``grid`` (as ``sample_bilinear`` lays it out) under each point; NaN outside."""
    x0, y0, res = origin
    col, row = np.floor((E - x0) / res).astype(np.int64), np.floor((y0 - N) / res).astype(np.int64)
    ok = (row >= 0) & (row < grid.shape[0]) & (col >= 0) & (col < grid.shape[1])
    return np.where(ok, grid[np.where(ok, row, 0), np.where(ok, col, 0)], np.float32(np.nan))


def sample_bilinear(grid: NDArray[np.float32], origin: tuple[float, float, float], E: NDArray, N: NDArray) -> NDArray[np.float32]:
    """Return ``grid`` (rows south from y0, columns east from x0, pixel-is-area) bilinearly
    interpolated at (E, N) of the working CRS; NaN outside or next to a NaN."""
    from gtgen.grids import bilinear

    x0, y0, res = origin
    col = (np.asarray(E) - x0) / res - 0.5
    row = (y0 - np.asarray(N)) / res - 0.5
    return bilinear(grid, row, col).astype(np.float32)
