"""``gtgen export mcap``: the dataset as one ROS 2 MCAP recording that Foxglove plays.

Per sample, stamped at its time (``meta/t_ns``), in drive and time order:

- ``/tf``: ``map -> target`` (the sample's placement after ICP, ``meta/T_crs_target``,
  with ``map`` the drive's working CRS shifted to its first sample so that coordinates
  stay small; a drive without a DEM: its odom frame, shifted alike), ``target -> base_link`` (``inputs/T_target_base``) and
  ``base_link -> camera_<name>`` (``inputs/T_base_cam``);
- ``/gtgen/labels/<range>``: ``grid_map_msgs/GridMap`` in ``target`` with the layers
  ``elevation``, ``risk``, ``region`` and, where the dataset keeps the QA grids
  (``shards.qa_ranges``), ``confidence``, ``count``, ``last_dt_s`` and ``dem_elevation``
  (the aligned DEM), heights relative to the base at t as in the dataset;
- ``/gtgen/xracer/<range>``: the X-Racer map at t (``elevation``, ``risk``, and
  ``confidence`` with the QA grids), same frame;
- ``/gtgen/labels/<range>/grid``: the labels as ``foxglove_msgs/Grid`` (``elevation``,
  ``risk``, ``region``), which Foxglove's 3D panel colours without a plugin;
- ``/gtgen/camera_<name>/image/compressed``: the stored JPEG file as it is (rectified),
  and ``.../camera_info`` with the stored intrinsics and no distortion;
- ``/gtgen/voxel_points``: the sample's voxel-map points as ``sensor_msgs/PointCloud2``
  in ``target``.

The file is written with rosbags' MCAP writer (zstd chunks), schemas included, so it
plays without the message packages installed; its rosbag2 metadata carries gtgen's
signature (``custom_data.written_by``), so a later export may replace it.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.image import file_size
from gtgen.config import RANGES
from gtgen.errors import GtgenError
from gtgen.geometry import matrix_to_quat, yaw_transform
from gtgen.runtime.output import signature, stage_output, temporary
from gtgen.runtime.progress import track
from gtgen.storage.dataset import DatasetStore, jpeg_files

LABEL_LAYERS = {"elevation": "elevation_m", "risk": "risk", "confidence": "confidence", "region": "region",
                "count": "count", "last_dt_s": "last_dt_s"}
XRACER_LAYERS = {"elevation": "elevation_m", "risk": "risk", "confidence": "confidence"}
GRID_LAYERS = ("elevation", "risk", "region")
BLOCK = 16  # samples read at once: bounded memory whatever the dataset's length


@dataclass
class McapExport:
    """What an MCAP export wrote: the file, samples, and messages per topic."""

    out: Path
    samples: int = 0
    counts: dict[str, int] = field(default_factory=dict)


class _Topics:
    """Connections created on first use; counts what was written."""

    def __init__(self, writer: object, store: object) -> None:
        self.w, self.store = writer, store
        self.conns: dict[str, object] = {}
        self.counts: dict[str, int] = {}

    def write(self, topic: str, msgtype: str, t_ns: int, blob: bytes) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.w.add_connection(topic, msgtype, typestore=self.store)  # type: ignore[attr-defined]
        self.w.write(self.conns[topic], int(t_ns), blob)  # type: ignore[attr-defined]
        self.counts[topic] = self.counts.get(topic, 0) + 1


def export_mcap(dataset: Path, out: Path, overwrite: bool = False) -> McapExport:
    """Write ``dataset`` as the ROS 2 MCAP file ``out`` (atomically)."""
    from gtgen.bag.messages import MessageFactory, open_mcap_writer

    ds = DatasetStore(dataset)
    if ds.n_samples == 0:
        raise GtgenError(f"dataset '{dataset}' has no samples; nothing to export")
    if out.suffix != ".mcap":
        raise GtgenError(f"output '{out}' must be a file ending in .mcap")
    cfg = ds.config
    cams = ds.cameras
    t_ns, drive, T = ds.meta("t_ns"), ds.meta("drive"), _map_poses(ds)
    order = np.lexsort((t_ns, drive))
    origin = {int(d): T[order[np.nonzero(drive[order] == d)[0][0]], :3, 3].copy() for d in np.unique(drive)}
    offsets = ds.voxel_offsets()
    points = ds.voxel_points()
    fac = MessageFactory(ros1=False)
    res = McapExport(out)
    # rosbags writes a recording folder; it lies beside the output (the same file system, so
    # the file moves by a rename) under a temporary name of this run (runtime/output.py)
    with stage_output(out, reads=[dataset], overwrite=overwrite, file=True) as tmp, temporary(out) as scratch:
        scratch.mkdir()
        w = open_mcap_writer(scratch / "bag")
        w.set_custom_data("written_by", signature())  # type: ignore[attr-defined]
        topics = _Topics(w, fac.store)
        try:
            for a in track(range(0, len(order), BLOCK), "export mcap", total=(len(order) + BLOCK - 1) // BLOCK):
                ks = np.sort(order[a:a + BLOCK])  # read one block in index order, write in time order
                block = _read_block(ds, ks)
                for k in order[a:a + BLOCK]:
                    T_map = T[k].copy()
                    T_map[:3, 3] -= origin[int(drive[k])]
                    _write_sample(fac, topics, block, int(np.searchsorted(ks, k)), int(k), int(t_ns[k]), T_map, cams, cfg, points, offsets)
        finally:
            w.close()  # type: ignore[attr-defined]
        shutil.move(str(next((scratch / "bag").glob("*.mcap"))), tmp)
    res.samples = len(order)
    res.counts = dict(sorted(topics.counts.items()))
    return res


def _map_poses(ds: DatasetStore) -> NDArray[np.float64]:
    """Return every sample's T_map_target before the drive's shift: its placement in the
    working CRS, or for a sample without one (a drive without a DEM) its pose in odom."""
    T = ds.meta("T_crs_target").copy()
    unplaced = ~np.isfinite(T).all(axis=(1, 2))
    if unplaced.any():
        pos, yaw = ds.meta("pos_odom_m")[unplaced], ds.meta("yaw_odom_rad")[unplaced]
        T[unplaced] = [yaw_transform(*p, y) for p, y in zip(pos, yaw)]
    return T


def _read_block(ds: DatasetStore, ks: NDArray) -> dict:
    """Read the grids and inputs a block of samples needs (``ks`` ascending), keyed
    (kind, range, layer) and by input name."""
    want = [("labels", r, v) for r in RANGES for v in LABEL_LAYERS.values()]
    want += [("xracer", r, v) for r in RANGES for v in XRACER_LAYERS.values()] + [("dem", r, "elevation_m") for r in RANGES]
    out: dict = {(kind, r, v): ds.grids(kind, r, v, ks) for kind, r, v in want if ds.has_grid(kind, r, v)}  # QA grids: with shards.qa_ranges
    out.update({n: ds.input_rows(n, ks) for n in ("T_target_base",) + (("jpeg", "jpeg_nbytes", "K", "T_base_cam") if ds.cameras else ())})
    return out


def _tf(fac: object, t: int, parent: str, child: str, T: NDArray) -> object:
    return fac.transform_stamped(t, parent, child, T[:3, 3], matrix_to_quat(T[:3, :3]))  # type: ignore[attr-defined]


def _write_sample(fac, topics: _Topics, block: dict, i: int, k: int, t: int, T_map_target: NDArray,
                  cams: list[str], cfg, points: Callable[[int, int], NDArray], offsets: NDArray) -> None:
    """Write sample ``k`` (row ``i`` of ``block``) at stamp ``t``."""
    tfs = [_tf(fac, t, "map", "target", T_map_target), _tf(fac, t, "target", "base_link", block["T_target_base"][i])]
    tfs += [_tf(fac, t, "base_link", f"camera_{c}", block["T_base_cam"][i, ci]) for ci, c in enumerate(cams)]
    topics.write("/tf", "tf2_msgs/msg/TFMessage", t, fac.serialize(fac.tf_message(tfs), "tf2_msgs/msg/TFMessage"))
    for r in RANGES:
        gr = cfg.grids.get(r)
        layers = {name: block[("labels", r, v)][i].astype(np.float32) for name, v in LABEL_LAYERS.items() if ("labels", r, v) in block}
        if ("dem", r, "elevation_m") in block:
            layers["dem_elevation"] = block[("dem", r, "elevation_m")][i].astype(np.float32)
        msg = fac.gridmap(t, "target", gr.resolution_m, np.zeros(2), layers, (0, 0), k)
        topics.write(f"/gtgen/labels/{r}", "grid_map_msgs/msg/GridMap", t, fac.serialize(msg, "grid_map_msgs/msg/GridMap"))
        xr = {name: block[("xracer", r, v)][i].astype(np.float32) for name, v in XRACER_LAYERS.items() if ("xracer", r, v) in block}
        msg = fac.gridmap(t, "target", gr.resolution_m, np.zeros(2), xr, (0, 0), k)
        topics.write(f"/gtgen/xracer/{r}", "grid_map_msgs/msg/GridMap", t, fac.serialize(msg, "grid_map_msgs/msg/GridMap"))
        grid = fac.foxglove_grid(t, "target", gr.resolution_m, {n: layers[n] for n in GRID_LAYERS})
        topics.write(f"/gtgen/labels/{r}/grid", "foxglove_msgs/msg/Grid", t, fac.serialize(grid, "foxglove_msgs/msg/Grid"))
    for ci, (c, jpeg) in enumerate(zip(cams, jpeg_files(block["jpeg"][i], block["jpeg_nbytes"][i]) if cams else [])):
        msg = fac.compressed_image(t, f"camera_{c}", jpeg, k)  # the stored JPEG as it is
        topics.write(f"/gtgen/camera_{c}/image/compressed", "sensor_msgs/msg/CompressedImage", t,
                     fac.serialize(msg, "sensor_msgs/msg/CompressedImage"))
        msg = fac.camera_info(t, f"camera_{c}", *file_size(jpeg), block["K"][i, ci], k)
        topics.write(f"/gtgen/camera_{c}/camera_info", "sensor_msgs/msg/CameraInfo", t, fac.serialize(msg, "sensor_msgs/msg/CameraInfo"))
    pts = points(int(offsets[k]), int(offsets[k + 1]))
    msg = fac.pointcloud_xyz(t, "target", pts, k)
    topics.write("/gtgen/voxel_points", "sensor_msgs/msg/PointCloud2", t, fac.serialize(msg, "sensor_msgs/msg/PointCloud2"))
