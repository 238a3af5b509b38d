"""Build one dataset from many drives: extract -> fuse -> dem-align per drive, then merge.

``build_dataset()`` reads like its steps: find the drives, skip the ones already done
with the same inputs, run the rest on a local process pool or a dask.distributed
cluster, then merge every drive's shards into one dataset with a provenance manifest.

Each drive is one unit of work written under ``OUT/drives/<name>/``; a unit is done
when its ``done.json`` (written last, atomically) records the hash of its inputs (bag
sha256s, resolved config, gtgen version). A re-run skips done units and redoes changed
ones; a killed run leaves only partial stores (``runtime/output.py``), which the re-run
removes. Every stage is deterministic, so the result is the same however the work was
split. The dataset holds the drives largest bags first (ties by name), the order they run in.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from gtgen import __version__, codes
from gtgen.bag.reader import SUFFIXES, hash_bag
from gtgen.config import GtgenConfig, read_yaml
from gtgen.dataset.dem_align import run_dem_align
from gtgen.dataset.merge import merging
from gtgen.dem.index import TileIndex, default_dem_dir
from gtgen.errors import ConfigError, GtgenError, InputNotFoundError
from gtgen.extract import run_extract
from gtgen.fuse.run import run_fuse
from gtgen.runtime.output import check_replace, lock, write_json
from gtgen.runtime.pool import Pool
from gtgen.runtime.progress import track

log = logging.getLogger(__name__)

DONE = "done.json"
UNIT_OUTPUTS = (DONE, "drive.zarr", "fused.zarr", "dataset.zarr")  # what a drive unit writes in drives/<name>/


@dataclass
class DriveResult:
    """What one drive unit produced (or why it failed)."""

    name: str
    ok: bool
    skipped: bool = False
    error: str = ""
    samples: int = 0
    kept: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    bag_sha256: list[str] = field(default_factory=list)
    workers: int = 1  # processes its stages ran on


@dataclass
class BuildResult:
    out: Path
    drives: list[DriveResult]
    n_samples: int
    split: dict[str, int]
    seconds: float


def find_drives(sources: list[Path], splits: dict[str, str] | None = None) -> dict[str, list[Path]]:
    """Return {drive name: bag paths} from a manifest YAML, drive folders, or bag files;
    ``splits``, if given, receives {drive name: split} of the manifest's drives that name one.

    A manifest maps names to bag lists (``drives: {name: [bag, ...]}``) or to entries
    ``{bags: [bag, ...], split: test}`` (a drive held out whole; ``split`` may be
    ``train``, ``val`` or ``test``; without one, a drive's samples are split by
    geography). A folder that holds bags (or is a rosbag2 recording) is one drive; a
    folder of such folders is one drive per subfolder; a bag file alone is a drive named
    after it.
    """
    drives: dict[str, list[Path]] = {}

    def add(name: str, bags: list[Path]) -> None:
        if name in drives:
            raise ConfigError(f"drive name {name!r} appears twice; rename one of its folders or manifest entries")
        drives[name] = sorted(bags)

    for src in sources:
        if not src.exists():
            raise InputNotFoundError(f"source '{src}' does not exist")
        if src.is_file() and src.suffix in (".yaml", ".yml"):
            for name, (bags, split) in _manifest(src).items():
                add(name, bags)
                if split is not None and splits is not None:
                    splits[name] = split
        elif src.is_file():
            add(src.stem, [src.resolve()])
        elif (src / "metadata.yaml").is_file():
            add(src.name, [src.resolve()])
        else:
            bags = [p.resolve() for p in sorted(src.iterdir()) if p.suffix in SUFFIXES or (p / "metadata.yaml").is_file()]
            if bags:
                add(src.name, bags)
            else:
                for sub in sorted(p for p in src.iterdir() if p.is_dir()):
                    inner = [p.resolve() for p in sorted(sub.iterdir()) if p.suffix in SUFFIXES or (p / "metadata.yaml").is_file()]
                    if inner:
                        add(sub.name, inner)
    if not drives:
        raise InputNotFoundError(f"no bags found in {[str(s) for s in sources]}")
    return drives


def _manifest(src: Path) -> dict[str, tuple[list[Path], str | None]]:
    """Return {drive name: (bags, split or None)} of a manifest file, or raise ConfigError
    saying what is wrong."""
    entries = read_yaml(src, "manifest").get("drives")
    shape = ("'drives: {name: [bag, ...]}' or 'drives: {name: {bags: [bag, ...], split: test}}' "
             "(a mapping of drive names to lists of bags)")
    if not isinstance(entries, dict) or not entries:
        raise ConfigError(f"manifest '{src}' must hold {shape}")
    out = {}
    for name, entry in entries.items():
        split = None
        if isinstance(entry, dict):
            extra = sorted(set(entry) - {"bags", "split"})
            if extra:
                raise ConfigError(f"manifest '{src}': drive {name!r} has keys {extra}; expected 'bags' and optionally 'split'")
            split, entry = entry.get("split"), entry.get("bags")
            if split is not None and split not in codes.SPLITS.values():
                raise ConfigError(f"manifest '{src}': drive {name!r} has split {split!r}; expected one of {list(codes.SPLITS.values())}")
        if not isinstance(entry, list) or not entry:
            raise ConfigError(f"manifest '{src}': drive {name!r} must list its bags; the manifest must hold {shape}")
        bags = entry
        paths = [(src.parent / str(b)).resolve() for b in bags]
        missing = [str(p) for p in paths if not p.exists()]
        if missing:
            raise InputNotFoundError(f"manifest '{src}': drive {name!r} names bags that do not exist: {missing}")
        out[str(name)] = (paths, split)
    return out


def unit_hash(bags: list[Path], cfg: GtgenConfig, dem_fingerprint: str, bag_sha256: list[str] | None = None) -> str:
    """Return the hash of one drive unit's inputs: the bags' own hashes (``bag_sha256``,
    computed here if not given), the resolved config, every file the DEM tiles read
    (``TileIndex.fingerprint``) and gtgen's version."""
    h = hashlib.sha256()
    for bh in bag_sha256 or [hash_bag(b) for b in bags]:
        h.update(bh.encode())
    h.update(json.dumps(cfg.model_dump(mode="json"), sort_keys=True).encode())
    h.update(dem_fingerprint.encode())
    h.update(__version__.encode())
    return h.hexdigest()


