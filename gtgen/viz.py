"""``gtgen viz``: one figure of one sample, forward up, left to the left."""

from __future__ import annotations

import textwrap
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from gtgen.config import RANGES
from gtgen.errors import ConfigError
from gtgen.runtime.output import save_figure
from gtgen.storage.dataset import DatasetStore

REGION_COLORS = np.array([[0.85, 0.85, 0.85], [0.98, 0.59, 0.15], [0.59, 0.14, 0.57], [0.26, 0.43, 0.69]])
TITLE_PT = 12  # the title's font size [pt]
COLORBAR_LABELS = {"terrain": "elevation [m, rel. base z at t]", "magma": "risk [0..1]", "viridis": "confidence [0..1]"}


def _utc(t_ns: int) -> str:
    """Return a stamp as ISO 8601 UTC to the millisecond (epoch seconds mean nothing to a reader)."""
    return datetime.fromtimestamp(int(t_ns) // 1_000_000 / 1e3, tz=timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", " UTC")


def forward_up(a: np.ndarray) -> np.ndarray:
    """Return a target-frame grid (axis 0 = x forward, axis 1 = y left) as an image, forward up."""
    return a[::-1, ::-1]


def render_sample(dataset: Path, index: int, out: Path, prediction: dict[str, np.ndarray] | None = None,
                  overwrite: bool = False) -> Path:
    """Write a PNG of sample ``index``: images, and per range labels, X-Racer at t and DEM."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ds = DatasetStore(dataset)
    if not 0 <= index < ds.n_samples:
        raise ConfigError(f"--sample {index} out of range; the dataset has {ds.n_samples} samples (0..{ds.n_samples - 1})")
    cols = ["elevation", "risk", "confidence", "regions", "X-Racer elevation at t", "DEM (aligned)"]
    if prediction:
        cols += ["predicted elevation", "predicted risk"]
    cams = ds.cameras  # a row of images when the dataset has any
    top = 1 if cams else 0
    fig = plt.figure(figsize=(3 * len(cols), 3.5 * (2 + top)))
    gs = fig.add_gridspec(2 + top, len(cols))
    if cams:
        row0 = gs[0, :].subgridspec(1, len(cams))
        for c_i, (cam, img) in enumerate(zip(cams, ds.images(index))):
            ax = fig.add_subplot(row0[0, c_i])
            ax.imshow(img)
            ax.set_title(cam)
            ax.axis("off")
    for row, r in enumerate(RANGES, start=top):
        el = ds.grid("labels", r, "elevation_m")[index]
        vmin, vmax = np.nanpercentile(el, [2, 98]) if np.isfinite(el).any() else (-1, 1)
        reg = ds.grid("labels", r, "region")[index]
        n = el.shape[0]
        L = n * ds.config.grids.get(r).resolution_m / 2
        ext = (L, -L, -L, L)  # left edge is +y (left), top is +x (forward)
        panels = [
            (el, "terrain", vmin, vmax), (ds.grid("labels", r, "risk")[index], "magma", 0, 1),
            (_qa_grid(ds, "labels", r, "confidence", index, el.shape), "viridis", 0, 1), (REGION_COLORS[reg], None, None, None),
            (ds.grid("xracer", r, "elevation_m")[index], "terrain", vmin, vmax),
            (_qa_grid(ds, "dem", r, "elevation_m", index, el.shape), "terrain", vmin, vmax),
        ]
        missing = {2: not ds.has_grid("labels", r, "confidence"), 5: not ds.has_grid("dem", r, "elevation_m")}
        if prediction:  # a single-range model's other range: empty panels
            none = np.full(el.shape, np.nan)
            panels += [(prediction.get(f"{r}/elevation", none), "terrain", vmin, vmax), (prediction.get(f"{r}/risk", none), "magma", 0, 1)]
        for c_i, (arr, cmap, lo, hi) in enumerate(panels):
            ax = fig.add_subplot(gs[row, c_i])
            im = ax.imshow(forward_up(arr), cmap=cmap, vmin=lo, vmax=hi, extent=ext, interpolation="nearest")
            ax.plot([0], [0], marker="^", color="red", markersize=8)
            ax.set_title(f"{r}: {cols[c_i]}" + ("\n(not stored: shards.qa_ranges)" if missing.get(c_i) else ""), fontsize=9)
            ax.set_xlabel("y left [m]", fontsize=7)
            ax.set_ylabel("x forward [m]", fontsize=7)
            ax.tick_params(labelsize=7)
            if cmap is not None:
                cb = fig.colorbar(im, ax=ax, fraction=0.046)
                cb.set_label(COLORBAR_LABELS[cmap], fontsize=7)
                cb.ax.tick_params(labelsize=7)
    t_ns, drive = ds.meta("t_ns"), ds.meta("drive")
    t, t0 = int(t_ns[index]), int(t_ns[drive == drive[index]].min())
    fit = float(ds.meta("icp_fitness")[index])
    placed = f"ICP fitness {fit:.3f}" if np.isfinite(fit) else "no DEM placement (fused labels alone)"
    lines = [f"{dataset.name} sample {index}:  t = {(t - t0) / 1e9:.2f} s after the drive's first sample ({_utc(t)}),  {placed}",
             "forward up; regions: orange observed past/current, purple observed future, blue unobserved (DEM), grey none"]
    # wrapped to the figure's width (about 0.6 em a character), so a long name or stamp never runs off its edges
    chars = int(fig.get_figwidth() * 72 / (0.6 * TITLE_PT))
    fig.suptitle("\n".join(textwrap.fill(ln, chars) for ln in lines), fontsize=TITLE_PT)
    n_lines = sum(len(textwrap.wrap(ln, chars)) for ln in lines)
    fig.tight_layout(rect=(0, 0, 1, 1 - (1.4 * n_lines + 0.6) * TITLE_PT / (72 * fig.get_figheight())))  # the panels below the title
    save_figure(fig, out, overwrite, dpi=70)
    plt.close(fig)
    return out


def _qa_grid(ds: DatasetStore, kind: str, r: str, layer: str, index: int, shape: tuple[int, ...]) -> np.ndarray:
    """Return sample ``index``'s QA grid, or NaN (a blank panel) where the dataset does not
    store it (``shards.qa_ranges``)."""
    return ds.grid(kind, r, layer)[index] if ds.has_grid(kind, r, layer) else np.full(shape, np.nan, np.float32)
