"""Write 1 m DEM GeoTIFF tiles of the synthetic world, named and laid out like USGS 3DEP."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gtgen.synth.world import SynthWorld

DEM_NODATA = -999999.0
DEM_RES_M = 1.0


def tile_name(cfg, e0: float, n1: float) -> str:
    """Return a USGS-like tile name for the tile with upper-left corner (e0, n1)."""
    zone = cfg.crs.split(":")[-1][-2:]
    return f"USGS_1M_{zone}_x{int(e0) // 100}y{int(n1) // 100}_CA_PasoRobles_gtgen_synth.tif"


def write_dem_tiles(world: SynthWorld, folder: Path) -> list[Path]:
    """Write DEM tiles covering the path plus a margin; a tile border crosses the drive."""
    import rasterio
    from rasterio.transform import from_origin

    cfg = world.cfg
    folder.mkdir(parents=True)
    rng = np.random.default_rng([cfg.seed, 6])
    tile = cfg.dem_tile_m
    utm = world.utm(world.path.uv)
    lo = utm.min(axis=0) - cfg.dem_margin_m
    hi = utm.max(axis=0) + cfg.dem_margin_m
    mid = utm[len(utm) // 2]
    # shift the tile lattice so that a border runs through the middle of the drive
    off = np.floor(mid) % tile
    e_starts = off[0] + tile * np.arange(np.floor((lo[0] - off[0]) / tile), np.ceil((hi[0] - off[0]) / tile))
    n_starts = off[1] + tile * np.arange(np.floor((lo[1] - off[1]) / tile), np.ceil((hi[1] - off[1]) / tile))
    ox, oy = cfg.origin_e_m, cfg.origin_n_m
    paths = []
    for e0 in e_starts:
        for n0 in n_starts:
            g = world.terrain.eval_grid(e0 - ox, n0 - oy, DEM_RES_M, tile, tile)
            z = g["ground"].astype(np.float64) + rng.normal(0, cfg.dem_noise_m, (tile, tile))
            # GeoTIFF rows run north to south: transpose (u, v) -> (v, u) and flip rows
            band = z.T[::-1].astype(np.float32)
            path = folder / tile_name(cfg, e0, n0 + tile)
            with rasterio.open(
                path, "w", driver="GTiff", width=tile, height=tile, count=1, dtype="float32",
                crs=cfg.crs, transform=from_origin(e0, n0 + tile, DEM_RES_M, DEM_RES_M),
                nodata=DEM_NODATA, compress="deflate", tiled=True, blockxsize=256, blockysize=256,
            ) as dst:
                dst.write(band, 1)
            paths.append(path)
    return paths
