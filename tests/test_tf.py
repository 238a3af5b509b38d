"""Frames from TF: maps published in a moving robot frame or in a drifting ``map`` frame
give the labels of the same maps published in odom; a gap in /tf drops exactly the maps
inside it; poses from TF alone; the buffer's lookups against hand-made transforms."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from bagtools import rewrite_mcap
from conftest import small_config
from gtgen.bag.poses import PoseTrack
from gtgen.bag.tf import TfBuffer, relevant_edges
from gtgen.extract import run_extract
from gtgen.fuse.run import run_fuse
from gtgen.geometry import invert, make_transform, matrix_to_quat, quat_to_matrix, quat_to_yaw, rpy_to_quat, yaw_transform

FUSED = ("fused/micro/elevation_m", "fused/short/elevation_m", "xracer/micro/elevation_m", "fused/short/region",
         "fused/micro/region", "fused/short/risk", "fused/micro/confidence")


def _stamp(h) -> int:
    return h.stamp.sec * 10**9 + h.stamp.nanosec


class _Rewrite:
    """Edits the synth drive so its maps are published in ``frame``, which TF relates to
    odom by ``T_odom_frame(t, base pose)``; /tf carries that edge at every odometry stamp."""

    def __init__(self, frame: str, T_odom_frame, gap_s: tuple[float, float] | None = None) -> None:
        self.frame, self.T_of, self.gap = frame, T_odom_frame, gap_s
        self.poses: dict[int, np.ndarray] = {}
        self.t0: int | None = None
        self.dropped_tf: list[int] = []

    def __call__(self, topic, t, msg):
        from gtgen.bag.msgdefs import typestore

        T = typestore(False).types
        self.t0 = t if self.t0 is None else self.t0
        if topic == "/xracer/odometry":
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            self.poses[_stamp(msg.header)] = make_transform(quat_to_matrix([q.x, q.y, q.z, q.w]), [p.x, p.y, p.z])
        elif topic == "/tf":
            ts = _stamp(msg.transforms[0].header)
            if self.gap and self.gap[0] < (ts - self.t0) * 1e-9 < self.gap[1]:
                self.dropped_tf.append(ts)
            else:
                M = self.T_of(ts * 1e-9, self.poses[ts])
                q = matrix_to_quat(M[:3, :3])
                tr = T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
                hdr = T["std_msgs/msg/Header"](stamp=msg.transforms[0].header.stamp, frame_id="odom")
                msg.transforms.append(T["geometry_msgs/msg/TransformStamped"](header=hdr, child_frame_id=self.frame, transform=tr))
        elif topic.startswith("/xracer/map/"):
            ts = _stamp(msg.header)
            M = invert(self.T_of(ts * 1e-9, self.poses[ts]))  # T_frame_odom
            c = msg.info.pose.position
            Tc = M @ yaw_transform(c.x, c.y, 0.0, 0.0)
            q = rpy_to_quat(0.0, 0.0, float(np.arctan2(Tc[1, 0], Tc[0, 0])))
            c.x, c.y = float(Tc[0, 3]), float(Tc[1, 3])
            o = msg.info.pose.orientation
            o.x, o.y, o.z, o.w = (float(v) for v in q)
            msg.header.frame_id = self.frame
            i = list(msg.layers).index("elevation")  # heights in a level frame: shifted by its height
            msg.data[i].data = (msg.data[i].data + np.float32(M[2, 3])).astype(np.float32)
        yield t, msg


def _gravity_frame(_t: float, T_odom_base: np.ndarray) -> np.ndarray:
    """base_gravity: at the base, heading with it, level."""
    return yaw_transform(*T_odom_base[:3, 3], float(quat_to_yaw(matrix_to_quat(T_odom_base[:3, :3]))))


def _drifting_map(t: float, _pose) -> np.ndarray:
    """odom -> map: localisation that drifts (the inverse of a map -> odom edge)."""
    return invert(yaw_transform(5.0 + 0.1 * (t % 1000), -3.0 + 0.05 * (t % 1000), 0.2, 0.3 + 0.01 * (t % 1000)))


def _fused(drive_dir, tmp_path, name, cfg, edit=None):
    bag = drive_dir / "drive.mcap" if edit is None else rewrite_mcap(drive_dir / "drive.mcap", tmp_path / f"{name}.mcap", edit)
    res = run_extract([bag], tmp_path / f"{name}.zarr", cfg, workers=1)
    run_fuse(tmp_path / f"{name}.zarr", tmp_path / f"{name}_f.zarr", cfg, workers=1)
    return res, zarr.open_group(str(tmp_path / f"{name}_f.zarr"), mode="r")


@pytest.mark.parametrize("frame, T_of", [("base_gravity", _gravity_frame), ("map", _drifting_map)])
def test_maps_in_other_frames_give_the_labels_of_maps_in_odom(drive_dir, tmp_path, cfg, frame, T_of):
    _, ref = _fused(drive_dir, tmp_path, "ref", cfg)
    res, got = _fused(drive_dir, tmp_path, frame, cfg, _Rewrite(frame, T_of))
    assert all(not t["dropped"] for t in res.topics)
    for name in FUSED:
        a, b = ref[name][:], got[name][:]
        if a.dtype.kind == "f":
            np.testing.assert_allclose(b, a, atol=1e-4, rtol=0, equal_nan=True, err_msg=name)
        else:
            np.testing.assert_array_equal(b, a, err_msg=name)


def test_a_gap_in_tf_drops_exactly_the_maps_inside_it(drive_dir, tmp_path, cfg):
    edit = _Rewrite("base_gravity", _gravity_frame, gap_s=(3.0, 4.2))
    bag = rewrite_mcap(drive_dir / "drive.mcap", tmp_path / "gap.mcap", edit)
    res = run_extract([bag], tmp_path / "gap.zarr", cfg, workers=1)
    lo, hi = min(edit.dropped_tf) - 20_000_000, max(edit.dropped_tf) + 20_000_000  # the TF stamps on either side
    for rng in ("micro", "short"):
        stamps = [_stamp(m.header) for m in _maps(drive_dir, rng)]
        inside = sum(lo < s < hi for s in stamps)
        topic = next(t for t in res.topics if t["role"] == f"map.{rng}")
        assert inside > 0 and topic["dropped"] == {"no_transform": inside}
        kept = zarr.open_group(str(tmp_path / "gap.zarr"), mode="r")[f"maps/{rng}/t_ns"][:]
        assert not np.any((kept > lo) & (kept < hi))


def _maps(drive_dir, rng):
    from rosbags.rosbag2 import Reader

    from gtgen.bag.msgdefs import typestore

    with Reader(drive_dir / "drive.mcap") as r:
        conns = [c for c in r.connections if c.topic == f"/xracer/map/{rng}"]
        return [typestore(False).deserialize_cdr(raw, c.msgtype) for c, _, raw in r.messages(connections=conns)]


def test_poses_from_tf_alone(drive_dir, drive_store, tmp_path):
    cfg = small_config(topics={"odometry": None})
    res = run_extract([drive_dir / "drive.mcap"], tmp_path / "tf.zarr", cfg, workers=1)
    assert res.poses.startswith("TF 'odom' -> 'base_link'")
    a, b = zarr.open_group(str(drive_store), mode="r"), zarr.open_group(str(tmp_path / "tf.zarr"), mode="r")
    np.testing.assert_array_equal(a["samples/t_ns"][:], b["samples/t_ns"][:])
    np.testing.assert_allclose(a["samples/pos_odom_m"][:], b["samples/pos_odom_m"][:], atol=1e-9)


def test_tf_buffer_chains_interpolates_and_refuses_to_extrapolate():
    rng = np.random.default_rng(0)
    t = np.arange(0, 1_000_000_000, 100_000_000, dtype=np.int64)  # 10 Hz
    yaw = 0.1 * np.arange(len(t))
    track = PoseTrack(t, np.column_stack([np.arange(len(t)), np.zeros(len(t)), np.zeros(len(t))]),
                      rpy_to_quat(0 * yaw, 0 * yaw, yaw), 60_000_000)
    T_base_cam = make_transform(quat_to_matrix(rpy_to_quat(0.1, -0.2, 0.3)), rng.normal(size=3))
    tf = TfBuffer({("base", "cam"): T_base_cam, ("map", "odom"): yaw_transform(1, 2, 3, 0.5)}, {("odom", "base"): track})
    q = np.array([0, 50_000_000, 450_000_000, 900_000_000, 950_000_000, 990_000_000])
    T, ok = tf.lookup("map", "cam", q)
    assert ok.tolist() == [True, True, True, True, True, False]  # 90 ms past the last pose: beyond the tolerance
    want = yaw_transform(1, 2, 3, 0.5) @ track.transforms(q[:5]) @ T_base_cam
    np.testing.assert_allclose(T[:5], want, atol=1e-12)
    Ti, ok_i = tf.lookup("cam", "map", q[:5])
    np.testing.assert_allclose(Ti, invert(want), atol=1e-12)
    assert tf.lookup("cam", "nowhere", q)[1].sum() == 0 and "no TF path" in tf.why_not("cam", "nowhere")
    # a wheel's edge connects no frame of the data: a slice need not keep it
    assert relevant_edges([("odom", "base"), ("base", "wheel")], [("base", "cam")], {"odom", "cam"}) == {("odom", "base")}


def test_a_topic_whose_frame_tf_never_connects_fails_naming_the_edge(drive_dir, tmp_path, cfg):
    def edit(topic, t, msg):
        if topic == "/xracer/map/short":
            msg.header.frame_id = "lidar_mast"  # no TF edge reaches it
        yield t, msg

    bag = rewrite_mcap(drive_dir / "drive.mcap", tmp_path / "lost.mcap", edit)
    from gtgen.errors import TopicError

    with pytest.raises(TopicError) as exc:
        run_extract([bag], tmp_path / "lost.zarr", cfg, workers=1)
    msg = str(exc.value)
    assert "/xracer/map/short" in msg and "'lidar_mast'" in msg and "no TF path" in msg and "\n" not in msg
