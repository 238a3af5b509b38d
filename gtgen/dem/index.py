"""The DEM tiles of a folder: an index of rasters in any CRS, with their headers cached.

Any raster GDAL reads is a tile (GeoTIFF, VRT, SRTM ``.hgt``, ERDAS ``.img``, ...), also
inside ``.zip`` archives (read through GDAL's ``/vsizip/``), in any CRS with known units:
projected (USGS 3DEP 1 m: NAD83 / UTM) or geographic (the 1/3 arc-second seamless DEM:
NAD83; SRTM, Copernicus: WGS84), with square or non-square pixels, several CRSs at once.
A drive is placed in one working CRS (``TileIndex.working_crs``): the tiles' own when they
share a projected one, else the UTM zone of the drive. ``gtgen.dem.tiles.DemMosaic``
reads the index's tiles in that CRS.
"""

from __future__ import annotations

import json
import logging
import os
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from gtgen.errors import DemError, InputNotFoundError
from gtgen.runtime.output import write_json

log = logging.getLogger(__name__)

SUFFIXES = (".tif", ".tiff", ".vrt", ".hgt", ".img", ".asc", ".dem", ".bil", ".flt", ".jp2")
ARCHIVES = (".zip",)
INDEX_VERSION = 4
_FEET = {"ft", "foot", "feet", "us survey foot", "us_survey_foot", "foot_us", "us-ft", "ftus"}


@dataclass(frozen=True)
class Tile:
    """One tile's header: its GDAL path, bounds in its own CRS, CRS (WKT), nodata, pixel
    size in CRS units, metres per height unit, and the file's size [bytes] and mtime that
    the header cache is keyed on."""

    path: str
    left: float
    bottom: float
    right: float
    top: float
    crs: str
    nodata: float | None
    res_x: float
    res_y: float
    z_to_m: float
    direct: bool  # float32, north-up: read without a warp when it is in the working CRS
    file_bytes: int
    mtime_ns: int
    files: tuple[str, ...] = ()  # every file GDAL reads for it (a VRT's sources, sidecars)


def _z_to_m(ds: Any) -> float:
    """Return the metres per height unit of a dataset (band unit, else a compound CRS's
    vertical axis, else metres)."""
    unit = (ds.units[0] or "").strip().lower() if ds.units else ""
    if unit in _FEET:
        return 0.3048006096012192 if "us" in unit else 0.3048
    if unit in ("", "m", "metre", "metres", "meter", "meters"):
        from pyproj import CRS

        crs = CRS.from_wkt(ds.crs.to_wkt())
        if crs.is_compound and len(crs.sub_crs_list) > 1:
            axis = crs.sub_crs_list[1].axis_info
            return float(axis[0].unit_conversion_factor) if axis else 1.0
        return 1.0
    raise DemError(f"DEM tile '{ds.name}' has heights in {unit!r}; expected metres or feet")


def _read_header(gdal_path: str, file: Path) -> Tile:
    import rasterio

    try:
        with rasterio.open(gdal_path) as ds:
            if ds.crs is None:
                raise DemError(f"DEM tile '{gdal_path}' has no CRS; expected a georeferenced raster (e.g. EPSG:26910 or EPSG:4269)")
            if not (ds.crs.is_projected or ds.crs.is_geographic):
                raise DemError(f"DEM tile '{gdal_path}' has a local CRS without a known unit or place on Earth "
                               f"({ds.crs.to_string()[:60]}); expected a projected or geographic CRS")
            b = ds.bounds
            t = ds.transform
            direct = ds.dtypes[0] == "float32" and t.b == 0 and t.d == 0 and t.e < 0
            st = file.stat()
            files = {str(file.resolve())} | {str(Path(f).resolve()) for f in ds.files if not f.startswith("/vsi")}
            return Tile(gdal_path, b.left, b.bottom, b.right, b.top, ds.crs.to_wkt(), None if ds.nodata is None else float(ds.nodata),
                        abs(t.a), abs(t.e), _z_to_m(ds), direct, st.st_size, st.st_mtime_ns, tuple(sorted(files)))
    except DemError:
        raise
    except Exception as err:  # noqa: BLE001 - rasterio raises many types on bad files
        raise DemError(f"DEM tile '{gdal_path}' cannot be read: {err}".splitlines()[0]) from err


# what a drive without a DEM (or without GNSS) does instead, said by every error that stops dem-align for the lack of one
NO_DEM = "or pass --no-dem (dem.enabled: false) for a dataset of the fused labels alone"


