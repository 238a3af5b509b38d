"""Trust at the edges: a damaged store is never read as data, a user's file is never
replaced, locks and failed commands leave nothing in the user's folders.

Each adverse case asserts the exit code (or the error class), a one-line message naming
what is wrong, and that nothing of the user's changed."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import SMALL, run_cli
from gtgen.errors import GtgenError, OutputExistsError, StoreError
from gtgen.runtime.output import atomic_output, lock_path, owned, write_json
from gtgen.storage.dataset import DatasetStore
from gtgen.storage.drive import DriveStore
from gtgen.storage.integrity import DamagedStoreError, write_manifest
from gtgen.storage.stores import verify_store


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _one_line(p: subprocess.CompletedProcess) -> str:
    assert "Traceback" not in p.stderr + p.stdout, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1, p.stderr
    return lines[0]


def _shard(store: Path, array: str, k: int = 1) -> Path:
    """Return shard file ``k`` (samples 16k to 16k + 15) of a per-sample array."""
    ndim = len(json.loads((store / array / "zarr.json").read_text())["shape"])
    return store.joinpath(*array.split("/"), "c", str(k), *["0"] * (ndim - 1))


def _all_shards(store: Path, array: str) -> None:
    for f in (store / array / "c").rglob("*"):
        if f.is_file():
            f.unlink()


# -- damaged datasets ------------------------------------------------------------------------

DAMAGES = {
    "labels shard deleted": lambda ds: _shard(ds, "labels/micro/elevation_m").unlink(),
    "bytes overwritten inside a shard": lambda ds: _overwrite(_shard(ds, "labels/short/elevation_m"), 40),
    "shard truncated": lambda ds: _truncate(_shard(ds, "labels/micro/region")),
    "meta/t_ns shard deleted": lambda ds: _shard(ds, "meta/t_ns").unlink(),
    "image shards deleted": lambda ds: _all_shards(ds, "inputs/jpeg"),
    "array metadata corrupt": lambda ds: (ds / "labels" / "micro" / "risk" / "zarr.json").write_text("{not json"),
    "root metadata deleted": lambda ds: (ds / "zarr.json").unlink(),
}


def _overwrite(f: Path, at: int) -> None:
    data = bytearray(f.read_bytes())
    data[at : at + 8] = b"\x00\xff" * 4
    f.write_bytes(bytes(data))


def _truncate(f: Path) -> None:
    f.write_bytes(f.read_bytes()[:-100])


@pytest.fixture(scope="module")
def damaged(dataset, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("damaged")
    out = {}
    for i, (name, damage) in enumerate(DAMAGES.items()):
        ds = _copy(dataset, root / f"d{i}" / "dataset.zarr")
        damage(ds)
        out[name] = ds
    return out


@pytest.mark.parametrize("name", list(DAMAGES))
def test_a_damaged_dataset_is_an_error_for_every_reader(damaged, name, cfg, tmp_path):
    """The Python API's reads, verify, report, viz and export each stop with one line
    naming the store as damaged and the command that rebuilds it; nothing reads fill as data."""
    ds_path = damaged[name]
    with pytest.raises(GtgenError, match="damaged.*gtgen dem-align") as err:
        ds = DatasetStore(ds_path)
        for kind, rng, layer in (("labels", "micro", "elevation_m"), ("labels", "short", "elevation_m"),
                                 ("labels", "micro", "region"), ("labels", "micro", "risk")):
            for k in range(ds.n_samples):
                ds.grid(kind, rng, layer)[k]
        ds.meta("t_ns")
        for k in range(ds.n_samples):
            ds.inputs("jpeg")[k]
    assert "\n" not in str(err.value)
    problems = verify_store(ds_path)[1].problems
    assert problems, name
    readers = {"verify": ["verify", ds_path], "report": ["report", ds_path, "-o", tmp_path / "rep"],
               "viz": ["viz", ds_path, "--sample", "16", "-o", tmp_path / "s.png"],
               "geotiff": ["export", "geotiff", ds_path, "-o", tmp_path / "tifs"], "mcap": ["export", "mcap", ds_path, "-o", tmp_path / "x.mcap"]}
    # every command that reads the damaged array (report and the GeoTIFFs read no image)
    names = ["verify", "viz", "mcap"] if name == "image shards deleted" else ["verify", "report", "viz", "geotiff"]
    for cmd in (readers[n] for n in names):
        p = run_cli(*cmd)
        assert p.returncode == 1, (cmd, p.stdout, p.stderr)
        line = _one_line(p)
        assert "damaged" in line and "gtgen dem-align" in line, (cmd, line)
    assert not any((tmp_path / n).exists() for n in ("tifs", "s.png", "x.mcap"))


def test_the_error_names_the_array_and_its_samples(damaged):
    ds = DatasetStore(damaged["labels shard deleted"])
    with pytest.raises(DamagedStoreError) as err:
        ds.grid("labels", "micro", "elevation_m")[20]
    msg = str(err.value)
    assert "array 'labels/micro/elevation_m' samples 16-31" in msg and "is missing" in msg and "gtgen verify" in msg
    ds = DatasetStore(damaged["bytes overwritten inside a shard"])
    with pytest.raises(DamagedStoreError, match="labels/short/elevation_m"):
        for k in range(16, 32):
            ds.grid("labels", "short", "elevation_m")[k]


@pytest.mark.parametrize("name, array", [("bytes overwritten inside a shard", "labels/short/elevation_m"),
                                         ("labels shard deleted", "labels/micro/elevation_m")])
def test_the_python_apis_xarray_and_zarr_views_are_checked_too(damaged, name, array):
    """Reads through users' own views (xarray, the zarr group) meet the same one-line error
    as gtgen's readers: a chunk that does not decode as well as one that is missing."""
    import gtgen

    ds = gtgen.open_dataset(damaged[name])
    group, _, layer = array.rpartition("/")
    for read in (lambda: ds.xarray(group)[layer].values, lambda: ds.zarr[array][:]):
        with pytest.raises(gtgen.GtgenError) as err:
            read()
        msg = str(err.value)
        assert f"array '{array}' samples 16-31" in msg and "gtgen dem-align" in msg and "\n" not in msg, msg


