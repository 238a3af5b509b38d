"""Robots other than X-Racer: any camera rig (0 to 8 cameras of any names), samples without
a camera (snapped to the lidar), no GNSS and no DEM (``--no-dem``), a base that tilts, one
slow lidar; and the real hand-held hall walk through the whole chain."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import REALDATA, SMALL, needs_realdata, run_cli, shared, small_config
from gtgen.config import CAMERAS, build_config, load_config
from gtgen.errors import ConfigError

HALL = REALDATA / "balm_indoor_lidar_0_59"
ROBOTS = Path(__file__).resolve().parents[1] / "configs" / "robots"
TINY = {"train": {"micro_size": 32, "short_size": 32, "image_width": 48, "image_height": 30, "depth_step_m": 8.0, "image_channels": 8,
                  "pillar_channels": 8, "decoder_channels": 8, "batch_size": 2, "steps": 200, "val_every": 0}}


def _cams(*names: str) -> dict:
    return {n: {"image": f"/{n}/image", "info": f"/{n}/info"} for n in names}


def test_a_camera_mapping_of_any_names_replaces_the_default_rig():
    cfg = build_config({"topics": {"cameras": _cams("cam0", "stereo_left")}})
    assert cfg.topics.camera_names == ["cam0", "stereo_left"] and cfg.reference == "cam0"
    none = build_config({"topics": {"cameras": {}, "gnss": None}})
    assert none.topics.camera_names == [] and none.reference == "lidar" and none.topics.gnss is None
    # a later layer's rig replaces an earlier one's whole; the default stays X-Racer's four
    assert build_config({"topics": {"cameras": _cams("a", "b")}}, {"topics": {"cameras": _cams("c")}}).topics.camera_names == ["c"]
    assert build_config().topics.camera_names == list(CAMERAS)
    assert build_config({"topics": {"cameras": _cams(*(f"c{i}" for i in range(8)))}}).topics.camera_names[-1] == "c7"


@pytest.mark.parametrize("over, needle", [
    ({"topics": {"cameras": _cams(*(f"c{i}" for i in range(9)))}}, "names 9 cameras"),
    ({"topics": {"cameras": {"front": {"image": "/front/image"}}}}, "'topics.cameras.front.info': Field required"),
    ({"topics": {"cameras": {"a": {"image": "/x", "info": "/a/info"}, "b": {"image": "/x", "info": "/b/info"}}}},
     "topic '/x' is given for topics.cameras.a.image and topics.cameras.b.image"),
    ({"topics": {"cameras": _cams("a/b")}}, "camera name 'a/b'"),
    ({"extract": {"reference": "rear"}}, "extract.reference = 'rear' names no configured sensor; expected one of ['front', 'left', 'right', 'back', 'lidar']"),
    ({"extract": {"reference": "lidar"}, "topics": {"lidar": []}}, "topics.lidar lists no lidar topic"),
])
def test_bad_rigs_are_one_line(over, needle):
    with pytest.raises(ConfigError) as exc:
        build_config(over)
    assert needle in str(exc.value) and "\n" not in str(exc.value)


def test_cli_refuses_no_dem_beside_dem_and_a_ninth_camera(tmp_path):
    p = run_cli("dem-align", tmp_path / "drive.zarr", "--no-dem", "--dem", tmp_path, cwd=tmp_path)
    assert p.returncode == 2 and "--no-dem and --dem" in p.stderr and "Traceback" not in p.stderr
    c = tmp_path / "nine.yaml"
    c.write_text(yaml.safe_dump({"topics": {"cameras": _cams(*(f"c{i}" for i in range(9)))}}))
    p = run_cli("extract", tmp_path / "x.mcap", "--config", c, cwd=tmp_path)
    assert p.returncode != 0 and "names 9 cameras" in p.stderr and len(p.stderr.strip().splitlines()) == 1


@pytest.fixture(scope="session")
def blind(tmp_path_factory) -> tuple[Path, Path]:
    """A drive without cameras whose samples snap to its one slow lidar (2 Hz), extracted,
    fused and placed without a DEM; returns (its config file, the dataset); read only, one
    copy for both xdist workers."""
    from gtgen.dataset.dem_align import run_dem_align
    from gtgen.extract import run_extract
    from gtgen.fuse.run import run_fuse
    from gtgen.synth import run_synth

    layer = {"topics": {"cameras": {}, "lidar": ["/lidar/front/points"]}, "synth": {"scan_rate_hz": 2.0, "formats": "mcap"}}

    def build(root: Path) -> None:
        root.mkdir(parents=True)
        cfg = small_config(**layer)
        run_synth(cfg, root / "drive")
        ws = root / "gtgen_ws"
        run_extract([root / "drive" / "drive.mcap"], ws / "drive.zarr", cfg, workers=1)
        run_fuse(ws / "drive.zarr", ws / "fused.zarr", cfg, workers=1)
        nodem = cfg.model_copy(update={"dem": cfg.dem.model_copy(update={"enabled": False})})
        run_dem_align(ws / "drive.zarr", ws / "fused.zarr", None, ws / "dataset.zarr", nodem, workers=1)
        (root / "blind.yaml").write_text(yaml.safe_dump({**yaml.safe_load(SMALL.read_text()), **{"topics": layer["topics"]}, **TINY}))

    root = shared(tmp_path_factory, "any_robot/blind", build)
    return root / "blind.yaml", root / "gtgen_ws" / "dataset.zarr"


def test_a_drive_without_cameras_snaps_to_the_lidar_and_holds_no_images(blind):
    import gtgen
    from gtgen.storage.drive import DriveStore

    _, dataset = blind
    drive = DriveStore(dataset.parent / "drive.zarr")
    scans = drive.scans
    assert drive.cameras == [] and drive.K().shape == (0, 3, 3) and drive.samples.image_t_ns.shape == (drive.n_samples, 0)
    assert np.isin(drive.samples.t_ns, scans.t_ns[scans.lidar == 0]).all()  # every sample at a scan of the first lidar
    ds = gtgen.open_dataset(dataset)
    assert ds.cameras == [] and ds.images(0) == [] and "jpeg" not in ds.zarr["inputs"]
    # no DEM: nothing unobserved is labelled, no DEM grid, no placement; the split by odom blocks
    for r in ("micro", "short"):
        reg = ds.store.grid("labels", r, "region")[0]
        assert (reg != 3).all() and (reg == 0).any() and np.isnan(ds.store.grid("dem", r, "elevation_m")[0]).all()  # QA grids kept (small.yaml)
    assert np.isnan(ds.store.meta("T_crs_target")).all() and ds.attrs.drives[0].crs == ""


def test_a_dataset_without_cameras_or_dem_reports_trains_evaluates_and_skips_the_camera_rows(blind, tmp_path):
    conf, dataset = blind
    p = run_cli("report", dataset, "-o", tmp_path / "rep", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "no DEM:" in p.stdout and "of the cells unlabelled" in p.stdout
    p = run_cli("train", dataset, "--steps", "1", "--run-dir", tmp_path / "run", "--config", conf, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "holds no camera images: the camera input is off" in p.stderr
    p = run_cli("eval", dataset, "--ckpt", tmp_path / "run" / "ckpt.pt", "--split", "all", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    # the elevation tables' rows (MAE with coverage per region; the risk table has none)
    elev = [ln for ln in p.stdout.splitlines() if ln.startswith("│ M&M-lite  ") and "%)" in ln]
    assert len(elev) == 2 and all(" - " in ln for ln in elev), elev  # the empty unobserved region prints "-"
    p = run_cli("viz", dataset, "-n", "1", "-o", tmp_path / "s.png", cwd=tmp_path)
    assert p.returncode == 0 and (tmp_path / "s.png").is_file()
    p = run_cli("export", "geotiff", dataset, "-o", tmp_path / "qgis", cwd=tmp_path)
    assert p.returncode == 1 and "no georeference" in p.stderr and "--no-dem" in p.stderr


def test_experiments_on_a_dataset_without_cameras_skip_the_camera_rows(blind):
    import gtgen.train.experiments as ex
    import gtgen.train.tables as tables

    plan = ex._plan(True, tables.parse_tables("I,II"), cameras=False)
    assert plan.no_cameras == ["LSS"] and not any(r.startswith("lss") for r in plan.needed)
    assert all(plan.runs[r].train.get("cameras") is False for r in plan.needed)
    labels = {ln.label: ln.inputs for ln in plan.tables[0].lines}
    assert labels["Ours"] == "VM" and labels["RoadRunner"] == "L + E" and labels["X-Racer at t"] == "C + VM"
    assert ex._plan(True, tables.parse_tables("I"), cameras=True).no_cameras == []


@pytest.fixture(scope="session")
def one_camera(tmp_path_factory) -> Path:
    """A drive of one camera (gtgen synth --cameras 1: front) through the chain with its DEM
    (read only: one copy for both xdist workers)."""
    return shared(tmp_path_factory, "any_robot/one", _one_camera) / "gtgen_ws" / "dataset.zarr"


def _one_camera(root: Path) -> None:
    root.mkdir(parents=True)
    conf = root / "small.yaml"
    conf.write_text(yaml.safe_dump({**yaml.safe_load(SMALL.read_text()), **TINY}))
    p = run_cli("synth", root / "d", "--cameras", "1", "--format", "mcap", "--config", conf, cwd=root)
    assert p.returncode == 0, p.stderr
    assert "--config" in p.stdout  # its topics are not the default mapping's: the summary says how to extract it
    saved = yaml.safe_load((root / "d" / "gtgen-config.yaml").read_text())
    assert list(saved["topics"]["cameras"]) == ["front"]
    for args in (("extract", root / "d" / "drive.mcap", "--workers", "1", "--config", root / "d" / "gtgen-config.yaml"),
                 ("fuse", "--workers", "1", "--config", root / "d" / "gtgen-config.yaml"), ("dem-align", "--config", root / "d" / "gtgen-config.yaml")):
        p = run_cli(*args, cwd=root)
        assert p.returncode == 0, p.stderr


def test_one_camera_trains_and_a_checkpoint_of_another_rig_is_refused(one_camera, dataset, tmp_path):
    import gtgen

    ds = gtgen.open_dataset(one_camera)
    assert ds.cameras == ["front"] and len(ds.images(0)) == 1 and ds.store.input_rows("K", [0]).shape == (1, 1, 3, 3)
    conf = tmp_path / "tiny.yaml"
    conf.write_text(yaml.safe_dump(TINY))
    p = run_cli("train", one_camera, "--steps", "1", "--run-dir", tmp_path / "one", "--config", conf, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    p = run_cli("eval", one_camera, "--ckpt", tmp_path / "one" / "ckpt.pt", "--split", "all", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    p = run_cli("export", "onnx", "--ckpt", tmp_path / "one" / "ckpt.pt", "-o", tmp_path / "one.onnx", cwd=tmp_path)
    assert p.returncode == 0 and "front" in p.stdout, p.stderr
    # the four-camera session dataset: the one-camera model's image branch does not fit it
    p = run_cli("eval", dataset, "--ckpt", tmp_path / "one" / "ckpt.pt", "--split", "all", cwd=tmp_path)
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1
    assert "trained on the cameras ['front']" in p.stderr and "['front', 'left', 'right', 'back']" in p.stderr


def test_merging_drives_of_two_rigs_is_one_line(one_camera, dataset, tmp_path):
    from gtgen.dataset.merge import merging
    from gtgen.errors import GtgenError

    with pytest.raises(GtgenError, match=r"has the cameras \['front', 'left', 'right', 'back'\], the drives before it \['front'\]"):
        with merging(tmp_path / "both.zarr", load_config(SMALL)) as m:
            m.add("one", one_camera)
            m.add("four", dataset)
    assert not (tmp_path / "both.zarr").exists()


@needs_realdata()
def test_a_lidar_log_under_the_default_config_says_how_to_map_it(tmp_path):
    p = run_cli("extract", HALL, cwd=tmp_path)
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1
    assert "hold no GridMap but PointCloud2 topics ['/points']" in p.stderr and "map_short and voxel_map to null" in p.stderr


@needs_realdata()
def test_the_real_hand_held_hall_walk_goes_through_the_chain(tmp_path):
    """60 real scans at 2 Hz from a tilted hand-held lidar, poses from lidar odometry, no
    camera, GNSS or DEM (configs/robots/lidar_poses.yaml): the floor is one plane, walls fatal."""
    from gtgen.grids import grid_xy
    from gtgen.storage.dataset import DatasetStore

    conf = ROBOTS / "lidar_poses.yaml"
    for args in (("extract", HALL, "--workers", "1"), ("fuse", "--workers", "1"), ("dem-align",)):  # a pool is not the point here
        p = run_cli(*args, "--config", conf, cwd=tmp_path)
        assert p.returncode == 0, (args, p.stderr)
    p = run_cli("report", cwd=tmp_path)
    assert p.returncode == 0 and "no DEM:" in p.stdout, p.stderr
    p = run_cli("viz", "--sample", "5", "-o", "s5.png", cwd=tmp_path)
    assert p.returncode == 0 and (tmp_path / "s5.png").is_file(), p.stderr
    ds = DatasetStore(tmp_path / "gtgen_ws" / "dataset.zarr")
    assert ds.n_samples >= 12 and ds.cameras == []
    g = ds.config.grids.micro
    X, Y = grid_xy(g.size, g.resolution_m)
    mads, fatal, labelled = [], 0, 0
    for k in range(ds.n_samples):
        el, rk = ds.grid("labels", "micro", "elevation_m")[k], ds.grid("labels", "micro", "risk")[k]
        lab = np.isfinite(el)
        floor = lab & (rk < 0.5)
        A = np.c_[X[floor], Y[floor], np.ones(int(floor.sum()))]
        res = el[floor] - A @ np.linalg.lstsq(A, el[floor], rcond=None)[0]
        mads.append(np.median(np.abs(res - np.median(res))))
        fatal += int((lab & (rk >= 0.5)).sum())
        labelled += int(lab.sum())
    assert max(mads) <= 0.03  # the raw scans' floor is one plane within 5 mm MAD
    assert 0.03 < fatal / labelled < 0.5  # walls and pillars
