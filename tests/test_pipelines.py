"""pipelines/build_dataset: pool vs Dask, kill + resume, a corrupt drive among good ones."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from bagtools import split_mcap
from conftest import SMALL, run_cli, shared, small_config
from gtgen.synth import run_synth
from pipelines.build_dataset import build_dataset

ARRAYS = ("labels/micro/elevation_m", "labels/short/region", "labels/short/risk", "meta/t_ns", "meta/drive",
          "meta/T_crs_target", "inputs/jpeg", "inputs/voxel_points_m", "inputs/voxel_offsets", "rejected/reason")


@pytest.fixture(scope="session")
def drives(tmp_path_factory) -> Path:
    """Three small drives, read and never changed (one copy for both xdist workers)."""

    def build(root: Path) -> None:
        for name, seed in (("a", 0), ("b", 1), ("c", 2)):
            run_synth(small_config(synth={"duration_s": 3.0, "seed": seed, "formats": "mcap"}), root / name)
        # drive c arrives as two bags
        c = root / "c"
        split_mcap(c / "drive.mcap", c / "part_0.mcap", c / "part_1.mcap", 1.5)
        (c / "drive.mcap").unlink()

    return shared(tmp_path_factory, "pipelines/drives", build)


def _arrays(path: Path) -> dict[str, np.ndarray]:
    g = zarr.open_group(str(path / "dataset.zarr"), mode="r")
    return {k: g[k][:] for k in ARRAYS}


def _same(a: dict, b: dict) -> None:
    for k in ARRAYS:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.fixture(scope="module")
def pool_build(drives, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("pool")
    res = build_dataset([drives], None, out, small_config(), workers=2)
    assert sorted(r.name for r in res.drives) == ["a", "b", "c"] and all(r.ok for r in res.drives)
    assert res.n_samples > 0 and set(np.unique(_arrays(out)["meta/drive"])) == {0, 1, 2}
    g = zarr.open_group(str(out / "dataset.zarr"), mode="r")
    prov = g.attrs["provenance"]
    assert "numpy" in prov["dependencies"] and len(prov["units"]) == 3
    assert all(len(b["sha256"]) == 64 for d in g.attrs["drives"] for b in d["bags"])
    assert [len(d["bags"]) for d in g.attrs["drives"] if d["name"] == "c"] == [2]
    sizes = [sum(b.stat().st_size for b in (drives / d["name"]).glob("*.mcap")) for d in g.attrs["drives"]]
    assert sizes == sorted(sizes, reverse=True)  # largest bags first: the order the drives ran in
    return out


def test_pool_and_dask_give_identical_arrays(drives, pool_build, tmp_path):
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        res = build_dataset([drives], None, tmp_path, small_config(), scheduler=cluster.scheduler_address)
    assert all(r.ok for r in res.drives)
    _same(_arrays(pool_build), _arrays(tmp_path))


def test_one_drive_runs_its_stages_on_every_worker(drives, pool_build, tmp_path):
    """A build of fewer drives than workers gives the spare workers to each drive's stages."""
    res = build_dataset([drives / "c"], None, tmp_path, small_config(), workers=2)
    assert [(r.name, r.ok, r.workers) for r in res.drives] == [("c", True, 2)]
    _same(_arrays(pool_build / "drives" / "c"), _arrays(tmp_path))
    assert {r.workers for r in build_dataset([drives], None, pool_build, small_config(), workers=2).drives} == {1}


def test_rerun_skips_done_drives(drives, pool_build):
    res = build_dataset([drives], None, pool_build, small_config(), workers=2)
    assert all(r.skipped for r in res.drives)


