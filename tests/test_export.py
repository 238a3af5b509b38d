"""The dataset where people already look: GeoTIFF mosaics (rasterio reads them back), one
MCAP recording (rosbags reads it back), the xarray view and the Python API."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli


@pytest.fixture(scope="module")
def tifs(dataset, tmp_path_factory) -> Path:
    from gtgen.export import export_geotiff

    out = tmp_path_factory.mktemp("export") / "geotiff"
    res = export_geotiff(dataset, out)
    assert res.samples > 0 and all(p.is_file() for p in res.files)
    return out / "drive"


class _Decoded:
    """The dataset's arrays by path as gtgen reads them (packed ones as floats)."""

    def __init__(self, path: Path) -> None:
        from gtgen.storage.dataset import DatasetStore

        self.ds = DatasetStore(path)

    def __getitem__(self, path: str) -> np.ndarray:
        return self.ds.read(path)


def _nearest_labelling_sample(g, r, size, res, E, N):
    """Oracle: for each point (E, N), the value of the label of the sample whose vehicle is
    nearest among those whose grid holds the point in a labelled cell (brute force)."""
    T = g["meta/T_crs_target"][:]
    dE, dN = E[:, None] - T[None, :, 0, 3], N[:, None] - T[None, :, 1, 3]
    x = T[None, :, 0, 0] * dE + T[None, :, 1, 0] * dN
    y = T[None, :, 0, 1] * dE + T[None, :, 1, 1] * dN
    half = 0.5 * size * res
    i, j = np.floor((x + half) / res).astype(int), np.floor((y + half) / res).astype(int)
    inside = (i >= 0) & (i < size) & (j >= 0) & (j < size)
    region = g[f"labels/{r}/region"][:]
    elev = g[f"labels/{r}/elevation_m"][:]
    k = np.arange(T.shape[0])[None, :].repeat(len(E), 0)
    lab = inside & (region[k, np.clip(i, 0, size - 1), np.clip(j, 0, size - 1)] > 0)
    d2 = np.where(lab, x * x + y * y, np.inf)
    best = np.argmin(d2, 1)
    rows = np.arange(len(E))
    ok = np.isfinite(d2[rows, best])
    val = elev[best, i[rows, best].clip(0, size - 1), j[rows, best].clip(0, size - 1)] + T[best, 2, 3]
    return np.where(ok, val, np.nan)


def test_geotiff_mosaic_is_in_the_dataset_crs_and_each_pixel_is_the_nearest_samples_label(dataset, tifs, cfg):
    import rasterio

    from gtgen.storage.dataset import DatasetStore

    g = _Decoded(dataset)
    info = DatasetStore(dataset)
    for r in ("micro", "short"):
        gr = cfg.grids.get(r)
        with rasterio.open(tifs / r / "elevation_m.tif") as src:
            assert src.crs.to_string() == info.info.drives[0].crs
            assert src.res == (gr.resolution_m, gr.resolution_m)
            assert src.overviews(1) or max(src.shape) <= 256, "a COG has overviews down to its 256 px tiles"
            assert src.profile["tiled"]
            band = src.read(1)
            rng = np.random.default_rng(0)
            rows, cols = np.nonzero(np.isfinite(band))
            pick = rng.choice(len(rows), 300, replace=False)
            E, N = rasterio.transform.xy(src.transform, rows[pick], cols[pick])
        want = _nearest_labelling_sample(g, r, gr.size, gr.resolution_m, np.asarray(E), np.asarray(N))
        got = band[rows[pick], cols[pick]]
        # ties between equally near samples aside, the mosaic is the oracle's value
        assert np.mean(np.isclose(got, want, atol=1e-3)) > 0.98, r


def test_geotiff_rocks_stand_at_their_easting_northing_and_the_dem_mosaic_matches_the_tile(dataset, tifs, cfg, drive_dir):
    import rasterio
    from rasterio.vrt import WarpedVRT

    from gtgen.synth.world import SynthWorld

    world = SynthWorld(cfg.synth)
    hits = 0
    with rasterio.open(tifs / "micro" / "elevation_m.tif") as el, rasterio.open(tifs / "micro" / "dem_elevation_m.tif") as dm, \
         rasterio.open(tifs / "micro" / "region.tif") as rg, rasterio.open(tifs / "micro" / "risk.tif") as rk:
        e, d, reg, risk = el.read(1), dm.read(1), rg.read(1), rk.read(1)
        for uv, h in zip(world.obstacles.rock_uv, world.obstacles.rock_height):
            east, north = world.utm(uv)
            row, col = el.index(east, north)
            if 0 <= row < el.height and 0 <= col < el.width and reg[row, col] in (1, 2):
                hits += 1
                assert e[row, col] - d[row, col] > 0.4 * h, "an observed rock stands above the bare-earth DEM at its pixel"
                assert risk[row, col] > 0.5
                ring = e[row - 20:row + 21, col - 20:col + 21] - d[row - 20:row + 21, col - 20:col + 21]
                assert abs(np.nanmedian(ring)) < 0.1, "the ground around it lies on the DEM"
        assert hits >= 1
        tile = sorted((drive_dir / "dem").glob("*.tif"))[0]
        with rasterio.open(tile) as src, WarpedVRT(src, crs=dm.crs, transform=dm.transform, width=dm.width, height=dm.height,
                                                    resampling=rasterio.enums.Resampling.bilinear) as v:
            ref = v.read(1, masked=True).filled(np.nan)
        both = np.isfinite(ref) & np.isfinite(d)
        assert both.sum() > 1000
        assert np.median(np.abs(ref - d)[both]) < 0.03  # the aligned DEM mosaic overlays the tile