def test_training_on_a_damaged_dataset_stops(damaged, tmp_path):
    p = run_cli("train", damaged["image shards deleted"], "--run", tmp_path / "run", "--steps", "2", "-c", SMALL)
    assert p.returncode == 1
    assert "damaged" in _one_line(p)


# -- chunks bound to their place: swapped, copied or stale chunks ----------------------------

def _swap(a: Path, b: Path) -> None:
    assert a.stat().st_size == b.stat().st_size  # what the size check alone let through
    data = a.read_bytes()
    a.write_bytes(b.read_bytes())
    b.write_bytes(data)


def _other_shard_same_size(ds: Path, array: str) -> None:
    """Put shard 2's bytes in shard 1's place, padded to shard 1's size (a whole, valid
    shard: its inner chunks and its index, at the end, decode)."""
    a, b = _shard(ds, array, 1), _shard(ds, array, 2)
    data, index = b.read_bytes(), 16 * 16 + 4
    a.write_bytes(data[:-index] + bytes(a.stat().st_size - len(data)) + data[-index:])


PLACES = {  # damage, array, the samples it may name (either of a swapped pair), reads that must stop
    "meta/t_ns shards swapped": (lambda ds: _swap(_shard(ds, "meta/t_ns", 0), _shard(ds, "meta/t_ns", 1)), "meta/t_ns", ("0-15", "16-31"),
                                 (lambda ds: ds.meta("t_ns"), lambda ds: ds.meta("t_ns", [3, 4]), lambda ds: ds.rows("meta/t_ns")[3])),
    "jpeg_nbytes shards swapped": (lambda ds: _swap(_shard(ds, "inputs/jpeg_nbytes", 0), _shard(ds, "inputs/jpeg_nbytes", 1)),
                                   "inputs/jpeg_nbytes", ("0-15", "16-31"), (lambda ds: ds.jpeg_files(3), lambda ds: ds.jpeg_bytes())),
    "a labels shard holding another's": (lambda ds: _other_shard_same_size(ds, "labels/micro/elevation_m"), "labels/micro/elevation_m",
                                         ("16-31",), (lambda ds: ds.grid("labels", "micro", "elevation_m")[20],
                                                   lambda ds: ds.group["labels/micro/elevation_m"][20])),
}