def test_killed_run_resumed_gives_identical_arrays(drives, pool_build, tmp_path):
    args = ["build", str(drives), "-o", str(tmp_path), "--workers", "1", "-c", str(SMALL)]
    p = subprocess.Popen([sys.executable, "-m", "gtgen", *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline and not list((tmp_path / "drives").glob("*/done.json")):
        time.sleep(0.2)
    time.sleep(1.0)  # let it get into the next drive
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    assert list((tmp_path / "drives").glob("*/done.json")), "the build never finished a drive"
    assert not (tmp_path / "dataset.zarr").exists()
    p = run_cli(*args)
    assert p.returncode == 0, p.stderr
    assert "skipped" in p.stdout
    _same(_arrays(pool_build), _arrays(tmp_path))


def test_corrupt_bag_fails_its_drive_only(drives, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for n in ("a", "b"):
        (src / n).symlink_to(drives / n)
    bad = src / "z_bad"
    bad.mkdir()
    data = (drives / "a" / "drive.mcap").read_bytes()
    (bad / "drive.mcap").write_bytes(data[:300])  # cut inside its first chunk: nothing to recover
    shutil.copytree(drives / "a" / "dem", bad / "dem")
    p = run_cli("build", src, "-o", tmp_path / "o", "-c", SMALL)
    assert p.returncode == 2
    text = " ".join(p.stdout.replace("│", " ").split())
    assert "drive z_bad FAILED" in text and "truncated inside its header or first chunk" in text
    g = zarr.open_group(str(tmp_path / "o" / "dataset.zarr"), mode="r")
    assert sorted(d["name"] for d in g.attrs["drives"]) == ["a", "b"]


def test_merged_dataset_is_the_drives_end_to_end(pool_build):
    """Shards copied as bytes: every per-sample array of the dataset is the concatenation
    of the drives' own datasets (meta/drive aside), and the voxel offsets are shifted."""
    from gtgen.storage import schema as sc

    g = zarr.open_group(str(pool_build / "dataset.zarr"), mode="r")
    names = [d["name"] for d in g.attrs["drives"]]
    assert sorted(names) == ["a", "b", "c"]
    parts = [zarr.open_group(str(pool_build / "drives" / n / "dataset.zarr"), mode="r") for n in names]
    sizes = [p["meta/t_ns"].shape[0] for p in parts]
    assert g["meta/t_ns"].shape[0] == sum(sizes) and sizes[0] % sc.SAMPLES_PER_SHARD != 0  # the second drive starts mid-shard
    for s in sc.DATASET.arrays:
        if s.path.startswith(("rejected/", "inputs/voxel_")) or s.path == "meta/drive" or s.path.endswith(("/x_m", "/y_m")):
            continue
        if s in sc.SCAN_ARRAYS and s.path.split("/")[1] not in g["inputs"]:
            continue  # the N-scan input exists where the drives have raw scans
        want = np.concatenate([p[s.path][:] for p in parts])
        np.testing.assert_array_equal(g[s.path][:], want, err_msg=s.path)
    np.testing.assert_array_equal(g["meta/drive"][:], np.repeat([0, 1, 2], sizes))
    np.testing.assert_array_equal(g["inputs/voxel_points_m"][:], np.concatenate([p["inputs/voxel_points_m"][:] for p in parts]))
    off = np.concatenate([[0]] + [p["inputs/voxel_offsets"][1:] + sum(q["inputs/voxel_offsets"][-1] for q in parts[:i]) for i, p in enumerate(parts)])
    np.testing.assert_array_equal(g["inputs/voxel_offsets"][:], off)


def test_shard_bytes_roundtrip_through_zarr(tmp_path):
    """write_shard produces shards zarr reads, read_shard reads the ones zarr writes."""
    from gtgen.storage.codecs import compressors
    from gtgen.storage.shards import read_shard, write_shard

    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    a = root.create_array("x", shape=(8, 3, 2), dtype="float32", chunks=(1, 3, 2), shards=(4, 3, 2), fill_value=np.nan, compressors=compressors())
    data = np.arange(48, dtype=np.float32).reshape(8, 3, 2)
    a[:4] = data[:4]
    chunks = read_shard(tmp_path / "s.zarr" / "x" / "c" / "0" / "0" / "0", 4)
    assert all(c is not None for c in chunks)
    write_shard(tmp_path / "s.zarr" / "x" / "c" / "1" / "0" / "0", [chunks[3], None, chunks[0], None])
    b = zarr.open_group(str(tmp_path / "s.zarr"), mode="r")["x"]
    np.testing.assert_array_equal(b[4], data[3])
    np.testing.assert_array_equal(b[6], data[0])
    assert np.isnan(b[5]).all() and np.isnan(b[7]).all()
    with pytest.raises(ValueError, match="bad index"):
        read_shard(tmp_path / "s.zarr" / "x" / "c" / "0" / "0" / "0", 5)


def _dem_of_kind(kind: str, tile: Path, root: Path) -> tuple[Path, Path]:
    """Return (a DEM folder of ``kind`` built from ``tile``, the file whose change must
    make the build redo its drives: the tile itself, or a VRT's source)."""
    import zipfile

    import rasterio
    import rasterio.shutil

    dem = root / kind
    dem.mkdir()
    if kind == "tif":
        shutil.copy(tile, dem / tile.name)
        return dem, dem / tile.name
    if kind == "zip":
        with zipfile.ZipFile(dem / "tiles.zip", "w") as z:
            z.write(tile, tile.name)
        return dem, dem / "tiles.zip"
    if kind == "hgt":
        src = root / "plane.tif"
        T = rasterio.transform.from_origin(-121.0 - 0.5 / 1200, 36.0 + 0.5 / 1200, 1 / 1200, 1 / 1200)
        with rasterio.open(src, "w", driver="GTiff", width=1201, height=1201, count=1, dtype="int16", crs="EPSG:4326",
                           transform=T) as o:
            o.write(np.full((1201, 1201), 300, np.int16), 1)
        rasterio.shutil.copy(src, dem / "N35W121.hgt", driver="SRTMHGT")
        return dem, dem / "N35W121.hgt"
    sources = root / "vrt_sources"  # outside the DEM folder: only the VRT is a tile
    sources.mkdir()
    shutil.copy(tile, sources / tile.name)
    with rasterio.open(sources / tile.name) as ds:
        w, h, t, crs = ds.width, ds.height, ds.transform, ds.crs.to_wkt()
    (dem / "mosaic.vrt").write_text(
        f'<VRTDataset rasterXSize="{w}" rasterYSize="{h}"><SRS>{crs.replace("&", "&amp;").replace("<", "&lt;")}</SRS>'
        f"<GeoTransform>{t.c}, {t.a}, 0, {t.f}, 0, {t.e}</GeoTransform><VRTRasterBand dataType=\"Float32\" band=\"1\">"
        f'<SimpleSource><SourceFilename relativeToVRT="0">{sources / tile.name}</SourceFilename><SourceBand>1</SourceBand>'
        f"</SimpleSource></VRTRasterBand></VRTDataset>")
    return dem, sources / tile.name


@pytest.mark.parametrize("kind", ["tif", "hgt", "vrt", "zip"])
def test_a_changed_dem_of_each_kind_redoes_the_drive_and_an_unchanged_one_is_skipped(drives, kind, tmp_path):
    """The build's input hash covers every file the DEM tiles read (a VRT's sources too)."""
    from pipelines.build_dataset import DriveResult, _dems, _done_and_todo, _mark_done, unit_hash

    tile = sorted((drives / "a" / "dem").glob("*.tif"))[0]
    dem, changes = _dem_of_kind(kind, tile, tmp_path)
    cfg = small_config()
    bags = {"a": sorted((drives / "a").glob("*.mcap"))}
    work = tmp_path / "work"
    (work / "a" / "dataset.zarr").mkdir(parents=True)  # as a finished drive leaves it
    dems = _dems(bags, dem, cfg)
    _mark_done(work / "a", unit_hash(bags["a"], cfg, dems["a"][1]), DriveResult("a", ok=True))
    done, todo = _done_and_todo(bags, _dems(bags, dem, cfg), work, cfg, 1, None)
    assert list(done) == ["a"] and todo == []  # unchanged: skipped
    time.sleep(0.01)
    changes.write_bytes(changes.read_bytes())  # the same bytes, written again: a new mtime
    os.utime(changes, ns=(time.time_ns(), time.time_ns() + 10**9))
    done, todo = _done_and_todo(bags, _dems(bags, dem, cfg), work, cfg, 1, None)
    assert done == {} and [t[0] for t in todo] == ["a"]


def test_build_checks_the_dem_before_any_work_and_takes_a_single_raster(drives, tmp_path):
    out = tmp_path / "out"
    p = run_cli("build", drives / "a", "--dem", tmp_path / "nope", "-o", out, "-c", SMALL)
    assert p.returncode == 1 and "does not exist" in p.stderr and "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1
    assert not (out / "drives").exists()  # no drive ran
    tile = sorted((drives / "a" / "dem").glob("*.tif"))
    from gtgen.dem.index import TileIndex

    assert len(TileIndex.build(tile[0]).tiles) == 1  # --dem FILE: one raster is a DEM
    bad = tmp_path / "m.yaml"
    bad.write_text("drives: [not, a, mapping")
    p = run_cli("build", bad, "-o", out)
    assert p.returncode == 1 and "not valid YAML" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    bad.write_text("drives: [a, b]")
    p = run_cli("build", bad, "-o", out)
    assert p.returncode == 1 and "mapping of drive names" in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_report_of_a_multi_drive_dataset_judges_each_drive_by_its_own_truth(pool_build, tmp_path):
    """Three drives of three seeds: each drive's labels against its own truth, as each
    drive's own report would (one shared truth would read as a corrupted merge)."""
    from gtgen.report import build_report

    rep = build_report(pool_build / "dataset.zarr", tmp_path / "rep")
    assert sorted(rep.truth["drives_with_truth"]) == ["a", "b", "c"]
    for r in ("micro", "short"):
        assert rep.truth[r]["obs_pc"]["elevation_mae_m"] < 0.2, rep.truth[r]
    c = rep.truth["rejections"]["confusion"]
    assert c["kept"]["bad"] == 0 and c["kept"]["good"] > 0
    alone = build_report(pool_build / "drives" / "b" / "dataset.zarr", tmp_path / "rep_b")
    assert abs(alone.truth["short"]["obs_pc"]["elevation_mae_m"] - rep.truth["short"]["obs_pc"]["elevation_mae_m"]) < 0.1


def test_build_replaces_only_what_gtgen_wrote_and_a_failed_build_leaves_nothing(drives, tmp_path):
    def build(src: Path, out: Path, *more: str) -> subprocess.CompletedProcess:
        return run_cli("build", src, "-o", out, "-c", SMALL, "--workers", "1", *more)

    def one_line(p: subprocess.CompletedProcess) -> str:
        assert "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
        return p.stderr.strip()

    src = tmp_path / "src"
    src.mkdir()
    (src / "a").symlink_to(drives / "a")
    afile = tmp_path / "a_file"
    afile.write_text("mine")
    p = build(src, afile)
    assert p.returncode == 1 and f"output '{afile}' is a file" in one_line(p) and afile.read_text() == "mine"
    # a file of the user's where a drive's store goes: refused before any drive runs; --overwrite reaches the drive's stages
    out = tmp_path / "out"
    mine = out / "drives" / "a" / "drive.zarr"
    mine.parent.mkdir(parents=True)
    mine.write_text("mine")
    p = build(src, out)
    line = one_line(p)
    assert p.returncode == 1 and str(mine) in line and "--overwrite" in line and "every drive failed" not in line, line
    assert mine.read_text() == "mine" and sorted(x.name for x in out.rglob("*")) == ["a", "drive.zarr", "drives"]
    p = build(src, out, "--overwrite")
    assert p.returncode == 0, p.stderr
    assert mine.is_dir() and (out / "dataset.zarr").is_dir()
    # a build whose every drive fails leaves no folder behind
    bad = tmp_path / "bad" / "z"
    bad.mkdir(parents=True)
    (bad / "drive.mcap").write_bytes((drives / "a" / "drive.mcap").read_bytes()[:300])
    shutil.copytree(drives / "a" / "dem", bad / "dem")
    p = build(bad.parent, tmp_path / "o2")
    assert p.returncode == 1 and "every drive failed" in one_line(p)
    assert not (tmp_path / "o2").exists()


def test_a_drive_held_out_as_test_is_in_no_other_split_and_eval_reports_on_it(drives, pool_build, tmp_path):
    """``split: test`` in the manifest holds a whole drive out: none of its samples is in
    train or val, the others keep their geography split, the card counts samples per split
    and drive, training never sees it and ``gtgen eval --split test`` prints its tables."""
    import json

    import yaml

    from gtgen import codes
    from gtgen.report import build_report
    from test_train import SMALL_TRAIN

    out = tmp_path / "out"
    shutil.copytree(pool_build / "drives", out / "drives")  # the drives are done: only the merge runs
    manifest = drives / "manifest.yaml"
    manifest.write_text(yaml.safe_dump({"drives": {"a": ["a/drive.mcap"], "b": {"bags": ["b/drive.mcap"], "split": "test"},
                                                   "c": ["c/part_0.mcap", "c/part_1.mcap"]}}))
    res = build_dataset([manifest], None, out, small_config(), workers=1)
    assert res.split.get("test", 0) > 0
    g = zarr.open_group(str(out / "dataset.zarr"), mode="r")
    names = [d["name"] for d in g.attrs["drives"]]
    drive, split = g["meta/drive"][:], g["meta/split"][:]
    b = drive == names.index("b")
    assert b.any() and np.all(split[b] == codes.TEST) and not np.any(split[~b] == codes.TEST)
    np.testing.assert_array_equal(split[~b], zarr.open_group(str(pool_build / "dataset.zarr"), mode="r")["meta/split"][:][~b])
    card = build_report(out / "dataset.zarr", tmp_path / "rep").card
    assert card["split_by_drive"]["b"]["test"] == int(b.sum()) and card["split_by_drive"]["b"]["train"] == 0
    assert sum(card["split_by_drive"]["a"].values()) == int((drive == names.index("a")).sum())
    bad = drives / "bad.yaml"
    bad.write_text(yaml.safe_dump({"drives": {"a": {"bags": ["a/drive.mcap"], "split": "holdout"}}}))
    with pytest.raises(Exception, match=r"split 'holdout'.*expected one of \['train', 'val', 'test'\]"):
        build_dataset([bad], None, tmp_path / "bad", small_config(), workers=1)
    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump(SMALL_TRAIN))
    p = run_cli("train", out / "dataset.zarr", "--preset", "tiny", "--steps", "1", "--run", tmp_path / "run", "--config", c, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    p = run_cli("eval", out / "dataset.zarr", "--ckpt", tmp_path / "run" / "ckpt.pt", "--split", "test", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert f"on test ({int(b.sum())} samples" in p.stdout and "obs PC" in p.stdout and "X-Racer" in p.stdout
    assert json.loads((tmp_path / "run" / "eval.json").read_text())["samples"] == int(b.sum())
