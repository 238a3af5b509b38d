"""What integrity costs: zstd checksums on every chunk, the manifest of every file, the
checks on every read. Ratios of one run; on the 60 s default drive's dataset.

- bytes: the manifest and the 4-byte checksum per chunk against the store's size;
- write: encoding a grid with and without its checksum, and writing the manifest against
  the whole dem-align that made the store;
- read: decoding with and without the checksum; a sample read by the training loader's
  readers with and without the manifest check; opening a store (kind, version, metadata
  CRC32C of every zarr.json).
"""

from __future__ import annotations

from _common import drive, fresh_workspace, header, run_measured

READS = """
import sys, time, json
import numpy as np
from pathlib import Path
from numcodecs import Zstd
from gtgen.storage.dataset import DatasetStore
from gtgen.storage.integrity import write_manifest, MANIFEST
from gtgen.storage.shards import SampleReader

path = Path(sys.argv[1])
grid = np.random.default_rng(0).normal(size=(250, 250)).astype(np.float32).cumsum(0)  # elevation-like
def per(fn, n):
    t = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t) / n
on, off = Zstd(level=1, checksum=True), Zstd(level=1, checksum=False)
e_on, e_off = on.encode(grid), off.encode(grid)
out = {"encode": per(lambda: on.encode(grid), 300) / per(lambda: off.encode(grid), 300),
       "decode": per(lambda: on.decode(e_on), 300) / per(lambda: off.decode(e_off), 300)}
t = time.perf_counter(); ds = DatasetStore(path); out["open_ms"] = 1000 * (time.perf_counter() - t)
names = [("labels", r, a) for r in ("micro", "short") for a in ("elevation_m", "risk", "region")]
checked = [ds.grid(*n) for n in names]
plain = [SampleReader(ds.array(f"{k}/{r}/{a}")) for k, r, a in names]
ks = np.arange(ds.n_samples)
def read(readers):
    for k in ks:
        for r in readers:
            r[k]
read(checked); read(plain)  # warm the page cache and the shard indices
a = min(per(lambda: read(checked), 1) for _ in range(3)); b = min(per(lambda: read(plain), 1) for _ in range(3))
out["read"] = a / b
out["read_ms_per_sample"] = 1000 * a / len(ks)
shutil = __import__("shutil"); shutil.rmtree(path / MANIFEST)
t = time.perf_counter(); write_manifest(path); out["manifest_s"] = time.perf_counter() - t
doc = json.loads((path / MANIFEST / "zarr.json").read_text())["attributes"]["gtgen_manifest"]
from gtgen.storage.schema import SAMPLE_ARRAYS
out["chunks"] = ds.n_samples * len(SAMPLE_ARRAYS) + len(doc["files"])  # inner chunks at most, plus whole-file chunks
out["manifest_bytes"] = (path / MANIFEST / "zarr.json").stat().st_size
out["store_bytes"] = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
print(json.dumps(out))
"""

if __name__ == "__main__":
    import json
    import subprocess
    import sys

    header("bench/integrity.py")
    d = drive(60)
    ws = fresh_workspace("ws_integrity")
    run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "drive.zarr")])
    run_measured(["fuse", str(ws / "drive.zarr")])
    t_align, _ = run_measured(["dem-align", str(ws / "drive.zarr"), "--dem", str(d / "dem")])
    r = json.loads(subprocess.run([sys.executable, "-c", READS, str(ws / "dataset.zarr")], capture_output=True, text=True,
                                  check=True).stdout.strip().splitlines()[-1])
    mb = r["store_bytes"] / 2**20
    print(f"bytes: manifest {r['manifest_bytes'] / 1024:.0f} KiB + checksums at most {4 * r['chunks'] / 1024:.0f} KiB (4 B per chunk) "
          f"= {100 * (r['manifest_bytes'] + 4 * r['chunks']) / r['store_bytes']:.3f} % of the {mb:.0f} MiB dataset")
    print(f"write: encode with / without checksum {r['encode']:.2f}x (250 x 250 float32 grid); manifest {r['manifest_s']:.2f} s "
          f"= {100 * r['manifest_s'] / t_align:.1f} % of dem-align ({t_align:.1f} s)")
    print(f"read: decode with / without checksum {r['decode']:.2f}x; a sample's label grids through the checked readers / "
          f"unchecked {r['read']:.2f}x ({r['read_ms_per_sample']:.2f} ms per sample); opening the dataset {r['open_ms']:.0f} ms")