@pytest.mark.parametrize("name", list(PLACES))
def test_a_chunk_out_of_its_place_is_an_error_naming_its_array(name, dataset, tmp_path):
    """Chunks of the same size swapped, or a shard holding another's bytes (the size check
    alone let both through, and they read as data): every reader stops with one line naming
    the array, its samples and the command that rebuilds the store; verify names it."""
    damage, array, samples, reads = PLACES[name]
    ds_path = _copy(dataset, tmp_path / "dataset.zarr")
    damage(ds_path)
    for read in reads:
        with pytest.raises(DamagedStoreError) as err:
            read(DatasetStore(ds_path))
        msg = str(err.value)
        assert any(f"array '{array}' samples {a}" in msg for a in samples) and "other" in msg and "gtgen dem-align" in msg and "\n" not in msg, msg
    v = verify_store(ds_path)[1]
    assert any(f"array '{array}'" in p for p in v.problems), v.problems


def test_viz_of_swapped_image_lengths_names_the_damage(dataset, tmp_path):
    ds_path = _copy(dataset, tmp_path / "dataset.zarr")
    PLACES["jpeg_nbytes shards swapped"][0](ds_path)
    p = run_cli("viz", ds_path, "-n", "3", "-o", tmp_path / "s.png")
    line = _one_line(p)
    assert p.returncode == 1 and "inputs/jpeg_nbytes" in line and "gtgen dem-align" in line, line
    assert not (tmp_path / "s.png").exists()


def test_a_users_note_in_a_store_is_named_not_called_damage(dataset, tmp_path):
    """A file zarr never reads (a note beside the arrays) is named as extra, removing it is
    enough; the store is not called damaged, nor a rebuild advised."""
    ds_path = _copy(dataset, tmp_path / "dataset.zarr")
    (ds_path / "NOTES.txt").write_text("mine")
    v = verify_store(ds_path)[1]
    assert v.problems == [] and v.extra == ["NOTES.txt"]
    p = run_cli("verify", ds_path)
    line = _one_line(p)
    assert p.returncode == 1 and "1 file gtgen did not write: 'NOTES.txt'" in line and "removing it is enough" in line, line
    assert "damaged" not in line and "rebuild" not in line.replace("nothing to rebuild", "")
    DatasetStore(ds_path).meta("t_ns")  # readers are not concerned


def test_no_output_goes_inside_a_store(dataset, tmp_path):
    """Every command's output inside a gtgen store (directly, or through a symlink) is
    refused in one line before any work; the store stays whole."""
    ds_path = _copy(dataset, tmp_path / "ws" / "dataset.zarr")
    (tmp_path / "link").symlink_to(ds_path)
    for cmd in (["report", ds_path, "-o", ds_path], ["viz", ds_path, "-o", tmp_path / "link" / "s.png"],
                ["export", "geotiff", ds_path, "-o", ds_path / "tifs"], ["experiments", ds_path, "-o", ds_path / "exp", "--steps", "1"],
                ["train", ds_path, "--run-dir", ds_path / "run", "--steps", "1"]):
        p = run_cli(*cmd, cwd=tmp_path)
        line = _one_line(p)
        assert p.returncode == 1 and "is inside the dataset store" in line and p.stdout == "", (cmd, line)
    v = verify_store(ds_path)[1]
    assert v.problems == [] and v.extra == []


def test_a_whole_store_verifies_and_reads_as_before(dataset):
    fmt, v = verify_store(dataset)
    assert fmt.kind == "gtgen-dataset" and v.checked > 10 and v.problems == [] and v.extra == []
    p = run_cli("verify", dataset)
    assert p.returncode == 0 and "whole" in p.stdout


