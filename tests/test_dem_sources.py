"""DEMs as users have them: other CRSs (geographic NAD83, web mercator, two UTM zones),
a VRT mosaic, zipped tiles, SRTM .hgt, feet; the labels do not depend on how the same
terrain was delivered."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.warp import Resampling, calculate_default_transform, reproject

from gtgen.dataset.dem_align import run_dem_align
from gtgen.dem.index import TileIndex
from gtgen.dem.tiles import DemMosaic
from gtgen.errors import DemError
from gtgen.storage.dataset import DatasetStore


def _reprojected(src_dir: Path, dst_dir: Path, crs_of) -> Path:
    """Write every tile of ``src_dir`` reprojected (bilinear) to ``crs_of(i)``."""
    dst_dir.mkdir()
    for i, p in enumerate(sorted(src_dir.glob("*.tif"))):
        with rasterio.open(p) as ds:
            crs = crs_of(i)
            T, w, h = calculate_default_transform(ds.crs, crs, ds.width, ds.height, *ds.bounds)
            out = np.full((h, w), -999999.0, np.float32)
            reproject(rasterio.band(ds, 1), out, src_transform=ds.transform, src_crs=ds.crs, dst_transform=T, dst_crs=crs,
                      resampling=Resampling.bilinear, src_nodata=ds.nodata, dst_nodata=-999999.0)
            prof = dict(driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=crs, transform=T, nodata=-999999.0)
        with rasterio.open(dst_dir / p.name, "w", **prof) as o:
            o.write(out, 1)
    return dst_dir


def _vrt(src_dir: Path, dst_dir: Path) -> Path:
    """Write one VRT mosaic of the tiles of ``src_dir`` (a folder holding only it)."""
    dst_dir.mkdir()
    tiles = sorted(src_dir.glob("*.tif"))
    with rasterio.open(tiles[0]) as ds:
        res, crs, nodata = ds.transform.a, ds.crs.to_wkt(), ds.nodata
    heads = []
    for p in tiles:
        with rasterio.open(p) as ds:
            heads.append((p, ds.bounds, ds.width, ds.height))
    x0, y1 = min(b.left for _, b, _, _ in heads), max(b.top for _, b, _, _ in heads)
    W = int(round((max(b.right for _, b, _, _ in heads) - x0) / res))
    H = int(round((y1 - min(b.bottom for _, b, _, _ in heads)) / res))
    src = "".join(
        f'<ComplexSource><SourceFilename relativeToVRT="0">{p}</SourceFilename><SourceBand>1</SourceBand>'
        f'<SrcRect xOff="0" yOff="0" xSize="{w}" ySize="{h}"/>'
        f'<DstRect xOff="{int(round((b.left - x0) / res))}" yOff="{int(round((y1 - b.top) / res))}" xSize="{w}" ySize="{h}"/>'
        f"<NODATA>{nodata}</NODATA></ComplexSource>" for p, b, w, h in heads)
    (dst_dir / "mosaic.vrt").write_text(
        f'<VRTDataset rasterXSize="{W}" rasterYSize="{H}"><SRS>{crs.replace("&", "&amp;").replace("<", "&lt;")}</SRS>'
        f"<GeoTransform>{x0}, {res}, 0, {y1}, 0, {-res}</GeoTransform>"
        f'<VRTRasterBand dataType="Float32" band="1"><NoDataValue>{nodata}</NoDataValue>{src}</VRTRasterBand></VRTDataset>')
    return dst_dir


def _zipped(src_dir: Path, dst_dir: Path) -> Path:
    dst_dir.mkdir()
    with zipfile.ZipFile(dst_dir / "usgs_tiles.zip", "w") as z:
        for p in sorted(src_dir.glob("*.tif")):
            z.write(p, f"tiles/{p.name}")
    return dst_dir


@pytest.fixture(scope="module")
def variants(drive_dir, tmp_path_factory):
    root = tmp_path_factory.mktemp("dems")
    dem = drive_dir / "dem"
    return {
        "EPSG:4269 (NAD83 geographic)": _reprojected(dem, root / "nad83", lambda i: "EPSG:4269"),
        "EPSG:3857 (web mercator)": _reprojected(dem, root / "mercator", lambda i: "EPSG:3857"),
        "two UTM zones": _reprojected(dem, root / "zones", lambda i: "EPSG:26910" if i % 2 else "EPSG:26911"),
        "VRT": _vrt(dem, root / "vrt"),
        "zip": _zipped(dem, root / "zip"),
    }


@pytest.mark.parametrize("name", ["EPSG:4269 (NAD83 geographic)", "EPSG:3857 (web mercator)", "two UTM zones", "VRT", "zip"])
def test_the_same_terrain_in_other_crs_and_containers_gives_the_same_labels(variants, name, dataset, drive_store, fused_store, cfg, tmp_path):
    out = tmp_path / "ds.zarr"
    run_dem_align(drive_store, fused_store, variants[name], out, cfg, workers=1)
    ref = DatasetStore(dataset)
    info = got = DatasetStore(out)
    np.testing.assert_array_equal(got.read("meta/t_ns"), ref.read("meta/t_ns"))  # the same accepted samples
    for r in ("micro", "short"):  # decoded reads: metres, NaN where unlabelled
        reg, el = ref.read(f"labels/{r}/region"), ref.read(f"labels/{r}/elevation_m")
        reg2, el2 = got.read(f"labels/{r}/region"), got.read(f"labels/{r}/elevation_m")
        dem = (reg == 3) & (reg2 == 3)
        assert dem.sum() > 0.95 * (reg == 3).sum()  # the DEM covers the same cells (a few at nodata edges may differ)
        err = np.abs(el2[dem] - el[dem])
        print(name, r, "DEM-region |diff| mean", err.mean(), "p95", np.quantile(err, 0.95))
        assert err.mean() <= 0.05 and np.quantile(err, 0.95) <= 0.10
        if name in ("VRT", "zip"):  # no resampling: the very same heights
            np.testing.assert_array_equal(el2, el)
    crs = info.info.drives[0].crs
    assert crs == {"EPSG:3857 (web mercator)": "EPSG:32610"}.get(name, "EPSG:26910")


def test_srtm_hgt_in_feet_and_a_local_crs(tmp_path):
    """An SRTM tile (GDAL's SRTMHGT driver) is read in the drive's UTM zone; heights in
    feet become metres; a raster in a local CRS is a one-line error."""
    import rasterio.shutil
    from pyproj import Transformer

    n = 1201  # 3 arc-second SRTM
    rows, cols = np.mgrid[0:n, 0:n]
    z = (100 + cols + 2 * rows).astype(np.int16)  # a plane: bilinear reprojection keeps it exact
    T = rasterio.transform.from_origin(-121.0 - 0.5 / (n - 1), 36.0 + 0.5 / (n - 1), 1 / (n - 1), 1 / (n - 1))
    src = tmp_path / "plane.tif"
    with rasterio.open(src, "w", driver="GTiff", width=n, height=n, count=1, dtype="int16", crs="EPSG:4326", transform=T, nodata=-32768) as o:
        o.write(z, 1)
    (tmp_path / "srtm").mkdir()
    rasterio.shutil.copy(src, tmp_path / "srtm" / "N35W121.hgt", driver="SRTMHGT")
    index = TileIndex.build(tmp_path / "srtm")
    crs = index.working_crs(-120.7, 35.6)
    assert crs == "EPSG:32610"
    with DemMosaic(index, crs) as dem:
        E, N = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(-120.7, 35.6)
        grid, (x0, y0, res) = dem.read(E - 200, N - 200, E + 200, N + 200)
        assert 70 < res < 95  # 3 arc-seconds in metres (east-west, the finer axis here)
        i, j = int((y0 - N) / res), int((E - x0) / res)
        e, nn = x0 + (j + 0.5) * res, y0 - (i + 0.5) * res
        lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(e, nn)
        want = 100 + (lon + 121.0) * (n - 1) + 2 * (36.0 - lat) * (n - 1)
        assert abs(grid[i, j] - want) < 0.05
    feet = tmp_path / "feet"
    feet.mkdir()
    with rasterio.open(feet / "ft.tif", "w", driver="GTiff", width=4, height=4, count=1, dtype="float32", crs="EPSG:26910",
                       transform=rasterio.transform.from_origin(700000, 3950000, 1, 1)) as o:
        o.write(np.full((4, 4), 100.0, np.float32), 1)
        o.units = ("ft",)
    with DemMosaic(TileIndex.build(feet), "EPSG:26910") as dem:
        grid, _ = dem.read(700000.5, 3949996.5, 700003.5, 3949999.5)
        assert np.allclose(grid[np.isfinite(grid)], 30.48)
    local = tmp_path / "local"
    local.mkdir()
    wkt = 'LOCAL_CS["site grid",UNIT["unknown",1],AXIS["x",EAST],AXIS["y",NORTH]]'
    with rasterio.open(local / "l.tif", "w", driver="GTiff", width=4, height=4, count=1, dtype="float32", crs=wkt,
                       transform=rasterio.transform.from_origin(0, 4, 1, 1)) as o:
        o.write(np.zeros((4, 4), np.float32), 1)
    with pytest.raises(DemError, match="local CRS") as exc:
        TileIndex.build(local)
    assert "\n" not in str(exc.value)


def test_a_tile_cut_short_is_named_in_one_line(drive_dir, drive_store, fused_store, cfg, tmp_path):
    """A GeoTIFF whose header reads but whose pixels are cut short (a copy interrupted)
    stopped dem-align with rasterio's 'Read failed. See previous exception for details.'
    naming no file: now a DemError naming the tile."""
    dem = tmp_path / "dem"
    dem.mkdir()
    tiles = sorted((drive_dir / "dem").glob("*.tif"))
    for t in tiles:
        (dem / t.name).write_bytes(t.read_bytes())
    for t in sorted(dem.glob("*.tif")):  # every tile cut: whichever the drive reads first is named
        t.write_bytes(t.read_bytes()[: t.stat().st_size // 3])
    with pytest.raises(DemError, match=r"DEM tile '.*\.tif' cannot be read: the file is damaged or cut short"):
        run_dem_align(drive_store, fused_store, dem, tmp_path / "out.zarr", cfg)
    assert not (tmp_path / "out.zarr").exists()
