"""Regenerate the documentation's figures (docs/img/*.png) from a short synthetic drive.

    .venv/bin/python scripts/docs_figures.py            # about 10 minutes on 2 cores
    .venv/bin/python scripts/docs_figures.py --keep /tmp/figs   # keep the drive and workspace

Runs the user's commands in a scratch folder (synth -> extract -> fuse -> dem-align ->
report -> viz -> train -> eval -> export geotiff), then writes small PNGs into docs/img/:
the figures gtgen draws (a sample, the QA plots, a prediction, the mosaic beside the DEM),
downscaled, and two it does not (the region masks of one sample, the training curves).
With the real HDL-64E scan of shared/realdata beside the repo, also that scan's map.
The drive is not the demo's (a 30 s drive, a few hundred training steps, so that the
figures are quick to remake): the pages say so under each figure.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
IMG = ROOT / "docs" / "img"
GTGEN = Path(sys.executable).parent / "gtgen"
HDL64 = ROOT.parent / "shared" / "realdata" / "swri_hdl64_single_scan.bag"
SAMPLE = 20
STEPS = 300
# a 30 s drive spans a few hundred metres: 60 m geography blocks leave some in val
FIGURE_CONFIG = """\
shards:
  split_block_m: 60
train:
  val_every: 50
  val_max_samples: 24
"""


def run(*args: object, cwd: Path) -> None:
    """Run one command in ``cwd``, echoing it; stop on failure."""
    cmd = [str(a) for a in args]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, cwd=cwd, check=True)


def make_workspace(work: Path) -> None:
    """The user's commands on a 30 s synthetic drive, in ``work``."""
    (work / "figures.yaml").write_text(FIGURE_CONFIG)
    run(GTGEN, "synth", "drive", "--duration", "30", "--format", "mcap", "--seed", "7", "--scan-rate", "2", cwd=work)
    run(GTGEN, "extract", "drive/drive.mcap", "--config", "figures.yaml", cwd=work)
    run(GTGEN, "fuse", "--window", "60", "--config", "figures.yaml", cwd=work)
    run(GTGEN, "dem-align", "--config", "figures.yaml", cwd=work)
    run(GTGEN, "report", cwd=work)
    run(GTGEN, "viz", "--sample", SAMPLE, "-o", "sample.png", cwd=work)
    run(GTGEN, "train", "--preset", "tiny", "--steps", STEPS, "--config", "figures.yaml", cwd=work)
    run(GTGEN, "eval", "--ckpt", "runs/latest/ckpt.pt", "--viz", SAMPLE, cwd=work)
    run(GTGEN, "export", "geotiff", "-o", "qgis", cwd=work)


def shrink(src: Path, name: str, width: int) -> None:
    """Write ``src`` as docs/img/``name``, ``width`` pixels wide, in a 256-colour palette
    (the figures are flat colour maps and text: a palette keeps them a tenth the size)."""
    from PIL import Image

    im = Image.open(src).convert("RGB")
    h = round(im.height * width / im.width)
    im = im.resize((width, h), Image.LANCZOS).quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    im.save(IMG / name, optimize=True)
    print(f"{IMG / name}: {width} x {h}, {(IMG / name).stat().st_size / 1e3:.0f} kB")


def region_masks(work: Path, out: Path) -> None:
    """Draw sample SAMPLE's region codes in both ranges, forward up and left on the left."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    import gtgen
    from gtgen.codes import REGIONS

    ds = gtgen.open_dataset(work / "gtgen_ws" / "dataset.zarr")
    colours = ListedColormap(["#ffffff", "#1b9e77", "#7570b3", "#d95f02"])
    fig, axes = plt.subplots(1, 2, figsize=(9, 4.6))
    for ax, rng in zip(axes, ("micro", "short")):
        reg = ds.xarray(f"labels/{rng}").region.isel(sample=SAMPLE).values
        half = ds.xarray(f"labels/{rng}").x_m.values.max()
        ax.imshow(reg[::-1, ::-1], cmap=colours, vmin=-0.5, vmax=3.5, interpolation="nearest", extent=(half, -half, -half, half))
        shares = [np.mean(reg[reg > 0] == c) * 100 for c in (1, 2, 3)]
        ax.set_title(f"{rng}: obs PC {shares[0]:.0f} %, obs F {shares[1]:.0f} %, unobs {shares[2]:.0f} %", fontsize=9)
        ax.set_xlabel("y [m] (left on the left)")
        ax.set_ylabel("x [m] (forward up)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours(c)) for c in range(4)]
    fig.legend(handles, [REGIONS[c].partition(":")[0] for c in range(4)], loc="lower center", ncol=4, fontsize=9, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(out, dpi=110)
    plt.close(fig)


def curves(run_dir: Path, out: Path) -> None:
    """Draw the training loss (every step) and the val elevation MAE (every validation)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def read(name: str) -> dict[str, np.ndarray]:
        with open(run_dir / name) as fh:
            rows = list(csv.DictReader(fh))
        return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}

    tr, va = read("train.csv"), read("val.csv")
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4))
    a.plot(tr["step"], tr["total"], lw=0.8, color="#555555")
    a.set_xlabel("step")
    a.set_ylabel("training loss (train.csv: total)")
    for key, colour in (("micro/mae_total_m", "#1b9e77"), ("short/mae_total_m", "#d95f02"), ("total_mae_m", "#000000")):
        if key in va:
            b.plot(va["step"], va[key], marker="o", ms=3, color=colour, label=key)
    b.set_xlabel("step")
    b.set_ylabel("val elevation MAE [m] (val.csv)")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=Path, help="work in this folder and keep it (default: a temporary one, removed)")
    a = ap.parse_args()
    work = a.keep or Path(tempfile.mkdtemp(prefix="gtgen-docs-figures-"))
    work.mkdir(parents=True, exist_ok=True)
    IMG.mkdir(parents=True, exist_ok=True)
    try:
        if not (work / "runs" / "latest" / "eval.json").is_file():
            make_workspace(work)
        shrink(work / "sample.png", "sample.png", 1100)
        shrink(work / "sample.png", "sample_small.png", 720)
        for name in ("qa_overview", "qa_track", "qa_label_error", "qa_rejection_signals"):
            shrink(work / "report" / f"{name}.png", f"{name}.png", 900)
        shrink(next((work / "runs" / "latest").glob("pred_*.png")), "prediction.png", 1100)
        region_masks(work, work / "regions.png")
        shrink(work / "regions.png", "regions.png", 900)
        curves(work / "runs" / "latest", work / "curves.png")
        shrink(work / "curves.png", "curves.png", 900)
        mosaic = next((work / "qgis").glob("*/micro"))
        run(sys.executable, ROOT / "scripts" / "plot_export.py", mosaic, work / "drive" / "dem", "-o", work / "mosaic.png", cwd=work)
        shrink(work / "mosaic.png", "mosaic.png", 1000)
        if HDL64.is_file():
            run(sys.executable, ROOT / "scripts" / "map_scan.py", HDL64, "--origin", "429.1", "-1226.2", "-3.1", "--sensor-height", "1.9",
                "-o", work / "hdl64.png", cwd=work)
            shrink(work / "hdl64.png", "hdl64.png", 900)
    finally:
        if a.keep is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