def dem_files(source: Path) -> list[tuple[str, Path]]:
    """Return (GDAL path, file) of every DEM tile of ``source``: a folder's rasters and the
    rasters inside its zip archives, or a single raster or zip file. The one rule of what
    is a DEM tile: dem-align reads these, and ``gtgen build`` hashes what they read."""
    if not source.exists():
        raise InputNotFoundError(f"DEM '{source}' does not exist; pass --dem DIR (a folder of tiles, or one raster), set dem.dir, {NO_DEM}")
    files = sorted(source.iterdir()) if source.is_dir() else [source]
    out = []
    for p in files:
        if p.suffix.lower() in SUFFIXES:
            out.append((str(p), p))
        elif p.suffix.lower() in ARCHIVES:
            try:
                with zipfile.ZipFile(p) as z:
                    out += [(f"/vsizip/{p}/{m}", p) for m in sorted(z.namelist()) if Path(m).suffix.lower() in SUFFIXES]
            except (OSError, zipfile.BadZipFile) as err:
                raise DemError(f"DEM archive '{p}' cannot be read: {err}") from err
    if not out:
        what = f"folder '{source}' has no raster tiles" if source.is_dir() else f"file '{source}' is not a raster or zip of rasters"
        raise DemError(f"DEM {what} (looked for {', '.join(SUFFIXES + ARCHIVES)})")
    return out


def default_dem_dir(cfg_dir: str | None, bags: list[Path]) -> Path:
    """Return the DEM of a drive: ``dem.dir`` if set, else ``dem/`` beside its first bag."""
    if cfg_dir:
        return Path(cfg_dir)
    if not bags:
        raise DemError(f"no DEM folder: set dem.dir, pass --dem DIR, {NO_DEM}")
    return Path(bags[0]).parent / "dem"


class TileIndex:
    """The tiles of a DEM folder, with a header cache beside the workspace."""

    def __init__(self, tiles: list[Tile]) -> None:
        if not tiles:
            raise DemError("the DEM folder has no raster tiles")
        self.tiles = tiles

    @classmethod
    def build(cls, source: Path, cache: Path | None = None, update_cache: bool = True) -> TileIndex:
        """Return the index of ``source`` (a folder of tiles, or one raster or zip file,
        see ``dem_files``); headers are cached in ``cache`` (JSON) by size and mtime,
        rewritten unless ``update_cache`` is False (a worker reading what its stage wrote)."""
        files = dem_files(source)
        known: dict[str, Tile] = {}
        if cache is not None and cache.is_file():
            try:
                data = json.loads(cache.read_text())
                if data.get("version") == INDEX_VERSION:
                    known = {t["path"]: Tile(**{**t, "files": tuple(t["files"])}) for t in data["tiles"]}
            except (ValueError, KeyError, TypeError):
                known = {}
        tiles = []
        for gdal_path, f in files:
            st = f.stat()
            t = known.get(gdal_path)
            if t is None or t.file_bytes != st.st_size or t.mtime_ns != st.st_mtime_ns:
                t = _read_header(gdal_path, f)
            tiles.append(t)
        if cache is not None and update_cache:
            try:
                write_json(cache, {"version": INDEX_VERSION, "tiles": [asdict(t) for t in tiles]})
            except OSError as err:
                log.warning("cannot write the DEM index cache '%s': %s", cache, err)
        return cls(tiles)

    def fingerprint(self) -> str:
        """Return a hash of every file the tiles read (sources of a VRT and sidecars
        included): name, size and mtime, stated afresh."""
        import hashlib

        h = hashlib.sha256()
        for f in sorted({f for t in self.tiles for f in t.files}):
            try:
                st = os.stat(f)
                h.update(f"{f}:{st.st_size}:{st.st_mtime_ns}\n".encode())
            except OSError:
                h.update(f"{f}:missing\n".encode())
        return h.hexdigest()

    def working_crs(self, lon_deg: float, lat_deg: float) -> str:
        """Return the CRS a drive at (lon, lat) is placed in: the tiles' own when they all
        share one projected CRS in metres that keeps distances true at the drive (within
        0.1 %: UTM, state plane in metres; not web mercator), else the UTM zone of the drive
        (on the tiles' datum when they share NAD83, else WGS84)."""
        from pyproj import CRS, Proj
        from pyproj.aoi import AreaOfInterest
        from pyproj.database import query_utm_crs_info

        crs = {t.crs for t in self.tiles}
        first = CRS.from_wkt(next(iter(crs)))
        if len(crs) == 1 and first.is_projected and first.axis_info[0].unit_conversion_factor == 1.0:
            f = Proj(first).get_factors(lon_deg, lat_deg)
            if max(abs(f.meridional_scale - 1), abs(f.parallel_scale - 1)) < 1e-3:
                return first.to_string() if first.to_epsg() is None else f"EPSG:{first.to_epsg()}"
        datums = {CRS.from_wkt(c).geodetic_crs.datum.name for c in crs}
        datum = "NAD83" if len(datums) == 1 and "North American Datum 1983" in next(iter(datums)) else "WGS 84"
        info = query_utm_crs_info(datum_name=datum, area_of_interest=AreaOfInterest(lon_deg, lat_deg, lon_deg, lat_deg))
        if not info:
            raise DemError(f"no UTM zone for the drive at lon {lon_deg:.4f}, lat {lat_deg:.4f} ({datum})")
        return f"{info[0].auth_name}:{info[0].code}"
