"""Build ROS 1 and ROS 2 messages from plain values, for one bag flavour at a time, and
open the MCAP writer gtgen writes them with (``gtgen synth``, ``gtgen export mcap``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.msgdefs import typestore


class MessageFactory:
    """Message constructors of one ROS flavour (field names differ between 1 and 2)."""

    def __init__(self, ros1: bool) -> None:
        self.ros1 = ros1
        self.store = typestore(ros1)
        self.T = self.store.types

    def serialize(self, msg: object, msgtype: str) -> bytes:
        """Return the wire bytes of ``msg`` for this flavour."""
        if self.ros1:
            return bytes(self.store.serialize_ros1(msg, msgtype))
        return bytes(self.store.serialize_cdr(msg, msgtype))

    def header(self, t_ns: int, frame: str, seq: int = 0) -> object:
        stamp = self.T["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))
        if self.ros1:
            return self.T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def pose(self, p: NDArray, q: NDArray) -> object:
        return self.T["geometry_msgs/msg/Pose"](
            position=self.T["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=self.T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )

    def transform_stamped(self, t_ns: int, parent: str, child: str, p: NDArray, q: NDArray) -> object:
        tf = self.T["geometry_msgs/msg/Transform"](
            translation=self.T["geometry_msgs/msg/Vector3"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
            rotation=self.T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )
        return self.T["geometry_msgs/msg/TransformStamped"](header=self.header(t_ns, parent), child_frame_id=child, transform=tf)

    def tf_message(self, transforms: list[object]) -> object:
        return self.T["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def odometry(self, t_ns: int, frame: str, child: str, p: NDArray, q: NDArray, v: NDArray, w: NDArray, seq: int) -> object:
        cov = np.diag([0.01, 0.01, 0.02, 0.001, 0.001, 0.002]).ravel()
        V3 = self.T["geometry_msgs/msg/Vector3"]
        return self.T["nav_msgs/msg/Odometry"](
            header=self.header(t_ns, frame, seq),
            child_frame_id=child,
            pose=self.T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(p, q), covariance=cov),
            twist=self.T["geometry_msgs/msg/TwistWithCovariance"](
                twist=self.T["geometry_msgs/msg/Twist"](linear=V3(x=float(v[0]), y=float(v[1]), z=float(v[2])), angular=V3(x=float(w[0]), y=float(w[1]), z=float(w[2]))),
                covariance=cov,
            ),
        )

    def navsatfix(self, t_ns: int, frame: str, lat: float, lon: float, alt: float, cov_diag: NDArray, status: int, seq: int) -> object:
        st = self.T["sensor_msgs/msg/NavSatStatus"](status=status, service=1)
        return self.T["sensor_msgs/msg/NavSatFix"](
            header=self.header(t_ns, frame, seq),
            status=st,
            latitude=float(lat),
            longitude=float(lon),
            altitude=float(alt),
            position_covariance=np.diag(cov_diag).ravel().astype(np.float64),
            position_covariance_type=2,
        )

    def compressed_image(self, t_ns: int, frame: str, jpeg: bytes, seq: int) -> object:
        return self.T["sensor_msgs/msg/CompressedImage"](
            header=self.header(t_ns, frame, seq), format="jpeg", data=np.frombuffer(jpeg, np.uint8)
        )

    def camera_info(self, t_ns: int, frame: str, width: int, height: int, K: NDArray, seq: int, D: NDArray | None = None) -> object:
        P = np.zeros((3, 4))
        P[:, :3] = K
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        vals = (np.zeros(5) if D is None else np.asarray(D, np.float64).ravel(), K.ravel().astype(np.float64), np.eye(3).ravel(), P.ravel())
        return self.T["sensor_msgs/msg/CameraInfo"](
            header=self.header(t_ns, frame, seq),
            height=height,
            width=width,
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **dict(zip(names, vals)),
        )

    def pointcloud_xyz(self, t_ns: int, frame: str, pts: NDArray, seq: int) -> object:
        PF = self.T["sensor_msgs/msg/PointField"]
        fields = [PF(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
        data = np.ascontiguousarray(pts, dtype="<f4").view(np.uint8).ravel()
        return self.T["sensor_msgs/msg/PointCloud2"](
            header=self.header(t_ns, frame, seq), height=1, width=len(pts), fields=fields,
            is_bigendian=False, point_step=12, row_step=12 * len(pts), data=data, is_dense=True,
        )

    def pointcloud(self, t_ns: int, frame: str, points: np.ndarray, seq: int) -> object:
        """Return a PointCloud2 of a structured array ``points`` (one field per name, at its
        offset; float32 -> FLOAT32, uint16 -> UINT16, ...; padding bytes stay in point_step)."""
        kinds = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}
        PF = self.T["sensor_msgs/msg/PointField"]
        dt = points.dtype
        fields = [PF(name=n, offset=dt.fields[n][1], datatype=kinds[dt.fields[n][0].str[1:]], count=1) for n in dt.names]
        data = np.frombuffer(np.ascontiguousarray(points).tobytes(), np.uint8)
        return self.T["sensor_msgs/msg/PointCloud2"](
            header=self.header(t_ns, frame, seq), height=1, width=len(points), fields=fields,
            is_bigendian=False, point_step=dt.itemsize, row_step=dt.itemsize * len(points), data=data, is_dense=True,
        )

    def foxglove_grid(self, t_ns: int, frame: str, resolution: float, layers: dict[str, NDArray]) -> object:
        """Return a foxglove_msgs Grid (ROS 2) of square float32 layers in gtgen layout
        (axis 0 = +x from -L/2, axis 1 = +y), centred on ``frame``'s origin: cell (i, j)
        is column i, row j, as Foxglove lays a grid out from its pose along +x then +y."""
        size = next(iter(layers.values())).shape[0]
        half = 0.5 * size * resolution
        F = self.T["foxglove_msgs/msg/PackedElementField"]
        fields = [F(name=name, offset=4 * i, type=7) for i, name in enumerate(layers)]  # FLOAT32
        cells = np.stack([np.asarray(a, np.float32).T for a in layers.values()], -1)  # (row j, column i, layer)
        stamp = self.T["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))
        return self.T["foxglove_msgs/msg/Grid"](
            timestamp=stamp, frame_id=frame, pose=self.pose(np.array([-half, -half, 0.0]), np.array([0.0, 0.0, 0.0, 1.0])),
            column_count=size, cell_size=self.T["foxglove_msgs/msg/Vector2"](x=float(resolution), y=float(resolution)),
            row_stride=4 * len(layers) * size, cell_stride=4 * len(layers), fields=fields,
            data=np.frombuffer(np.ascontiguousarray(cells, "<f4").tobytes(), np.uint8),
        )

    def gridmap(
        self,
        t_ns: int,
        frame: str,
        resolution: float,
        center: NDArray,
        layers: dict[str, NDArray],
        start: tuple[int, int],
        seq: int,
    ) -> object:
        """Return a GridMap of square layers given in gtgen layout (axis 0 = +x from -L/2).

        grid_map stores index (0, 0) at the +x/+y corner in a column-major circular
        buffer; the layers are flipped, rolled by ``start`` and flattened in Fortran order.
        """
        size = next(iter(layers.values())).shape[0]
        MAD = self.T["std_msgs/msg/MultiArrayDimension"]
        layout = self.T["std_msgs/msg/MultiArrayLayout"](
            dim=[MAD(label="column_index", size=size, stride=size * size), MAD(label="row_index", size=size, stride=size)],
            data_offset=0,
        )
        arrays = []
        for arr in layers.values():
            buf = np.roll(arr[::-1, ::-1], start, axis=(0, 1))
            arrays.append(self.T["std_msgs/msg/Float32MultiArray"](layout=layout, data=np.asfortranarray(buf).ravel(order="F").astype(np.float32)))
        length = size * resolution
        pose = self.pose(np.array([center[0], center[1], 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))
        info_kw = dict(resolution=float(resolution), length_x=float(length), length_y=float(length), pose=pose)
        if self.ros1:
            info = self.T["grid_map_msgs/msg/GridMapInfo"](header=self.header(t_ns, frame, seq), **info_kw)
            return self.T["grid_map_msgs/msg/GridMap"](
                info=info, layers=list(layers), basic_layers=[next(iter(layers))], data=arrays,
                outer_start_index=start[0], inner_start_index=start[1],
            )
        info = self.T["grid_map_msgs/msg/GridMapInfo"](**info_kw)
        return self.T["grid_map_msgs/msg/GridMap"](
            header=self.header(t_ns, frame), info=info, layers=list(layers), basic_layers=[next(iter(layers))],
            data=arrays, outer_start_index=start[0], inner_start_index=start[1],
        )


def open_mcap_writer(folder: Path) -> object:
    """Return an open rosbags ROS 2 writer of MCAP storage (zstd chunks) into ``folder``
    (which must not exist); the caller adds connections, writes and closes it."""
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

    w = Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP)
    w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    w.open()
    _fast_zstd(w)
    return w


def _fast_zstd(writer: object) -> None:
    """Compress the MCAP chunks at zstd level 1 instead of rosbags' default 3: faster to
    write (the synth's main process compresses every chunk) for slightly larger files;
    any zstd reader reads them. Left as is if rosbags' writer changes shape."""
    import zstandard
    from rosbags.rosbag2.storage_mcap import McapWriter

    storage = getattr(writer, "storage", None)
    if isinstance(storage, McapWriter) and getattr(storage, "compression", "") == "zstd":
        storage.compressor = zstandard.ZstdCompressor(level=1).compress
