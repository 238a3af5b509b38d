"""Bytes per sample per array of two datasets (``python bench/bytes.py OLD NEW``).

Each array's bytes are the sizes of the files under its folder (chunks, shards and its
``zarr.json``), divided by the dataset's samples; the total is every file of the store.
Arrays in one dataset only show '-' in the other. Sorted by the old dataset's bytes.
Reads files and the root ``zarr.json`` only, so datasets of any version compare.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def samples(store: Path) -> int:
    """Return the samples of the dataset at ``store`` (the shape of ``meta/t_ns``)."""
    return int(json.loads((store / "meta" / "t_ns" / "zarr.json").read_text())["shape"][0])


def array_bytes(store: Path) -> dict[str, int]:
    """Return {array path: bytes of its files} of every array of the store at ``store``."""
    out: dict[str, int] = {}
    for meta in store.rglob("zarr.json"):
        doc = json.loads(meta.read_text())
        if doc.get("node_type") != "array":
            continue
        folder = meta.parent
        out[folder.relative_to(store).as_posix()] = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    return out


def total_bytes(store: Path) -> int:
    """Return the bytes of every file of the store at ``store``."""
    return sum(f.stat().st_size for f in store.rglob("*") if f.is_file())


def table(old: Path, new: Path) -> str:
    """Return the bytes-per-sample table of ``old`` against ``new`` (KB = 1000 bytes)."""
    so, sn = samples(old), samples(new)
    bo, bn = array_bytes(old), array_bytes(new)
    names = sorted(set(bo) | set(bn), key=lambda p: (-bo.get(p, 0) / max(so, 1), p))
    rows = [f"{'array':<34} {'old KB/sample':>14} {'new KB/sample':>14} {'new/old':>8}"]

    def kb(b: int | None, s: int) -> str:
        return "-" if b is None else f"{b / max(s, 1) / 1e3:.1f}"

    for p in names:
        o, n = bo.get(p), bn.get(p)
        if (o or 0) / max(so, 1) < 100 and (n or 0) / max(sn, 1) < 100:
            continue  # below 0.1 KB a sample in both: in the total only
        ratio = f"{(n / sn) / (o / so):.3f}" if o and n else "-"
        rows.append(f"{p:<34} {kb(o, so):>14} {kb(n, sn):>14} {ratio:>8}")
    to, tn = total_bytes(old), total_bytes(new)
    rows.append(f"{'TOTAL (every file)':<34} {kb(to, so):>14} {kb(tn, sn):>14} {(tn / sn) / (to / so):>8.3f}")
    rows.append(f"samples: old {so}, new {sn}; MB/sample: old {to / so / 1e6:.2f}, new {tn / sn / 1e6:.2f}")
    return "\n".join(rows)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit("usage: python bench/bytes.py OLD_DATASET NEW_DATASET")
    print(table(Path(sys.argv[1]), Path(sys.argv[2])))
