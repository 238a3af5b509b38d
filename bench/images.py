"""What the stored JPEG images cost: bytes per sample, and how fast the loader decodes them.

On the 30 s default drive (cameras at 640 x 396, one with a plumb_bob lens) through
extract, fuse and dem-align:

- bytes: a sample's four stored JPEG files (``inputs/jpeg_nbytes``), their padded rows on
  disk (``inputs/jpeg`` after zstd), and the whole dataset per sample; beside them what
  four raw RGB images of that size would take (the format before version 5 stored raw
  RGB, at 160 x 100 by default);
- decode: JPEG files per second decoded at the stored size (the paper preset's 640 x 396)
  and at the tiny preset's 96 x 60 (libjpeg's 1/4-scale decode, then a resize), beside
  a plain copy of the raw bytes (what the raw format's loader did), one process;
- the loader: ``ShardDataset`` samples per second with images only (points and the raw
  grid off), both presets.

Expected (not timed here, the lead times it on an idle machine): a 640 x 396 JPEG
decodes in about 2-3 ms on one core, so the paper preset's four images add ~10 ms per
sample (a few % of a GPU step); the tiny preset's 1/4-scale decode is 3-4x faster than
the full one. Four images take ~50 kB on the synthetic drive (smooth renders) and
~200-400 kB for real 640 x 396 camera frames at quality 90, against 3 MB raw.
"""

from __future__ import annotations

from _common import drive, fresh_workspace, header, run_measured

MEASURE = """
import json, sys, time
import numpy as np
from pathlib import Path
from gtgen.storage.dataset import DatasetStore
from gtgen.train.data import decode_at
from gtgen.config import load_config
from gtgen.train.presets import preset_overrides
from gtgen.train.data import ShardDataset

path = Path(sys.argv[1])
ds = DatasetStore(path)
S = ds.n_samples
nb = ds.read("inputs/jpeg_nbytes").astype(np.int64)
def size(p):
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
files = [f for k in range(min(S, 16)) for f in ds.jpeg_files(k)]
w, h = ds.info.image_size
out = {"samples": S, "jpeg_per_sample": float(nb.sum(1).mean()), "jpeg_disk_per_sample": size(path / "inputs" / "jpeg") / S,
       "dataset_per_sample": size(path) / S, "raw_per_sample": 4 * 3 * w * h, "size": [w, h]}
def rate(fn, n):
    t = time.perf_counter()
    for i in range(n):
        fn(files[i % len(files)])
    return n / (time.perf_counter() - t)
raw = np.zeros((h, w, 3), np.uint8)
out["decode_full_per_s"] = rate(lambda f: decode_at(f, w, h), 200)
out["decode_tiny_per_s"] = rate(lambda f: decode_at(f, 96, 60), 200)
out["copy_raw_per_s"] = rate(lambda f: raw.copy(), 2000)
for preset in ("tiny", "paper"):
    cfg = load_config(None, preset_overrides(preset), {"train": {"points": False, "raw_elevation": False}})
    loader = ShardDataset(path, cfg.train)
    n = min(len(loader), 40)
    t = time.perf_counter()
    for i in range(n):
        loader[i]
    out[f"loader_{preset}_per_s"] = n / (time.perf_counter() - t)
print(json.dumps(out))
"""

if __name__ == "__main__":
    import json
    import subprocess
    import sys

    header("bench/images.py")
    d = drive(30)
    ws = fresh_workspace("ws_images")
    run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "drive.zarr")])
    run_measured(["fuse", str(ws / "drive.zarr")])
    run_measured(["dem-align", str(ws / "drive.zarr"), "--dem", str(d / "dem")])
    r = json.loads(subprocess.run([sys.executable, "-c", MEASURE, str(ws / "dataset.zarr")], capture_output=True, text=True,
                                  check=True).stdout.strip().splitlines()[-1])
    w, h = r["size"]
    print(f"bytes per sample ({r['samples']} samples, {w} x {h}): four JPEG files {r['jpeg_per_sample'] / 1e3:.1f} kB, "
          f"their padded rows on disk {r['jpeg_disk_per_sample'] / 1e3:.1f} kB, raw RGB would be {r['raw_per_sample'] / 1e3:.0f} kB "
          f"({r['raw_per_sample'] / r['jpeg_disk_per_sample']:.0f}x); whole dataset {r['dataset_per_sample'] / 1e6:.2f} MB")
    print(f"decode: {r['decode_full_per_s']:.0f} JPEG/s at {w} x {h}, {r['decode_tiny_per_s']:.0f} JPEG/s to 96 x 60 "
          f"({r['decode_tiny_per_s'] / r['decode_full_per_s']:.1f}x), raw copy {r['copy_raw_per_s']:.0f}/s")
    print(f"loader (images only): tiny {r['loader_tiny_per_s']:.1f} samples/s, paper {r['loader_paper_per_s']:.1f} samples/s")
