"""Adverse inputs at the edges, each through the real CLI: bags with duplicated and with
undecodable messages (ROS 2 MCAP and ROS 1), bad option values, bad config and manifest
files, misspelt keys. Every case asserts the exit code, a one-line message without a
traceback, and that no file in the user's folder changed."""

from __future__ import annotations

import dataclasses
import hashlib
import subprocess
from pathlib import Path

import numpy as np
import pytest

from bagtools import rewrite
from conftest import SMALL, assert_same_store, run_cli
from gtgen.bag.reader import stamp_ns
from gtgen.storage.drive import DriveStore

MICRO, SHORT, VOXEL = "/xracer/map/micro", "/xracer/map/short", "/xracer/voxel_map"
LEFT, RIGHT = "/cam_left/image/compressed", "/cam_right/image/compressed"


# -- what every case checks ---------------------------------------------------------------
def gtgen(*args: object, cwd: Path, columns: int = 80) -> subprocess.CompletedProcess:
    """Run ``python -m gtgen ARGS`` in ``cwd`` on a terminal ``columns`` wide."""
    return run_cli(*args, cwd=cwd, columns=columns, timeout=300)


def snapshot(folder: Path) -> dict[str, str]:
    """Return every file and folder under ``folder`` with the sha256 of each file."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "folder"
            for p in sorted(folder.rglob("*"))}


@pytest.fixture
def user(tmp_path: Path) -> Path:
    """A user's folder holding files of their own (the commands run in it)."""
    home = tmp_path / "user"
    (home / "qgis").mkdir(parents=True)
    (home / "notes.txt").write_text("field notes, day 3\n")
    (home / "qgis" / "project.qgz").write_bytes(bytes(range(256)))
    return home


def error_line(p: subprocess.CompletedProcess, code: int) -> str:
    """Assert exit ``code`` and a one-line error (after the usage line for a usage error,
    exit 2); return the error line."""
    lines = p.stderr.strip().splitlines()
    assert p.returncode == code, (p.returncode, p.stderr[-2000:])
    assert "Traceback" not in p.stdout + p.stderr
    assert len(lines) == (2 if code == 2 else 1), p.stderr
    if code == 2:
        assert lines[0].startswith("Usage: gtgen ")
    assert lines[-1].startswith("error: ")
    return lines[-1]


def topics(store: Path) -> dict[str, dict]:
    return {t["topic"]: t for t in DriveStore(store).attrs["report"]["topics"]}


def table_row(stdout: str, topic: str) -> list[str]:
    """Return the cells of the extract table's row of ``topic`` (a wide terminal: one line)."""
    line = next(line for line in stdout.splitlines() if f"│ {topic} " in line)
    return [c.strip() for c in line.split("│")[1:-1]]


def stamp(msg: object) -> int:
    return stamp_ns(msg.header if hasattr(msg, "header") else msg.info.header)


@pytest.fixture(scope="module")
def needed(drive_store: Path) -> dict[str, set[int]]:
    """Stamps of the messages the clean drive's store holds, per topic. Every candidate of
    the small drive is a sample, so a message no sample uses is one no candidate uses."""
    g = DriveStore(drive_store).group
    assert (g["candidates/reason"][:] == 0).all()
    return {MICRO: set(g["maps/micro/t_ns"][:].tolist()), SHORT: set(g["maps/short/t_ns"][:].tolist()),
            RIGHT: set(g["samples/image_t_ns"][:, 2].tolist())}


def extract(user: Path, bag: Path, *more: object) -> tuple[subprocess.CompletedProcess, Path]:
    out = user / "out" / "d.zarr"
    return gtgen("extract", bag, "-o", out, "-c", SMALL, *more, cwd=user, columns=200), out


# -- bags: duplicated messages ---------------------------------------------------------------
@pytest.mark.parametrize("name", ["drive.mcap", "drive.bag"])
def test_every_message_recorded_twice_is_used_once(drive_dir, drive_store, user, name):
    """Every message twice: half the copies at the same record time (the same slice), half
    3 s later (another slice on 2 workers). Each topic counts half its messages as
    duplicates and the store is the clean bag's."""
    n = {"k": 0}

    def twice(topic, t, msg):
        n["k"] += 1
        return [(t, msg), (t + (3_000_000_000 if n["k"] % 2 else 0), msg)]

    bag = rewrite(drive_dir / name, user / f"twice{Path(name).suffix}", twice)
    before = snapshot(user)
    p, out = extract(user, bag, "--workers", "2")
    assert p.returncode == 0, p.stderr[-2000:]
    rows, clean = topics(out), topics(drive_store)
    assert rows.keys() == clean.keys() and len(rows) == 15
    for t, row in rows.items():
        n = clean[t].pop("count")
        assert row.pop("count") == 2 * n and row.pop("dropped") == {"duplicate": n}, t
        assert row == {k: v for k, v in clean[t].items() if k != "dropped"}, t  # rates, gaps, skews: the clean bag's
    assert table_row(p.stdout, MICRO)[6] == f"duplicate {topics(drive_store)[MICRO]['count']}"  # the dropped column
    assert_same_store(drive_store, out)
    assert {k: v for k, v in snapshot(user).items() if not k.startswith("out")} == before