def test_a_chunk_of_fill_is_not_stored_and_reads_as_fill(tmp_path):
    """Chunks all of fill are not stored, by design: the manifest tells them from lost ones."""
    from gtgen.storage.fused import LABEL_LAYERS, XRACER_LAYERS, FusedStore, FusedWriter

    w = FusedWriter(tmp_path / "f.zarr")
    w.create_grids(2, {"micro": 4, "short": 4})
    ones = {n: np.ones((4, 4)) for n in LABEL_LAYERS}
    nan = {n: np.full((4, 4), np.nan) for n in LABEL_LAYERS} | {"count": np.zeros((4, 4)), "region": np.zeros((4, 4))}
    for r in ("micro", "short"):
        w.write_sample(r, 0, ones, {n: np.ones((4, 4)) for n in XRACER_LAYERS})
        w.write_sample(r, 1, nan, {n: np.full((4, 4), np.nan) for n in XRACER_LAYERS})
    w.finish(np.zeros(2, np.uint8))
    grid = tmp_path / "f.zarr" / "fused" / "micro" / "elevation_m"
    assert (grid / "c.0.0.0").is_file() and not (grid / "c.1.0.0").exists()
    f = FusedStore(tmp_path / "f.zarr")
    assert np.isnan(f.grid("micro", "elevation_m")[1]).all() and (f.grid("micro", "elevation_m")[0] == 1).all()
    (grid / "c.0.0.0").unlink()
    with pytest.raises(DamagedStoreError, match="fused/micro/elevation_m' sample 0.*is missing"):
        FusedStore(tmp_path / "f.zarr").grid("micro", "elevation_m")[0]


def test_a_store_without_its_manifest_or_with_a_stray_file(dataset, tmp_path):
    ds = _copy(dataset, tmp_path / "a.zarr")
    (ds / "labels" / "micro" / "elevation_m" / "c" / "9").write_bytes(b"stray")
    v = verify_store(ds)[1]
    assert v.problems == [] and v.strays == ["labels/micro/elevation_m/c/9"], v
    p = run_cli("verify", ds)  # named as a chunk: zarr would read it; removing it is enough, not a rebuild
    line = _one_line(p)
    assert p.returncode == 1 and "named as a chunk" in line and "removing it is enough" in line and "rebuild" not in line, line
    (ds / "labels" / "micro" / "elevation_m" / "c" / "9").unlink()
    assert verify_store(ds)[1].problems == [] and verify_store(ds)[1].strays == []
    shutil.rmtree(ds / "gtgen_manifest")
    with pytest.raises(DamagedStoreError, match="record of what was written"):
        DatasetStore(ds)
    p = run_cli("verify", ds)
    line = _one_line(p)
    assert p.returncode == 1 and "record of what was written" in line and line.count("is damaged") == 1, line


def test_damaged_drive_and_fused_stores_stop_the_next_stage(drive_store, fused_store, tmp_path):
    drive = _copy(drive_store, tmp_path / "ws" / "drive.zarr")
    victim = next(p for p in (drive / "maps" / "micro" / "elevation_m").iterdir() if p.name.startswith("c."))
    victim.unlink()
    p = run_cli("fuse", drive, "-c", SMALL, "--workers", "1")
    line = _one_line(p)
    assert p.returncode == 1 and "maps/micro/elevation_m" in line and "gtgen extract" in line, line
    assert not (tmp_path / "ws" / "fused.zarr").exists()
    fused = _copy(fused_store, tmp_path / "ws2" / "fused.zarr")
    os.symlink(drive_store, tmp_path / "ws2" / "drive.zarr")
    victim = next(p for p in (fused / "fused" / "short" / "region").iterdir() if p.name.startswith("c."))
    victim.unlink()
    p = run_cli("dem-align", tmp_path / "ws2" / "drive.zarr", "-c", SMALL)
    line = _one_line(p)
    assert p.returncode == 1 and "fused/short/region" in line and "gtgen fuse" in line, line


# -- outputs over the user's files -----------------------------------------------------------