def test_geotiff_per_sample_rasters_put_each_cell_at_its_placement(dataset, tmp_path, cfg):
    import rasterio

    from gtgen.export import export_geotiff
    from gtgen.grids import grid_xy

    res = export_geotiff(dataset, tmp_path / "s", samples=[3])
    assert res.samples == 1
    g = _Decoded(dataset)
    T = g["meta/T_crs_target"][3]
    gr = cfg.grids.short
    lab = g["labels/short/elevation_m"][3]
    x, y = grid_xy(gr.size, gr.resolution_m)
    rng = np.random.default_rng(1)
    i, j = rng.integers(0, gr.size, 200), rng.integers(0, gr.size, 200)
    E = T[0, 0] * x[i, j] + T[0, 1] * y[i, j] + T[0, 3]
    N = T[1, 0] * x[i, j] + T[1, 1] * y[i, j] + T[1, 3]
    with rasterio.open(tmp_path / "s" / "samples" / "3" / "short" / "elevation_m.tif") as src:
        got = np.array([v[0] for v in src.sample(zip(E, N))])
        # the pixel holding (E, N) reads the cell that holds the pixel's own centre: map
        # that centre back into the sample's grid
        rows, cols = rasterio.transform.rowcol(src.transform, E, N)
        pe, pn = (np.asarray(a) for a in rasterio.transform.xy(src.transform, rows, cols))
    dE, dN = pe - T[0, 3], pn - T[1, 3]
    px, py = T[0, 0] * dE + T[1, 0] * dN, T[0, 1] * dE + T[1, 1] * dN
    half = 0.5 * gr.size * gr.resolution_m
    pi, pj = np.floor((px + half) / gr.resolution_m).astype(int), np.floor((py + half) / gr.resolution_m).astype(int)
    inside = (pi >= 0) & (pi < gr.size) & (pj >= 0) & (pj < gr.size)
    want = np.where(inside, lab[pi.clip(0, gr.size - 1), pj.clip(0, gr.size - 1)] + T[2, 3], np.nan)
    ok = np.isfinite(want)
    assert ok.sum() > 50
    np.testing.assert_allclose(got[ok], want[ok], atol=1e-3)
    near = np.abs(pi - i) + np.abs(pj - j) <= 2
    assert near.all(), "the pixel holding a cell's centre reads that cell or a neighbour"


def test_mcap_export_plays_back_with_rosbags(dataset, tmp_path, cfg):
    from rosbags.highlevel import AnyReader

    from gtgen.bag.decode.gridmap import decode_gridmap
    from gtgen.bag.msgdefs import typestore
    from gtgen.export import export_mcap

    out = tmp_path / "labels.mcap"
    res = export_mcap(dataset, out)
    assert out.is_file() and not any(p.name.endswith(".partial") for p in tmp_path.iterdir())
    g = _Decoded(dataset)
    t_ns = g["meta/t_ns"][:]
    S = len(t_ns)
    want = {"/tf", "/gtgen/voxel_points"} | {f"/gtgen/{k}/{r}" for k in ("labels", "xracer") for r in ("micro", "short")}
    want |= {f"/gtgen/labels/{r}/grid" for r in ("micro", "short")}
    want |= {f"/gtgen/camera_{c}/{p}" for c in ("front", "left", "right", "back") for p in ("image/compressed", "camera_info")}
    with AnyReader([out], default_typestore=typestore(False)) as reader:
        topics = {c.topic: c for c in reader.connections}
        assert set(topics) == want
        for c in reader.connections:
            assert c.msgcount == S, c.topic
        stamps = [t for _, t, _ in reader.messages(connections=[topics["/gtgen/labels/short"]])]
        assert stamps == sorted(t_ns.tolist())
        k = 5
        for conn, t, raw in reader.messages(connections=[topics["/gtgen/labels/micro"], topics["/gtgen/camera_front/image/compressed"],
                                                         topics["/tf"]]):
            if t != t_ns[k]:
                continue
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/gtgen/labels/micro":
                m = decode_gridmap(msg)
                assert m.frame_id == "target" and m.resolution_m == pytest.approx(cfg.grids.micro.resolution_m)
                np.testing.assert_array_equal(m.layers["elevation"], g["labels/micro/elevation_m"][k])
                np.testing.assert_array_equal(m.layers["region"], g["labels/micro/region"][k].astype(np.float32))
            elif conn.topic == "/tf":
                tf = {(x.header.frame_id, x.child_frame_id): x.transform.translation for x in msg.transforms}
                T0 = g["meta/T_crs_target"][int(np.argmin(t_ns))]
                Tk = g["meta/T_crs_target"][k]
                p = tf[("map", "target")]
                np.testing.assert_allclose([p.x, p.y, p.z], Tk[:3, 3] - T0[:3, 3], atol=1e-6)
                assert ("base_link", "camera_front") in tf
            else:
                # the stored JPEG file, byte for byte
                assert bytes(msg.data) == g["inputs/jpeg"][k, 0, : int(g["inputs/jpeg_nbytes"][k, 0])].tobytes()
    assert res.counts["/tf"] == S