# -- bags: messages that do not decode ---------------------------------------------------------
def _break_unneeded(needed: dict[str, set[int]]):
    """Return an edit breaking the first message, among those no sample uses, of: the micro
    maps (data shorter than the layout), the short maps (twice the resolution: another
    grid), the right camera (not a JPEG)."""
    todo = {MICRO, SHORT, RIGHT}

    def edit(topic, t, msg):
        if topic in todo and stamp(msg) not in needed[topic]:
            todo.discard(topic)
            if topic == MICRO:
                msg.data[0].data = msg.data[0].data[:-1]
            elif topic == SHORT:
                msg.info.resolution *= 2
                msg.info.length_x *= 2
                msg.info.length_y *= 2
            else:
                msg = dataclasses.replace(msg, data=np.frombuffer(b"not a jpeg", np.uint8))
        yield t, msg

    return edit


@pytest.mark.parametrize("name", ["drive.mcap", "drive.bag"])
def test_messages_that_do_not_decode_are_counted_and_the_run_goes_on(drive_dir, drive_store, needed, user, name):
    bag = rewrite(drive_dir / name, user / f"bad{Path(name).suffix}", _break_unneeded(needed))
    before = snapshot(user)
    p, out = extract(user, bag, "--workers", "1")
    assert p.returncode == 0, p.stderr[-2000:]
    rows = topics(out)
    assert rows[MICRO]["decode_failures"] == 1 and "values for a" in rows[MICRO]["first_error"]
    assert rows[SHORT]["decode_failures"] == 0 and rows[SHORT]["dropped"] == {"size_changed": 1}
    assert rows[RIGHT]["decode_failures"] == 1 and "does not decode" in rows[RIGHT]["first_error"]
    assert sum(r["decode_failures"] for r in rows.values()) == 2
    assert table_row(p.stdout, MICRO)[5].startswith("1 (GridMap layer")  # the decode failures column
    assert_same_store(drive_store, out)
    assert {k: v for k, v in snapshot(user).items() if not k.startswith("out")} == before