def test_outputs_never_replace_what_gtgen_did_not_write(drive_dir, drive_store, dataset, tmp_path):
    mine = tmp_path / "mydata"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    p = run_cli("extract", drive_dir / "drive.mcap", "-o", mine, "-c", SMALL)
    assert p.returncode == 1 and "--overwrite" in _one_line(p) and str(mine) in p.stderr
    assert (mine / "notes.txt").read_text() == "mine"
    afile = tmp_path / "a_file"
    afile.write_text("mine")
    p = run_cli("fuse", drive_store, "-o", afile, "-c", SMALL)
    assert p.returncode == 1 and afile.read_text() == "mine"
    p = run_cli("viz", dataset, "-o", afile)
    assert p.returncode == 1 and "--overwrite" in _one_line(p) and afile.read_text() == "mine"
    p = run_cli("export", "mcap", dataset, "-o", tmp_path / "mine.mcap")
    assert p.returncode == 0
    assert owned(tmp_path / "mine.mcap")


def test_an_output_over_an_input_or_a_gtgen_output_of_another_kind_is_refused(drive_store, fused_store, dataset, tmp_path):
    """The second campaign's LOST class: the output named is the command's own input, or a
    gtgen file or store of another kind (a checkpoint, a figure, a store of another stage):
    one line, nothing replaced; --overwrite still replaces it."""
    import hashlib
    import shutil

    def digest(path: Path) -> str:
        files = sorted(f for f in path.rglob("*") if f.is_file()) if path.is_dir() else [path]
        return hashlib.sha256(b"".join(f.read_bytes() for f in files)).hexdigest()

    drive = tmp_path / "drive.zarr"
    shutil.copytree(drive_store, drive)
    before = digest(drive)
    p = run_cli("fuse", drive, "-o", drive, "-c", SMALL, cwd=tmp_path)
    assert p.returncode == 1 and "is an input of this command" in _one_line(p) and digest(drive) == before
    fused = tmp_path / "fused.zarr"
    shutil.copytree(fused_store, fused)
    before = digest(fused)
    p = run_cli("viz", dataset, "-n", "1", "-o", tmp_path / "fig.png", cwd=tmp_path)
    assert p.returncode == 0
    png = (tmp_path / "fig.png").read_bytes()
    # a figure over a store, a store over a figure, and a store of another stage over a store
    p = run_cli("viz", dataset, "-n", "1", "-o", fused, cwd=tmp_path)
    assert p.returncode == 1 and digest(fused) == before
    p = run_cli("export", "mcap", dataset, "-o", tmp_path / "x.mcap", cwd=tmp_path)
    assert p.returncode == 0
    mcap = (tmp_path / "x.mcap").read_bytes()
    p = run_cli("viz", dataset, "-n", "1", "-o", tmp_path / "x.mcap", cwd=tmp_path)
    assert p.returncode == 1 and "holds a gtgen MCAP file" in _one_line(p) and (tmp_path / "x.mcap").read_bytes() == mcap
    shutil.copytree(dataset, tmp_path / "ds.zarr")
    before = digest(tmp_path / "ds.zarr")
    p = run_cli("fuse", drive_store, "-o", tmp_path / "ds.zarr", "-c", SMALL, cwd=tmp_path)
    assert p.returncode == 1 and "holds a gtgen dataset store" in _one_line(p) and digest(tmp_path / "ds.zarr") == before
    p = run_cli("viz", dataset, "-n", "1", "-o", tmp_path / "x.mcap", "--overwrite", cwd=tmp_path)
    assert p.returncode == 0 and (tmp_path / "x.mcap").read_bytes()[:4] == b"\x89PNG"
    assert png[:4] == b"\x89PNG"