def test_export_cli_and_its_errors(dataset, tmp_path):
    p = run_cli("export", "mcap", str(dataset), "-o", str(tmp_path / "x.bag"))
    assert p.returncode == 1 and p.stderr.strip().count("\n") == 0 and ".mcap" in p.stderr
    p = run_cli("export", "geotiff", str(dataset), "--samples", "99999", "-o", str(tmp_path / "g"))
    assert p.returncode == 1 and "99999" in p.stderr and "Traceback" not in p.stderr
    p = run_cli("export", "geotiff", str(dataset), "--samples", "1", "-o", str(tmp_path / "g"))
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "g" / "samples" / "1" / "micro" / "risk.tif").is_file()


def test_open_dataset_gives_schema_splits_and_xarray_in_metres(dataset, cfg):
    import zarr

    import gtgen
    from gtgen.grids import cell_centers

    ds = gtgen.open_dataset(dataset)
    assert len(ds) > 0 and sum(len(v) for v in ds.splits.values()) == len(ds)
    assert ds.schema["labels/micro/elevation_m"].units.startswith("m")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no foreign files inside the store
        zarr.open_group(str(dataset), mode="r")
        list(zarr.open_group(str(dataset), mode="r").members(max_depth=None))
    x = ds.xarray("labels/micro")
    assert x["elevation_m"].dims == ("sample", "x_m", "y_m")
    np.testing.assert_allclose(x["x_m"].values, cell_centers(cfg.grids.micro.size, cfg.grids.micro.resolution_m))
    assert x["x_m"].attrs["units"] == "m"
    t = ds.zarr["meta/t_ns"][:]
    np.testing.assert_array_equal(x["sample"].values.astype("datetime64[ns]").astype(np.int64), t)
    s = ds.xarray("labels/short")
    assert s["x_m"].values[-1] == pytest.approx(0.5 * cfg.grids.short.length_m - 0.5 * cfg.grids.short.resolution_m)
    # a cell by its coordinates in metres
    v = x["elevation_m"].sel(x_m=0.0, y_m=0.0, method="nearest").isel(sample=0).values.item()
    i = int(np.argmin(np.abs(x["x_m"].values)))
    assert v == pytest.approx(float(ds.read("labels/micro/elevation_m", slice(0, 1))[0, i, i]), nan_ok=True)
    tr = ds.torch("train")
    assert len(tr) == len(ds.splits["train"])
    item = tr[0]
    assert item["images"].shape[:2] == (4, 3) and item["micro/elevation"].ndim == 2 and item["micro/region"].dtype.is_floating_point is False


def test_geotiff_tiles_give_the_one_tile_mosaic(dataset, tifs, tmp_path, monkeypatch):
    """Memory is bounded by mosaic tiles: written tile by tile (many small tiles here), the
    mosaic equals the one written as a single tile."""
    import rasterio

    import gtgen.export.geotiff as gt

    monkeypatch.setattr(gt, "TILE", 100)
    monkeypatch.setattr(gt, "BLOCK", 3)
    gt.export_geotiff(dataset, tmp_path / "tiled")
    for r in ("micro", "short"):
        for layer in gt.LAYERS:
            with rasterio.open(tifs / r / f"{layer}.tif") as a, rasterio.open(tmp_path / "tiled" / "drive" / r / f"{layer}.tif") as b:
                assert a.transform == b.transform and a.shape == b.shape
                assert a.shape[0] > 100 or a.shape[1] > 100, "several tiles"
                np.testing.assert_array_equal(a.read(1), b.read(1))