def process_drive(name: str, bags: list[str], dem_dir: str, work: str, cfg: GtgenConfig,
                  bag_sha256: list[str] | None = None, workers: int = 1, overwrite: bool = False) -> DriveResult:
    """Run extract, fuse and dem-align for one drive (a picklable task for any executor),
    each stage on ``workers`` processes; the bags are hashed while extract reads them
    unless ``bag_sha256`` gives the hashes. A drive that fails leaves no folder it made."""
    folder = Path(work) / name
    made = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    (folder / DONE).unlink(missing_ok=True)
    res = DriveResult(name, ok=False, workers=workers)
    try:
        t = time.perf_counter()
        ex = run_extract([Path(b) for b in bags], folder / "drive.zarr", cfg, workers=workers, bag_sha256=bag_sha256, overwrite=overwrite)
        res.seconds["extract"] = time.perf_counter() - t
        t = time.perf_counter()
        run_fuse(folder / "drive.zarr", folder / "fused.zarr", cfg, workers=workers, overwrite=overwrite)
        res.seconds["fuse"] = time.perf_counter() - t
        t = time.perf_counter()
        al = run_dem_align(folder / "drive.zarr", folder / "fused.zarr", Path(dem_dir) if dem_dir else None, folder / "dataset.zarr", cfg, workers=workers,
                           overwrite=overwrite)
        res.seconds["dem-align"] = time.perf_counter() - t
    except GtgenError as err:
        res.error = f"{type(err).__name__}: {err}"
        if made and not any(folder.iterdir()):
            folder.rmdir()
        return res
    res.ok, res.samples, res.kept, res.bag_sha256 = True, ex.n_samples, al.n_kept, ex.bag_sha256
    res.rejected = {**ex.rejected, **al.rejected}
    return res


def _mark_done(folder: Path, digest: str, res: DriveResult) -> None:
    write_json(folder / DONE, {"hash": digest, "result": asdict(res)})


def _already_done(folder: Path, digest: str) -> DriveResult | None:
    try:
        data = json.loads((folder / DONE).read_text())
    except (OSError, ValueError):
        return None
    if data.get("hash") != digest or not (folder / "dataset.zarr").is_dir():
        return None
    r = DriveResult(**data["result"])
    r.skipped = True
    return r


def build_dataset(sources: list[Path], dem_dir: Path | None, out: Path, cfg: GtgenConfig,
                  workers: int = 2, scheduler: str | None = None, overwrite: bool = False) -> BuildResult:
    """Build ``out/dataset.zarr`` from every drive in ``sources``; see the module docstring."""
    t0 = time.perf_counter()
    splits: dict[str, str] = {}
    drives = find_drives(sources, splits)
    if out.exists() and not out.is_dir():
        raise GtgenError(f"output '{out}' is a file; gtgen build writes dataset.zarr and drives/ into a folder")
    work = out / "drives"
    for path in (out / "dataset.zarr", *(work / name / f for name in drives for f in UNIT_OUTPUTS)):
        check_replace(path, overwrite)  # before any work: nothing of the user's is replaced
    dems = _dems(drives, dem_dir, cfg)  # every drive's DEM checked before any work
    made = [p for p in (work, *work.parents) if not p.exists()]
    with lock(out / "build"), _remove_if_failed(made):
        work.mkdir(parents=True, exist_ok=True)
        results, todo = _done_and_todo(drives, dems, work, cfg, workers, scheduler, overwrite)
        # drives run largest bags first, so that no worker is left with a long drive at the
        # end, and the dataset holds them in that same order: each is merged as soon as it and
        # all before it are done, so merging overlaps with the drives still running
        order = sorted(drives, key=lambda n: (-sum(_size(b) for b in drives[n]), n))
        rank = {n: i for i, n in enumerate(order)}
        todo.sort(key=lambda t: rank[t[0]])
        with merging(out / "dataset.zarr", cfg, overwrite) as merger:
            merged = 0

            def merge_ready() -> None:
                nonlocal merged
                while merged < len(order) and order[merged] in results:
                    res = results[order[merged]]
                    if res.ok:
                        merger.add(res.name, work / res.name / "dataset.zarr", splits.get(res.name))
                    merged += 1

            merge_ready()
            for res in _execute(todo, workers, scheduler):
                if res.ok:
                    _mark_done(work / res.name, unit_hash(drives[res.name], cfg, dems[res.name][1], res.bag_sha256), res)
                results[res.name] = res
                merge_ready()
            ordered = [results[n] for n in order]
            if not any(r.ok for r in ordered):
                raise GtgenError("every drive failed: " + "; ".join(f"{r.name}: {r.error}" for r in ordered))
            n, split = merger.finish(_provenance(ordered))
    return BuildResult(out, ordered, n, split, time.perf_counter() - t0)