def test_an_output_holding_an_input_is_refused_even_with_overwrite(drive_dir, drive_store, fused_store, cfg, tmp_path):
    """The third campaign's LOST class: '-o' a folder that holds the command's input (the
    bag, the drive or fused store, the DEM folder) with --overwrite replaced the folder and
    deleted the input. Refused before any work, the inputs as they were."""
    from gtgen.dataset.dem_align import run_dem_align
    from gtgen.extract import run_extract

    bags = tmp_path / "bags"
    bags.mkdir()
    bag = bags / "drive.mcap"
    os.link(drive_dir / "drive.mcap", bag)
    with pytest.raises(OutputExistsError, match="holds .*drive.mcap', an input of this command"):
        run_extract([bag], bags, cfg, overwrite=True)
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "drive.zarr").symlink_to(drive_store)  # through a symlink too
    with pytest.raises(OutputExistsError, match="an input of this command"):
        run_dem_align(ws / "drive.zarr", fused_store, None, ws, cfg, overwrite=True)
    dem = tmp_path / "dem"
    shutil.copytree(drive_dir / "dem", dem)
    tiles = sorted(dem.iterdir())
    with pytest.raises(OutputExistsError, match="is an input of this command"):
        run_dem_align(drive_store, fused_store, dem, dem, cfg, overwrite=True)
    mine = tmp_path / "mine"  # the DEM folder the config names (no --dem): an input all the same
    shutil.copytree(dem, mine / "dem")
    configured = cfg.model_copy(update={"dem": cfg.dem.model_copy(update={"dir": str(mine / "dem")})})
    with pytest.raises(OutputExistsError, match="holds .*dem', an input of this command"):
        run_dem_align(drive_store, fused_store, None, mine, configured, overwrite=True)
    assert bag.is_file() and sorted(dem.iterdir()) == tiles and (ws / "drive.zarr").is_symlink()
    assert sorted(p.name for p in (mine / "dem").iterdir()) == [t.name for t in tiles]


def test_a_fused_store_of_another_drive_is_refused(drive_store, fused_store, cfg, tmp_path):
    """A fused store made from another drive store (a workspace whose drive was extracted
    again, longer, without fusing again) was read as this drive's: an IndexError traceback,
    or a dataset of wrong labels. Matched by the drive store's identity the fused store
    records, or, in a store fused before that, by the bags and samples."""
    from gtgen.dataset.dem_align import run_dem_align

    def with_attrs(**change: object) -> Path:
        fused = tmp_path / f"fused{len(list(tmp_path.iterdir()))}.zarr"
        shutil.copytree(fused_store, fused)
        meta = json.loads((fused / "zarr.json").read_text())
        for k, v in change.items():
            if v is None:
                meta["attributes"].pop(k)
            else:
                meta["attributes"][k] = v
        (fused / "zarr.json").write_text(json.dumps(meta))
        shutil.rmtree(fused / "gtgen_manifest")
        write_manifest(fused)  # a complete store of another drive, not a damaged one
        return fused

    for fused in (with_attrs(drive_identity="0123456789abcdef"),
                  with_attrs(drive_identity=None, drive_bags=[{"path": "other.mcap", "sha256": "0" * 64}])):
        with pytest.raises(StoreError, match="was fused from another drive store .* run 'gtgen fuse"):
            run_dem_align(drive_store, fused, None, tmp_path / "out.zarr", cfg)
        assert not (tmp_path / "out.zarr").exists()
    assert json.loads((fused_store / "zarr.json").read_text())["attributes"]["drive_identity"] == DriveStore(drive_store).identity


def test_export_geotiff_writes_into_a_folder_and_leaves_the_rest(dataset, tmp_path):
    qgis = tmp_path / "qgis"
    qgis.mkdir()
    (qgis / "project.qgz").write_bytes(b"qgis project")
    (qgis / "notes.txt").write_text("notes")
    for _ in range(2):  # the second run replaces its own files
        p = run_cli("export", "geotiff", dataset, "-o", qgis)
        assert p.returncode == 0, p.stderr
    assert (qgis / "project.qgz").read_bytes() == b"qgis project" and (qgis / "notes.txt").read_text() == "notes"
    tif = next(qgis.rglob("elevation_m.tif"))
    tif.write_bytes(b"the user's own raster")
    p = run_cli("export", "geotiff", dataset, "-o", qgis)
    assert p.returncode == 1 and "--overwrite" in _one_line(p)
    assert tif.read_bytes() == b"the user's own raster"
    assert run_cli("export", "geotiff", dataset, "-o", qgis, "--overwrite").returncode == 0
    assert owned(tif)


