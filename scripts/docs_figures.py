"""Regenerate the documentation's figures (docs/img/*.png) from a short synthetic drive.

    .venv/bin/python scripts/docs_figures.py            # about 10 minutes on 2 idle cores
    .venv/bin/python scripts/docs_figures.py --keep /tmp/figs   # keep the drive and workspace

Runs the user's commands in a scratch folder (synth -> extract -> fuse -> dem-align ->
report -> viz -> train -> eval -> export geotiff), and the report of a short drive of
configs/adversity.yaml (a DEM tile shifted, one of another place, GNSS jumps), then writes
small PNGs into docs/img/: the figures gtgen draws (a sample, the QA plots, a prediction,
the mosaic beside the DEM), downscaled, and two it does not (the region masks of one
sample, the training curves).
With the real HDL-64E scan of shared/realdata beside the repo (or --hdl64), also that scan's map.
The drive is not the demo's (a 30 s drive, 150 training steps, so that the
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
# a 30 s drive spans a few hundred metres: 60 m geography blocks leave some in val; a short
# schedule of its own (not --steps, which keeps the preset's 1000) so the curves end it
FIGURE_CONFIG = """\
shards:
  split_block_m: 60
train:
  steps: 150
  val_every: 25
  val_max_samples: 16
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
    run(GTGEN, "train", "--preset", "tiny", "--config", "figures.yaml", cwd=work)
    run(GTGEN, "eval", "--ckpt", "runs/latest/ckpt.pt", "--viz", SAMPLE, cwd=work)
    run(GTGEN, "export", "geotiff", "-o", "qgis", cwd=work)


def make_adversity_workspace(work: Path) -> None:
    """A 40 s drive of configs/adversity.yaml (every realism knob on) with 100 m DEM tiles, so
    that it crosses the shifted tile and the wrong one, in ``work``: report only."""
    import yaml

    cfg = yaml.safe_load((ROOT / "configs" / "adversity.yaml").read_text())
    cfg["synth"].update(duration_s=40, dem_tile_m=100)
    work.mkdir(parents=True, exist_ok=True)
    (work / "adversity.yaml").write_text(yaml.safe_dump(cfg))
    run(GTGEN, "synth", "drive", "--config", "adversity.yaml", "--format", "mcap", "--scan-rate", "0", cwd=work)
    for stage in ("extract drive/drive.mcap", "fuse --window 60", "dem-align", "report"):
        run(GTGEN, *stage.split(), cwd=work)


def shrink(src: Path, name: str, width: int, drop_title: bool = False) -> None:
    """Write ``src`` as docs/img/``name``, ``width`` pixels wide, in a 256-colour palette
    (the figures are flat colour maps and text: a palette keeps them a tenth the size).
    ``drop_title``: cut the figure's first line of text (``gtgen viz``'s title is wider than
    its figure; the page's caption says what it said)."""
    from PIL import Image

    im = Image.open(src).convert("RGB")
    if drop_title:
        ink = np.flatnonzero((np.asarray(im.convert("L")) < 250).any(axis=1))
        end = ink[np.flatnonzero(np.diff(ink) > 1)[0]]  # the last row of the first line of ink
        im = im.crop((0, end + 1, im.width, im.height))
    h = round(im.height * width / im.width)
    im = im.resize((width, h), Image.LANCZOS).quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    im.save(IMG / name, optimize=True)
    print(f"{IMG / name}: {width} x {h}, {(IMG / name).stat().st_size / 1e3:.0f} kB")


def region_masks(work: Path, out: Path) -> None:
    """Draw sample SAMPLE's region codes in both ranges, forward up and left on the left, in
    the colours of ``gtgen viz``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import gtgen
    from gtgen.codes import LABELLED, REGIONS
    from gtgen.viz import REGION_COLORS

    ds = gtgen.open_dataset(work / "gtgen_ws" / "dataset.zarr")
    fig, axes = plt.subplots(1, 2, figsize=(9, 4.6))
    for ax, rng in zip(axes, ("micro", "short")):
        labels = ds.xarray(f"labels/{rng}")
        reg = labels.region.isel(sample=SAMPLE).values
        x = labels.x_m.values
        half = float(x[-1] + (x[1] - x[0]) / 2)  # the grid's edge: the last cell centre and half a cell
        ax.imshow(REGION_COLORS[reg[::-1, ::-1]], interpolation="nearest", extent=(half, -half, -half, half))
        ax.plot(0, 0, "^", color="crimson", ms=8)
        shares = {REGIONS[c]: np.mean(reg[reg > 0] == c) * 100 for c in LABELLED}
        ax.set_title(f"{rng}: " + ", ".join(f"{k} {v:.0f} %" for k, v in shares.items()), fontsize=9)
        ax.set_xlabel("y [m] (left on the left)")
        ax.set_ylabel("x [m] (forward up)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=REGION_COLORS[c]) for c in REGIONS]
    fig.legend(handles, [f"{c} {name}" for c, name in REGIONS.items()], loc="lower center", ncol=4, fontsize=9, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(out, dpi=100)
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
    ap.add_argument("--hdl64", type=Path, default=HDL64, help=f"the real HDL-64E scan's bag (default: {HDL64.relative_to(ROOT.parent)} beside the repo)")
    a = ap.parse_args()
    work = a.keep or Path(tempfile.mkdtemp(prefix="gtgen-docs-figures-"))
    work.mkdir(parents=True, exist_ok=True)
    IMG.mkdir(parents=True, exist_ok=True)
    try:
        if not (work / "runs" / "latest" / "eval.json").is_file():
            make_workspace(work)
        if not (work / "adversity" / "report" / "report.json").is_file():
            make_adversity_workspace(work / "adversity")
        shrink(work / "sample.png", "sample.png", 1100, drop_title=True)
        shrink(work / "sample.png", "sample_small.png", 720, drop_title=True)
        shrink(work / "report" / "qa_overview.png", "qa_overview.png", 900)
        for name in ("qa_track", "qa_label_error", "qa_rejection_signals"):
            shrink(work / "adversity" / "report" / f"{name}.png", f"adversity_{name}.png", 900)
        shrink(next((work / "runs" / "latest").glob("pred_*.png")), "prediction.png", 1100, drop_title=True)
        region_masks(work, work / "regions.png")
        shrink(work / "regions.png", "regions.png", 900)
        curves(work / "runs" / "latest", work / "curves.png")
        shrink(work / "curves.png", "curves.png", 900)
        mosaic = next((work / "qgis").glob("*/micro"))
        run(sys.executable, ROOT / "scripts" / "plot_export.py", mosaic, work / "drive" / "dem", "-o", work / "mosaic.png", cwd=work)
        shrink(work / "mosaic.png", "mosaic.png", 1000, drop_title=True)
        if a.hdl64.is_file():
            run(sys.executable, ROOT / "scripts" / "map_scan.py", a.hdl64, "--origin", "429.1", "-1226.2", "-3.1", "--sensor-height", "1.9",
                "-o", work / "hdl64.png", cwd=work)
            shrink(work / "hdl64.png", "hdl64.png", 900)
    finally:
        if a.keep is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