@pytest.mark.parametrize("topic, column, skew, reason, needle", [
    (LEFT, "samples/image_t_ns", "image_skew_s", "no_image", "does not decode"),  # a JPEG cut short
    (VOXEL, "samples/voxel_t_ns", "voxel_skew_s", "no_voxel", "data bytes"),  # a PointCloud2 whose data stop halfway
])
def test_an_undecodable_message_a_sample_needs_rejects_that_sample(drive_dir, drive_store, cfg, user, topic, column, skew, reason,
                                                                   needle):
    """Sample 5's left image or voxel map does not decode: each sample that used it takes
    another within its skew tolerance or is rejected with its reason; the others are the
    clean bag's."""
    clean = DriveStore(drive_store).group
    col = (lambda g: g[column][:, 1]) if column.endswith("image_t_ns") else (lambda g: g[column][:])
    victim = int(col(clean)[5])
    lost = col(clean) == victim

    def edit(t_, t, msg):
        if t_ == topic and stamp(msg) == victim:
            msg = dataclasses.replace(msg, data=msg.data[: len(msg.data) // 2])
        yield t, msg

    bag = rewrite(drive_dir / "drive.mcap", user / "cut.mcap", edit)
    before = snapshot(user)
    p, out = extract(user, bag, "--workers", "1")
    assert p.returncode == 0, p.stderr[-2000:]
    assert topics(out)[topic]["decode_failures"] == 1 and needle in topics(out)[topic]["first_error"]
    g = DriveStore(out).group
    t_new, t_clean = g["samples/t_ns"][:], clean["samples/t_ns"][:]
    gone = ~np.isin(t_clean, t_new)
    assert gone[lost].any() and not gone[~lost].any() and np.isin(t_new, t_clean).all()
    assert g.attrs["report"]["rejected"] == {reason: int(gone.sum())}
    again = np.isin(t_new, t_clean[lost])  # took another message within the tolerance
    assert (col(g)[again] != victim).all() and (np.abs(col(g)[again] - t_new[again]) <= getattr(cfg.extract, skew) * 1e9).all()
    for j, k in zip(np.nonzero(~again)[0], np.nonzero(~lost)[0]):
        assert t_new[j] == t_clean[k]
        np.testing.assert_array_equal(g["samples/jpeg"][j], clean["samples/jpeg"][k])
        np.testing.assert_array_equal(g["voxel_maps/points_odom_m"][int(g["samples/voxel_index"][j])],
                                      clean["voxel_maps/points_odom_m"][int(clean["samples/voxel_index"][k])])
        for r in ("micro", "short"):
            np.testing.assert_array_equal(g[f"maps/{r}/elevation_m"][int(g[f"samples/map_index_{r}"][j])],
                                          clean[f"maps/{r}/elevation_m"][int(clean[f"samples/map_index_{r}"][k])])
    assert {k: v for k, v in snapshot(user).items() if not k.startswith("out")} == before


@pytest.mark.parametrize("name", ["drive.mcap", "drive.bag"])
def test_an_uncalibrated_camera_info_and_a_nan_pose_are_decode_failures(drive_dir, drive_store, user, name):
    """The back camera's first three CameraInfo say 0 x 0 px and every 50th odometry
    message holds a NaN: counted, not used; the calibration is the clean bag's and the
    pose track the clean one without those stamps."""
    seen = {"info": 0, "odom": 0}
    nan_stamps = []

    def edit(topic, t, msg):
        if topic == "/cam_back/camera_info" and seen["info"] < 3:
            seen["info"] += 1
            msg = dataclasses.replace(msg, width=0, height=0)
        elif topic == "/xracer/odometry":
            seen["odom"] += 1
            if seen["odom"] % 50 == 1:
                nan_stamps.append(stamp(msg))
                pose = msg.pose.pose
                pose = dataclasses.replace(pose, position=dataclasses.replace(pose.position, x=float("nan")))
                msg = dataclasses.replace(msg, pose=dataclasses.replace(msg.pose, pose=pose))
        yield t, msg

    bag = rewrite(drive_dir / name, user / f"uncalibrated{Path(name).suffix}", edit)
    before = snapshot(user)
    p, out = extract(user, bag, "--workers", "1")
    assert p.returncode == 0, p.stderr[-2000:]
    rows = topics(out)
    assert rows["/cam_back/camera_info"]["decode_failures"] == 3 and "not a calibration" in rows["/cam_back/camera_info"]["first_error"]
    assert rows["/xracer/odometry"]["decode_failures"] == len(nan_stamps) == 9 and "not a pose" in rows["/xracer/odometry"]["first_error"]
    g, clean = DriveStore(out).group, DriveStore(drive_store).group
    np.testing.assert_array_equal(g["calib/K"][:], clean["calib/K"][:])
    t_clean = clean["poses/t_ns"][:]
    np.testing.assert_array_equal(g["poses/t_ns"][:], t_clean[~np.isin(t_clean, nan_stamps)])
    assert np.isfinite(g["poses/pos_odom_m"][:]).all() and np.isfinite(g["samples/pos_odom_m"][:]).all()
    assert {k: v for k, v in snapshot(user).items() if not k.startswith("out")} == before


def _garbage_image(msg):
    return dataclasses.replace(msg, data=np.frombuffer(b"\xff\xd8 not a jpeg", np.uint8))


def _short_data(msg):
    msg.data[0].data = msg.data[0].data[:-1]
    return msg


def _uncalibrated(msg):
    return dataclasses.replace(msg, width=0, height=0)


@pytest.mark.parametrize("topic, spoil, needle", [
    (LEFT, _garbage_image, "does not decode"),
    (MICRO, _short_data, "values for a"),
    ("/cam_back/camera_info", _uncalibrated, "not a calibration"),
])
def test_a_topic_with_no_usable_message_stops_the_run_in_one_line(drive_dir, user, topic, spoil, needle):
    bag = rewrite(drive_dir / "drive.mcap", user / "spoilt.mcap", lambda t_, t, msg: [(t, spoil(msg) if t_ == topic else msg)])
    before = snapshot(user)
    p, out = extract(user, bag, "--workers", "1")
    line = error_line(p, 1)
    assert line.startswith(f"error: {topic}: none of its ") and "decode failures" in line and needle in line
    assert not out.exists()
    assert {k: v for k, v in snapshot(user).items() if not k.startswith("out")} == before


# -- bad option values ----------------------------------------------------------------------
@pytest.mark.parametrize("args, option", [
    (("fuse", "--window", "inf"), "--window"),
    (("fuse", "--window", "nan"), "--window"),
    (("fuse", "--window", "-inf"), "--window"),
    (("fuse", "--window", "0"), "--window"),
    (("fuse", "--window", "1e300"), "--window"),
    (("fuse", "--past", "inf"), "--past"),
    (("fuse", "--past", "nan"), "--past"),
    (("fuse", "--past", "-1"), "--past"),
    (("fuse", "--workers", "0"), "--workers"),
    (("synth", "drive", "--duration", "inf"), "--duration"),
    (("synth", "drive", "--duration", "nan"), "--duration"),
    (("synth", "drive", "--duration", "0"), "--duration"),
    (("synth", "drive", "--duration", "1e9"), "--duration"),
    (("synth", "drive", "--seed", "-1"), "--seed"),
    (("synth", "drive", "--format", "zip"), "--format"),
    (("extract", "bag.mcap", "--workers", "0"), "--workers"),
    (("extract", "bag.mcap", "--workers", "100000"), "--workers"),
    (("build", "drives", "--workers", "0"), "--workers"),
    (("viz", "--sample", "-1"), "--sample"),
    (("export", "geotiff", "--samples", "-1"), "--samples"),
    (("export", "geotiff", "--samples", "3,x"), "--samples"),
    (("viz", "--config", "c.yaml"), "--config"),  # viz reads the dataset's own config only
])
def test_a_bad_option_value_is_a_one_line_usage_error(user, args, option):
    before = snapshot(user)
    line = error_line(gtgen(*args, cwd=user), 2)
    assert option in line
    assert snapshot(user) == before


# -- bad config and manifest files --------------------------------------------------------------
@pytest.mark.parametrize("text, needle", [
    ("fuse:\n  windw_s: 30\n", "config key 'fuse.windw_s' is not a gtgen setting; did you mean 'fuse.window_s'?"),
    ("fuze:\n  window_s: 30\n", "config key 'fuze' is not a gtgen setting; did you mean 'fuse'?"),
    ("grids:\n  micro:\n    resoluton_m: 0.1\n", "did you mean 'grids.micro.resolution_m'?"),
    ("topics:\n  cameras:\n    front:\n      imag: /cam\n", "did you mean 'topics.cameras.front.image'?"),
    ("fuse:\n  zzz: 1\n", "fuse takes: window_s, past_s"),
    ("fuse:\n  window_s: .inf\n", "'fuse.window_s' = inf: Input should be a finite number"),
    ("fuse:\n  past_s: .nan\n", "'fuse.past_s' = nan: Input should be a finite number"),
    ("fuse:\n  window_s: 1.0e+12\n", "less than or equal to 86400"),
    ("fuse: [unclosed\n", "is not valid YAML: expected ',' or ']', but got '<stream end>' at line 2, column 1"),
    ("- a\n- b\n", "must hold a mapping of keys to values, got a list"),
    ("just words\n", "must hold a mapping of keys to values, got a str"),
    (b"\xff\xfe\x00garbage", "is not a text file: byte 0 is not UTF-8"),
    (None, "is a folder; expected a YAML file"),
])
def test_a_bad_config_file_is_a_one_line_error(user, text, needle):
    cfg = user / "my.yaml"
    if text is None:
        cfg.mkdir()
    elif isinstance(text, bytes):
        cfg.write_bytes(text)
    else:
        cfg.write_text(text)
    before = snapshot(user)
    line = error_line(gtgen("fuse", "--config", cfg, cwd=user), 1)
    assert needle in line
    assert snapshot(user) == before


@pytest.mark.parametrize("text, needle", [
    ("drives: {a: [x.mcap]\n", "manifest '{}' is not valid YAML"),
    ("- a.mcap\n- b.mcap\n", "manifest '{}' must hold a mapping of keys to values, got a list"),
])
def test_a_bad_manifest_is_a_one_line_error_before_any_drive_runs(user, text, needle):
    manifest = user / "manifest.yaml"
    manifest.write_text(text)
    before = snapshot(user)
    line = error_line(gtgen("build", manifest, "-o", user / "built", cwd=user), 1)
    assert needle.format(manifest) in line
    assert snapshot(user) == before