def test_train_eval_and_viz_refuse_the_users_files_before_any_work(dataset, tmp_path):
    """train --run-dir into a folder of the user's: a file of a run's name there (its CSV
    curves too, which carry no signature) stops the run before it writes anything;
    --overwrite replaces it; a run folder gtgen wrote is its own to write again."""
    import yaml

    from test_train import SMALL_TRAIN

    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump(SMALL_TRAIN))
    for name in ("train.csv", "ckpt.pt", "metrics.json"):
        run = tmp_path / name.replace(".", "_")
        run.mkdir()
        (run / name).write_text("mine")
        (run / "notes.txt").write_text("notes")
        p = run_cli("train", dataset, "--steps", "1", "--run-dir", run, "-c", c, cwd=tmp_path)
        line = _one_line(p)
        assert p.returncode == 1 and "--overwrite" in line and str(run / name) in line, line
        assert sorted(x.name for x in run.iterdir()) == sorted([name, "notes.txt"])  # nothing written beside them
        assert (run / name).read_text() == "mine"
    run = tmp_path / "train_csv"
    p = run_cli("train", dataset, "--steps", "1", "--run-dir", run, "-c", c, "--overwrite", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert (run / "train.csv").read_text().startswith("step,") and owned(run / "ckpt.pt")
    p = run_cli("train", dataset, "--steps", "1", "--run-dir", run, "-c", c, cwd=tmp_path)  # its own run folder now
    assert p.returncode == 0, p.stderr
    assert (run / "notes.txt").read_text() == "notes"
    # eval and viz --ckpt refuse a file of the user's before they evaluate (no table printed)
    mine = tmp_path / "mine.json"
    mine.write_text("mine")
    for cmd in (("eval", dataset, "--ckpt", run / "ckpt.pt", "--split", "all", "-o", mine),
                ("viz", dataset, "-n", "1", "--ckpt", run / "ckpt.pt", "-o", mine)):
        p = run_cli(*cmd, cwd=tmp_path)
        assert p.returncode == 1 and "--overwrite" in _one_line(p) and p.stdout == "", (cmd, p.stdout)
        assert mine.read_text() == "mine"
    p = run_cli("eval", dataset, "--ckpt", run / "ckpt.pt", "--split", "all", "-o", mine, "--overwrite", cwd=tmp_path)
    assert p.returncode == 0 and owned(mine), p.stderr


def test_report_refuses_the_users_files_before_any_work(dataset, tmp_path):
    """A user's report.json in the report folder: refused before any figure is written
    there; a file as the report folder: one line naming it."""
    qa = tmp_path / "qa"
    qa.mkdir()
    (qa / "report.json").write_text("mine")
    p = run_cli("report", dataset, "-o", qa)
    assert p.returncode == 1 and "--overwrite" in _one_line(p) and str(qa / "report.json") in p.stderr
    assert [x.name for x in qa.iterdir()] == ["report.json"] and (qa / "report.json").read_text() == "mine"
    afile = tmp_path / "a_file"
    afile.write_text("mine")
    p = run_cli("report", dataset, "-o", afile)
    assert p.returncode == 1 and f"output '{afile}' is a file" in _one_line(p) and afile.read_text() == "mine"
    p = run_cli("report", dataset, "-o", qa, "--overwrite")
    assert p.returncode == 0 and owned(qa / "report.json"), p.stderr


def test_a_rerun_replaces_its_own_outputs_and_overwrite_replaces_the_users(tmp_path):
    out = tmp_path / "r.json"
    write_json(out, {"a": 1})
    write_json(out, {"a": 2})
    assert json.loads(out.read_text())["a"] == 2
    out.write_text('{"a": 3}')
    with pytest.raises(OutputExistsError, match="--overwrite"):
        write_json(out, {"a": 4})
    write_json(out, {"a": 5}, overwrite=True)
    assert json.loads(out.read_text())["a"] == 5


def test_locks_and_failed_outputs_leave_nothing_in_the_users_folders(tmp_path):
    out = tmp_path / "new" / "deeper" / "x.zarr"
    with pytest.raises(RuntimeError), atomic_output(out) as tmp:
        tmp.mkdir()
        raise RuntimeError("boom")
    assert not (tmp_path / "new").exists()  # the folders made for the output went with it
    assert tmp_path not in lock_path(out).parents
    p = run_cli("fuse", "-c", SMALL, cwd=tmp_path)  # no workspace: fails, makes none
    assert p.returncode == 1 and not (tmp_path / "gtgen_ws").exists()
    assert not list(tmp_path.rglob("*.lock"))


def test_a_full_disk_is_one_line_and_leaves_nothing(dataset, tmp_path):
    small = tmp_path / "small"
    small.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(small)], capture_output=True).returncode:
        pytest.skip("this machine does not let the tests mount a small tmpfs")
    try:
        p = run_cli("export", "mcap", dataset, "-o", small / "x.mcap")
        assert p.returncode == 1 and "no space left" in _one_line(p)
        assert not list(small.iterdir())
        p = run_cli("export", "geotiff", dataset, "-o", small / "tifs")
        assert p.returncode == 1 and "no space left" in _one_line(p).lower()
        assert not list(small.iterdir())
    finally:
        subprocess.run(["umount", str(small)], check=False)


