"""Write 1 m DEM GeoTIFF tiles of the synthetic world, named and laid out like USGS 3DEP."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.synth.world import SynthWorld

DEM_NODATA = -999999.0
DEM_RES_M = 1.0


def tile_name(cfg, e0: float, n1: float) -> str:
    """Return a USGS-like tile name for the tile with upper-left corner (e0, n1)."""
    zone = cfg.crs.split(":")[-1][-2:]
    return f"USGS_1M_{zone}_x{int(e0) // 100}y{int(n1) // 100}_CA_PasoRobles_gtgen_synth.tif"


WRONG_TILE_FROM_M = (0.0, 1000.0)  # where a wrong tile's terrain comes from, relative to its place [m]


def tile_lattice(world: SynthWorld) -> tuple[NDArray, NDArray]:
    """Return the easting and northing of the lower-left corners of the DEM tiles; the
    lattice is shifted so that a tile border runs through the middle of the drive."""
    cfg = world.cfg
    tile = cfg.dem_tile_m
    utm = world.utm(world.path.uv)
    lo = utm.min(axis=0) - cfg.dem_margin_m
    hi = utm.max(axis=0) + cfg.dem_margin_m
    off = np.floor(utm[len(utm) // 2]) % tile
    e_starts = off[0] + tile * np.arange(np.floor((lo[0] - off[0]) / tile), np.ceil((hi[0] - off[0]) / tile))
    n_starts = off[1] + tile * np.arange(np.floor((lo[1] - off[1]) / tile), np.ceil((hi[1] - off[1]) / tile))
    return e_starts, n_starts


def altered_tiles(world: SynthWorld) -> dict[tuple[float, float], tuple[float, float]]:
    """Return {(e0, n0) of a tile: (dE, dN) its content comes from}: the shifted tile (under
    the path at 3/4 of the drive) and the wrong tile (at 1/3), when those knobs are on."""
    cfg = world.cfg
    utm = world.utm(world.path.uv)
    e_starts, n_starts = tile_lattice(world)
    out: dict[tuple[float, float], tuple[float, float]] = {}

    def under(frac: float) -> tuple[float, float]:
        e, n = utm[int(frac * (len(utm) - 1))]
        return float(e_starts[e_starts <= e].max()), float(n_starts[n_starts <= n].max())

    if cfg.dem_wrong_tile:
        out[under(1 / 3)] = WRONG_TILE_FROM_M
    if cfg.dem_shifted_tile_m:
        out.setdefault(under(3 / 4), (-cfg.dem_shifted_tile_m, 0.0))  # the content of E - shift sits at E
    return out


def write_dem_tiles(world: SynthWorld, folder: Path) -> list[Path]:
    """Write DEM tiles covering the path plus a margin (the terrain as surveyed: before the
    terrain changes; with the shifted or wrong tile when those knobs are on)."""
    import rasterio
    from rasterio.transform import from_origin

    cfg = world.cfg
    folder.mkdir(parents=True)
    rng = np.random.default_rng([cfg.seed, 6])
    tile = cfg.dem_tile_m
    e_starts, n_starts = tile_lattice(world)
    altered = altered_tiles(world)
    ox, oy = cfg.origin_e_m, cfg.origin_n_m
    paths = []
    for e0 in e_starts:
        for n0 in n_starts:
            de, dn = altered.get((float(e0), float(n0)), (0.0, 0.0))
            g = world.terrain.eval_grid(e0 + de - ox, n0 + dn - oy, DEM_RES_M, tile, tile, surveyed=True)
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
