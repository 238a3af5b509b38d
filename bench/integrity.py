"""What integrity costs: zstd checksums on every chunk, the manifest of every file (size
and CRC32C of every chunk and shard file, CRC32C of each shard's index), the checks on
every read, and ``gtgen verify``. Ratios of one run; on the 60 s default drive's dataset.

- bytes: the manifest and the 4-byte checksum per chunk against the store's size;
- write: encoding a grid with and without its checksum; writing the manifest against the
  whole dem-align that made the store, and the share of it the CRC32C hashes take (the
  manifest of sizes only, the one before, is the rest);
- read: decoding with and without the checksum; a sample's label grids read by the
  training loader's readers unchecked, checked by sizes only (before the hashes) and
  checked with the hashes (after: each shard's index); every per-sample metadata array read
  whole (zarr, small shards hashed whole) with sizes only and with the hashes; opening a
  store (kind, version, metadata CRC32C of every zarr.json);
- verify: ``gtgen verify`` of the dataset against the dem-align that made it, and the share
  its hashes (reading and hashing every file) take of it.
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
sizes = [SampleReader(ds.array(f"{k}/{r}/{a}"), check=ds.manifest.check, check_size=ds.manifest.check_size) for k, r, a in names]
read(sizes)
s_ = min(per(lambda: read(sizes), 1) for _ in range(3))
out["read"] = a / b
out["read_sizes"] = s_ / b
out["read_ms_per_sample"] = 1000 * a / len(ks)

# every per-sample metadata array read whole, with the hashes and with sizes only (a check
# that skips the CRC32C: the one before)
from gtgen.storage import integrity as I
metas = [p for p in json.loads((path / I.MANIFEST / "zarr.json").read_text())["attributes"]["gtgen_manifest"]["metadata"]
         if p.startswith("meta/") and p.count("/") == 2]  # meta/<array>/zarr.json
metas = sorted({p.rsplit("/", 1)[0] for p in metas})
def read_meta():
    d = DatasetStore(path)
    for m in metas:
        d.read(m)
read_meta()
hashed = min(per(read_meta, 1) for _ in range(3))
full_check = I.Manifest.check
def size_check(self, key, data):
    want = self.files.get(key)
    if want is None or data is None:
        return full_check(self, key, data)
    if memoryview(data).nbytes != want[0]:
        raise self.damaged_chunk(key, "size")
I.Manifest.check = size_check
sized = min(per(read_meta, 1) for _ in range(3))
I.Manifest.check = full_check
out["meta_read"] = hashed / sized

# verify whole, and its hashes alone (every file read and hashed)
from gtgen.storage.stores import verify_store
t = time.perf_counter(); v = verify_store(path)[1]; out["verify_s"] = time.perf_counter() - t
assert not v.problems, v.problems
files = [f for f in path.rglob("*") if f.is_file()]
t = time.perf_counter()
for f in files:
    I.crc32c(f.read_bytes())
out["hash_all_s"] = time.perf_counter() - t
shutil = __import__("shutil"); shutil.rmtree(path / MANIFEST)
t = time.perf_counter(); write_manifest(path); out["manifest_s"] = time.perf_counter() - t
t = time.perf_counter(); I._store_files(path); out["manifest_sizes_s"] = time.perf_counter() - t  # walking and sizing the files alone
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
          f"= {100 * r['manifest_s'] / t_align:.1f} % of dem-align ({t_align:.1f} s), of which the CRC32C hashes "
          f"{100 * (r['manifest_s'] - r['manifest_sizes_s']) / t_align:.1f} % (sizes alone {r['manifest_sizes_s']:.2f} s)")
    print(f"read: decode with / without checksum {r['decode']:.2f}x; a sample's label grids through the checked readers / "
          f"unchecked: with the hashes {r['read']:.2f}x, sizes only (before) {r['read_sizes']:.2f}x ({r['read_ms_per_sample']:.2f} ms "
          f"per sample with the hashes); every per-sample metadata array read whole, with / without the hashes {r['meta_read']:.2f}x; "
          f"opening the dataset {r['open_ms']:.0f} ms")
    print(f"verify: {r['verify_s']:.1f} s = {r['verify_s'] / t_align:.2f}x the dem-align that wrote the dataset; reading and "
          f"hashing every file {100 * r['hash_all_s'] / r['verify_s']:.0f} % of it (the rest: decoding every chunk)")