@contextlib.contextmanager
def _remove_if_failed(made: list[Path]) -> Iterator[None]:
    """Remove the folders ``made`` (deepest first) where still empty if the block fails."""
    try:
        yield
    except BaseException:
        for p in made:
            with contextlib.suppress(OSError):
                p.rmdir()
        raise


def _dems(drives: dict[str, list[Path]], dem_dir: Path | None, cfg: GtgenConfig) -> dict[str, tuple[Path, str]]:
    """Return each drive's DEM (``--dem``, else dem.dir, else dem/ beside its bags) and the
    fingerprint of every file its tiles read; a DEM that does not exist or holds no tile is
    an error before any drive runs. Without a DEM (``dem.enabled`` false): none, ''."""
    out, seen = {}, {}
    if not cfg.dem.enabled:
        if dem_dir is not None:
            raise ConfigError(f"--dem {dem_dir} given with --no-dem (dem.enabled: false); expected one of them")
        return {name: (Path(""), "") for name in drives}
    for name, bags in drives.items():
        src = dem_dir or default_dem_dir(cfg.dem.dir, bags)
        if src not in seen:
            seen[src] = TileIndex.build(src).fingerprint()
        out[name] = (src, seen[src])
    return out


def _done_and_todo(drives: dict[str, list[Path]], dems: dict[str, tuple[Path, str]], work: Path, cfg: GtgenConfig, workers: int,
                   scheduler: str | None, overwrite: bool = False) -> tuple[dict[str, DriveResult], list[tuple]]:
    """Return the units already done with the same inputs, and the tasks of the others.
    With fewer drives than workers (one long drive, say) each drive's stages run on the
    spare workers themselves, so no core idles; a Dask task stays one process."""
    done, todo = {}, []
    for name, bags in drives.items():
        hashes = None
        if (work / name / DONE).is_file():  # hash now only to compare; otherwise extract hashes as it reads
            hashes = [hash_bag(b) for b in bags]
            res = _already_done(work / name, unit_hash(bags, cfg, dems[name][1], hashes))
            if res is not None:
                done[name] = res
                continue
        todo.append((name, [str(b) for b in bags], str(dems[name][0]) if cfg.dem.enabled else "", str(work), cfg, hashes))
    inner = 1 if scheduler else max(1, workers // max(len(todo), 1))
    return done, [(*t, inner, overwrite) for t in todo]


def _execute(todo: list[tuple], workers: int, scheduler: str | None):
    """Yield the DriveResult of each unit, as they finish."""
    if not todo:
        return
    if scheduler:
        from dask.distributed import Client, as_completed

        with Client(scheduler) as client:
            futs = [client.submit(process_drive, *t, pure=False) for t in todo]
            for fut in track(as_completed(futs), "build: drives", total=len(futs)):
                yield fut.result()
        return
    with Pool(min(workers, len(todo))) as pool:
        yield from pool.as_completed(process_drive, todo, "build: drives")


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size


def _provenance(results: list[DriveResult]) -> dict:
    import importlib.metadata as md

    versions = {}
    for p in ("numpy", "zarr", "rosbags", "rasterio", "pyproj", "open3d-cpu", "open3d", "torch"):
        try:
            versions[p] = md.version(p)
        except md.PackageNotFoundError:
            pass
    return {"dependencies": versions, "units": [asdict(r) for r in results]}


def summary_rows(res: BuildResult) -> list[tuple[str, Any]]:
    """Return the rows of the final table."""
    rows: list[tuple[str, Any]] = [("dataset", res.out / "dataset.zarr"), ("samples", res.n_samples)]
    rows += [(f"  split {k}", v) for k, v in res.split.items()]
    for r in res.drives:
        if r.ok:
            st = ", ".join(f"{k} {v:.1f} s" for k, v in r.seconds.items()) if not r.skipped else "done earlier (skipped)"
            rej = ", ".join(f"{k} {v}" for k, v in r.rejected.items()) or "none"
            rows.append((f"drive {r.name}", f"kept {r.kept} of {r.samples}; rejected: {rej}; {st}"))
        else:
            rows.append((f"drive {r.name}", f"FAILED: {r.error}"))
    rows.append(("time", f"{res.seconds:.1f} s"))
    return rows
