"""``gtgen export``: the dataset for the tools people already look with (QGIS, Foxglove)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from gtgen.cli.app import WORKSPACE, OverwriteOpt, app, table

export = typer.Typer(no_args_is_help=True, rich_markup_mode="markdown", help="""Export a dataset: GeoTIFF mosaics for GIS, one MCAP recording for Foxglove; or a trained model as ONNX.

**Examples**

```
gtgen export geotiff -o qgis/
gtgen export mcap -o labels.mcap
gtgen export onnx --ckpt runs/latest/best.pt -o model.onnx
```
""")
app.add_typer(export, name="export")


def _samples(text: Optional[str]) -> Optional[list[int]]:
    if text is None:
        return None
    try:
        out = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise typer.BadParameter(f"'{text}' is not a comma-separated list of sample indices, e.g. 3,7", param_hint="'--samples'") from None
    if not out or min(out) < 0:
        raise typer.BadParameter(f"'{text}' lists no sample or a negative one; expected indices >= 0, e.g. 3,7", param_hint="'--samples'")
    return out


@export.command()
def geotiff(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", metavar="DATASET", help="dataset from 'gtgen dem-align' or 'gtgen build'"),
    out: Path = typer.Option(Path("export/geotiff"), "-o", "--out", help="folder to write"),
    samples: Optional[str] = typer.Option(None, "--samples", metavar="I,J,...", help="instead of mosaics, one raster set per listed sample, e.g. 3,7"),
    overwrite: bool = OverwriteOpt,
) -> None:
    """Write north-up Cloud-Optimized GeoTIFFs in the dataset's CRS: per drive and range the
    mosaics of the labels (elevation in the DEM's datum, risk, region, count, last
    observation time) and of the aligned DEM.

    Reads only the dataset (its CRS and grids as recorded): no --config.

    **Examples**

    ```
    gtgen export geotiff -o qgis/
    gtgen export geotiff --samples 3,7 -o qgis/samples
    ```
    """
    from gtgen.export import export_geotiff

    res = export_geotiff(dataset, out, _samples(samples), overwrite=overwrite)
    table("gtgen export geotiff", [("out", res.out), ("samples", res.samples), ("files", len(res.files)),
                                   ("e.g.", res.files[0] if res.files else "-")])


@export.command()
def mcap(
    dataset: Path = typer.Argument(WORKSPACE / "dataset.zarr", metavar="DATASET", help="dataset from 'gtgen dem-align' or 'gtgen build'"),
    out: Path = typer.Option(Path("export/dataset.mcap"), "-o", "--out", help=".mcap file to write"),
    overwrite: bool = OverwriteOpt,
) -> None:
    """Write one ROS 2 MCAP that Foxglove plays: per sample the label and X-Racer grids
    (GridMap and foxglove Grid), TF, the four images and the voxel points, at the sample
    times.

    Reads only the dataset: no --config.

    **Examples**

    ```
    gtgen export mcap -o labels.mcap
    gtgen export mcap datasets/paso.zarr -o paso.mcap
    ```
    """
    from gtgen.export import export_mcap

    res = export_mcap(dataset, out, overwrite=overwrite)
    rows = [("out", res.out), ("samples", res.samples)] + [(f"  {k}", v) for k, v in res.counts.items()]
    table("gtgen export mcap", rows)


@export.command()
def onnx(
    ckpt: Path = typer.Option(Path("runs/latest/ckpt.pt"), "--ckpt", metavar="CKPT", help="checkpoint from 'gtgen train'"),
    out: Path = typer.Option(Path("model.onnx"), "-o", "--out", help=".onnx file to write"),
    overwrite: bool = OverwriteOpt,
) -> None:
    """Write the trained network as one ONNX graph (opset 18, batch 1) for onnxruntime or
    TensorRT: inputs, their layout and normalisation in docs/training.md ("Deployment") and in
    gtgen/train/onnx.py.

    **Examples**

    ```
    gtgen export onnx --ckpt runs/latest/best.pt -o model.onnx
    ```
    """
    from gtgen.train.onnx import export_onnx

    res = export_onnx(ckpt, out, overwrite=overwrite)
    table("gtgen export onnx", [("out", res.out), ("checkpoint", f"{ckpt} (preset {res.preset}, step {res.step})"),
                                ("inputs", ", ".join(res.inputs)), ("outputs", ", ".join(res.outputs)),
                                ("cameras", ", ".join(res.cameras) if res.cameras else "none (no images input)")])