def test_drive_store_reads_are_checked_too(drive_store, tmp_path):
    drive = _copy(drive_store, tmp_path / "d.zarr")
    victim = next(p for p in (drive / "samples" / "jpeg").iterdir() if p.name.startswith("c."))
    victim.unlink()
    d = DriveStore(drive)
    with pytest.raises(StoreError, match="samples/jpeg.*gtgen extract"):
        d.jpeg(np.arange(d.n_samples))


# -- a kill -9 inside each stage, then the same command again --------------------------------

def _kill_when(folder: Path, pattern: str, args: list, cwd: Path, hold: str | None = None) -> None:
    """Start ``gtgen ARGS``, SIGKILL it once something matching ``pattern`` (its partial
    output or scratch) appears in ``folder``. ``hold`` ("module.function") makes that
    function of the run hang at its first call, for a stage too quick to catch mid-write
    (the kill then lands while the function's caller holds its temporary output)."""
    import signal
    import sys
    import time

    cmd = [sys.executable, "-m", "gtgen"]
    if hold is not None:
        mod, fn = hold.rsplit(".", 1)
        cmd = [sys.executable, "-c",
               f"import sys, time, {mod} as m\n"
               f"m.{fn} = lambda *a, **k: time.sleep(600)\n"
               "from gtgen.cli import main\nsys.argv[0] = 'gtgen'\nmain()"]
    p = subprocess.Popen([*cmd, *map(str, args)], cwd=cwd, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 300
    while not list(folder.glob(pattern)) and p.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert p.poll() is None, f"gtgen {args[0]} ended before it could be killed mid-write"
    if hold is not None:
        time.sleep(0.5)  # let it reach the held call
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()


@pytest.mark.parametrize("stage", ["extract", "dem-align", "export-mcap"])
def test_a_stage_killed_then_run_again_gives_the_same_output(stage, drive_dir, drive_store, fused_store, dataset, tmp_path):
    ws = tmp_path / "gtgen_ws"
    ws.mkdir()
    if stage == "extract":
        args, out, ref = ["extract", drive_dir / "drive.mcap", "-c", SMALL, "--workers", "1"], ws / "drive.zarr", drive_store
    elif stage == "dem-align":
        (ws / "drive.zarr").symlink_to(drive_store)
        (ws / "fused.zarr").symlink_to(fused_store)
        args, out, ref = ["dem-align", "-c", SMALL], ws / "dataset.zarr", dataset
    else:
        args, out, ref = ["export", "mcap", dataset, "-o", ws / "x.mcap"], ws / "x.mcap", None
    # the export of the small dataset is over in an instant: it is held at its first sample
    if stage == "export-mcap":
        _kill_when(ws, "x.mcap.*", args, tmp_path, hold="gtgen.export.mcap._write_sample")
    else:
        _kill_when(ws, "*.partial", args, tmp_path)
    assert not out.exists()
    p = run_cli(*args, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert not list(ws.glob("*.partial"))  # nothing left of the killed run
    if ref is not None:
        a, b = (DatasetStore(x) if stage == "dem-align" else DriveStore(x) for x in (ref, out))
        for path in (("labels/micro/elevation_m", "meta/T_crs_target") if stage == "dem-align" else ("samples/t_ns", "samples/jpeg")):
            np.testing.assert_array_equal(a.read(path), b.read(path), err_msg=path)
        assert verify_store(out)[1].problems == []
