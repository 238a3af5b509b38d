"""Draw an exported label mosaic beside the DEM tiles it overlays, and their difference.

    python scripts/plot_export.py export/geotiff/drive/micro drive/dem -o mosaic_vs_dem.png

Reads the mosaic's ``elevation_m.tif`` and ``risk.tif``, and the DEM tiles of the folder
reprojected onto the mosaic's grid (rasterio WarpedVRT, bilinear), and writes one PNG:
label elevation, DEM, label minus DEM (vegetation and rocks stand out; bare ground near 0),
and risk.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mosaic", type=Path, help="folder <drive>/<range> written by 'gtgen export geotiff'")
    ap.add_argument("dem", type=Path, help="folder of DEM tiles")
    ap.add_argument("-o", "--out", type=Path, default=Path("mosaic_vs_dem.png"))
    a = ap.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.vrt import WarpedVRT

    with rasterio.open(a.mosaic / "elevation_m.tif") as src:
        label, crs, tr, w, h = src.read(1), src.crs, src.transform, src.width, src.height
    with rasterio.open(a.mosaic / "risk.tif") as src:
        risk = src.read(1)
    dem = np.full_like(label, np.nan)
    for tile in sorted(a.dem.glob("*.tif")):
        with rasterio.open(tile) as src, WarpedVRT(src, crs=crs, transform=tr, width=w, height=h, resampling=Resampling.bilinear) as v:
            z = v.read(1, masked=True).filled(np.nan)
        dem = np.where(np.isfinite(z), z, dem)
    extent = (tr.c, tr.c + w * tr.a, tr.f + h * tr.e, tr.f)
    lo, hi = np.nanpercentile(np.concatenate([label[np.isfinite(label)], dem[np.isfinite(label)]]), [1, 99])
    fig, ax = plt.subplots(1, 4, figsize=(22, 6), constrained_layout=True)
    for axi, (img, title, kw) in zip(ax, [
        (label, "label elevation (DEM datum) [m]", dict(cmap="terrain", vmin=lo, vmax=hi)),
        (np.where(np.isfinite(label), dem, np.nan), "DEM tile(s), same grid [m]", dict(cmap="terrain", vmin=lo, vmax=hi)),
        (label - dem, "label - DEM [m]", dict(cmap="RdBu_r", vmin=-1, vmax=1)),
        (risk, "risk", dict(cmap="magma", vmin=0, vmax=1)),
    ]):
        im = axi.imshow(img, extent=extent, **kw)
        axi.set_title(title)
        axi.set_xlabel(f"easting [m] ({crs.to_string()})")
        fig.colorbar(im, ax=axi, shrink=0.7)
    ax[0].set_ylabel("northing [m]")
    diff = (label - dem)[np.isfinite(label - dem)]
    fig.suptitle(f"{a.mosaic}: |label - DEM| median {np.median(np.abs(diff)):.3f} m over {diff.size} pixels")
    fig.savefig(a.out, dpi=90)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
