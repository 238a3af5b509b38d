"""The drive store (``gtgen extract``): read by name through :class:`DriveStore`, written
through :class:`DriveWriter`. Arrays and units: ``schema.DRIVE`` and data_schema.md."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen.config import RANGES, GtgenConfig, stored_config
from gtgen.geometry import quat_to_yaw
from gtgen.storage.chunks import check_encoded_chunks, chunk_file, make_parent, place_chunk
from gtgen.storage.codecs import encode_chunk
from gtgen.storage.schema import DRIVE, MAP_LAYERS
from gtgen.storage.stores import Rows, Store, StoreWriter


@dataclass(frozen=True)
class Poses:
    """Odometry of the drive: stamps [ns], base position [m] and orientation (x, y, z, w) in odom."""

    t_ns: NDArray[np.int64]
    pos_odom_m: NDArray[np.float64]
    quat_odom_xyzw: NDArray[np.float64]


@dataclass(frozen=True)
class Fixes:
    """GNSS fixes: stamps [ns], WGS84 latitude / longitude [deg], ellipsoidal altitude [m],
    ENU variance diagonal [m^2] (NaN if unknown), NavSatStatus.status (-1: no fix)."""

    t_ns: NDArray[np.int64]
    lat_deg: NDArray[np.float64]
    lon_deg: NDArray[np.float64]
    alt_m: NDArray[np.float64]
    var_enu_m2: NDArray[np.float64]
    status: NDArray[np.int8]

    @property
    def usable(self) -> NDArray[np.bool_]:
        """Fixes with a fix and a finite position."""
        return (self.status >= 0) & np.isfinite(self.lat_deg) & np.isfinite(self.lon_deg) & np.isfinite(self.alt_m)


@dataclass(frozen=True)
class DriveSamples:
    """The drive's samples: time [ns], base pose in odom at t, travel since the start [m],
    the X-Racer map at t per range (index into ``DriveStore.maps``), image stamps (S, C)
    [ns] of the C cameras, the voxel map used (stamp, index), camera extrinsics at each
    image's stamp (S, C, 4, 4: base_link <- camera optical)."""

    t_ns: NDArray[np.int64]
    pos_odom_m: NDArray[np.float64]
    quat_odom_xyzw: NDArray[np.float64]
    distance_m: NDArray[np.float64]
    map_index: dict[str, NDArray[np.int64]]
    image_t_ns: NDArray[np.int64]
    voxel_t_ns: NDArray[np.int64]
    voxel_index: NDArray[np.int64]
    T_base_cam: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.t_ns)

    @cached_property
    def yaw_odom_rad(self) -> NDArray[np.float64]:
        """Base yaw at t in odom [rad]."""
        return quat_to_yaw(self.quat_odom_xyzw)


@dataclass
class MapStream:
    """The kept X-Racer maps of one range: stamps [ns], grid centres in odom [m], grid yaw
    in odom [rad], cell size [m]; ``layers(i)`` reads map ``i``."""

    t_ns: NDArray[np.int64]
    center_odom_m: NDArray[np.float64]
    yaw_odom_rad: NDArray[np.float64]
    z_offset_m: NDArray[np.float64]
    resolution_m: float
    _layers: tuple[Rows, Rows, Rows]

    def __len__(self) -> int:
        return len(self.t_ns)

    def layers(self, i: int) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        """Return map ``i``'s elevation (heights in odom [m]), risk and confidence grids
        (axis 0 = map x from -L/2; NaN where unknown)."""
        elev, risk, conf = (a[i] for a in self._layers)
        if self.z_offset_m[i]:
            elev += np.float32(self.z_offset_m[i])
        return elev, risk, conf


@dataclass(frozen=True)
class Scans:
    """The kept raw scans: stamps [ns], lidar (index into topics.lidar), points, travel at
    the stamp [m], sensor pose in odom at the stamp; sorted by lidar, then stamp."""

    t_ns: NDArray[np.int64]
    lidar: NDArray[np.uint8]
    n_points: NDArray[np.int64]
    distance_m: NDArray[np.float64]
    T_odom_sensor: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.t_ns)


class DriveStore(Store):
    """A complete drive store, read by name."""

    fmt = DRIVE

    @cached_property
    def config(self) -> GtgenConfig:
        """The config the drive was extracted with (its train section left out)."""
        return stored_config(self.attrs.get("config", {}), f"drive store '{self.path}'", self.fmt.config_sections)

    @property
    def bags(self) -> list[dict[str, str]]:
        """The bags read: [{path, sha256}]."""
        return list(self.attrs.get("bags") or [])

    @property
    def image_size(self) -> tuple[int, int]:
        """The box stored images fit in: width, height [px] (``image_sizes`` per camera)."""
        w, h = self.attrs["image_size"]
        return int(w), int(h)

    @property
    def cameras(self) -> list[str]:
        """Camera names in the order of the image axis."""
        return list(self.attrs.get("cameras") or [])

    @property
    def n_samples(self) -> int:
        """Samples of the drive."""
        return self.shape("samples/t_ns")[0]

    def poses(self) -> Poses:
        """Return the odometry."""
        return Poses(self.read("poses/t_ns"), self.read("poses/pos_odom_m"), self.read("poses/quat_odom_xyzw"))

    def gnss(self) -> Fixes:
        """Return the GNSS fixes."""
        return Fixes(*(self.read(f"gnss/{n}") for n in ("t_ns", "lat_deg", "lon_deg", "alt_m", "var_enu_m2", "status")))

    @cached_property
    def samples(self) -> DriveSamples:
        """The samples' times, poses and what each uses."""
        r = self.read
        return DriveSamples(r("samples/t_ns"), r("samples/pos_odom_m"), r("samples/quat_odom_xyzw"), r("samples/distance_m"),
                            {rng: r(f"samples/map_index_{rng}") for rng in RANGES}, r("samples/image_t_ns"), r("samples/voxel_t_ns"),
                            r("samples/voxel_index"), r("samples/T_base_cam"))

    def maps(self, rng: str) -> MapStream:
        """Return the kept maps of range ``rng``."""
        g = f"maps/{rng}"
        res = float(self.group[g].attrs["resolution_m"])
        return MapStream(self.read(f"{g}/t_ns"), self.read(f"{g}/center_odom_m"), self.read(f"{g}/yaw_odom_rad"),
                         self.read(f"{g}/z_offset_m"), res, tuple(self.rows(f"{g}/{n}") for n in MAP_LAYERS))  # type: ignore[arg-type]

    def jpeg(self, ks: NDArray) -> tuple[NDArray[np.uint8], NDArray[np.int64]]:
        """Return the stored JPEG files of samples ``ks`` (sorted): their zero-padded rows
        (len(ks), C, B) and lengths (len(ks), C) [bytes], C cameras."""
        return self.read("samples/jpeg", ks), self.read("samples/jpeg_nbytes", ks)

    @property
    def jpeg_capacity(self) -> int:
        """Bytes of the zero-padded row holding each stored JPEG file (B)."""
        return self.shape("samples/jpeg")[2]

    def K(self) -> NDArray[np.float64]:
        """Return the intrinsics of the cameras' stored (rectified) images (C, 3, 3) [px]."""
        return self.read("calib/K")

    def image_sizes(self) -> NDArray[np.int64]:
        """Return the (width, height) of each camera's stored images (C, 2) [px]."""
        return self.read("calib/image_size")

    def voxel_counts(self) -> NDArray[np.int64]:
        """Return the points of each stored voxel map."""
        return self.read("voxel_maps/n_points")

    def voxel_points(self, vs: NDArray) -> NDArray[np.float32]:
        """Return voxel maps ``vs`` (sorted): (len(vs), P, 3) points in odom [m], NaN-padded."""
        return self.read("voxel_maps/points_odom_m", vs)

    @cached_property
    def scans(self) -> Scans:
        """The kept raw scans (none: the drive has no lidar role)."""
        return Scans(*(self.read(f"scans/{n}") for n in ("t_ns", "lidar", "n_points", "distance_m", "T_odom_sensor")))

    def scan_rows(self, ls: NDArray) -> NDArray[np.int16]:
        """Return scans ``ls`` (sorted): (len(ls), Q, 3) int16 cm in the sensor frame,
        ``extract.lidar.FILL`` past each scan's points (``extract.lidar.expand``). Each is
        read from its chunk file (a zarr call per block cost 40 % of dem-align)."""
        ls = np.asarray(ls)
        if not len(ls):
            return self.read("scans/points_cm", ls)
        return np.stack([self._scan_files[int(k)] for k in ls])

    @cached_property
    def _scan_files(self) -> Rows:
        return self.rows("scans/points_cm")


class DriveWriter(StoreWriter):
    """A drive store being written: the small arrays whole, the images, maps and voxel
    clouds a chunk at a time (moved in as staged chunk files, or written)."""

    fmt = DRIVE

    def __init__(self, path: Path, new: bool = True) -> None:
        super().__init__(path, new)
        self._seps: dict[str, str] = {}
        self._made: set[Path] = set()

    @classmethod
    def reopen(cls, path: Path) -> DriveWriter:
        """Return the writer of a drive store being written (in another process)."""
        return cls(path, new=False)

    def write_poses(self, t_ns: NDArray, pos_odom_m: NDArray, quat_odom_xyzw: NDArray) -> None:
        """Write the odometry."""
        self.write("poses/t_ns", t_ns)
        self.write("poses/pos_odom_m", pos_odom_m)
        self.write("poses/quat_odom_xyzw", quat_odom_xyzw)

    def write_gnss(self, fixes: Fixes) -> None:
        """Write the GNSS fixes."""
        for name in ("t_ns", "lat_deg", "lon_deg", "alt_m", "var_enu_m2", "status"):
            self.write(f"gnss/{name}", getattr(fixes, name))

    def write_candidates(self, t_ns: NDArray, reason: NDArray) -> None:
        """Write the candidate sample times and why each was not kept (0: kept)."""
        self.write("candidates/t_ns", t_ns)
        self.write("candidates/reason", reason)

    def write_samples(self, s: DriveSamples, voxel_map_t_ns: NDArray, K: NDArray, image_size: NDArray) -> None:
        """Write the samples, the stamps of the voxel maps they use, the intrinsics and the
        stored image sizes."""
        for name in ("t_ns", "pos_odom_m", "quat_odom_xyzw", "distance_m", "image_t_ns", "voxel_t_ns", "voxel_index", "T_base_cam"):
            self.write(f"samples/{name}", getattr(s, name))
        for rng in RANGES:
            self.write(f"samples/map_index_{rng}", s.map_index[rng])
        self.write("voxel_maps/t_ns", voxel_map_t_ns)
        self.write("calib/K", K)
        self.write("calib/image_size", image_size)

    def create_large(self, S: int, C: int, jpeg_capacity: int, maps: dict[str, tuple[int, tuple[int, int], float, str]],
                     V: int, P: int, L: int = 0, Q: int = 1) -> None:
        """Create the image, map, voxel and raw scan arrays: S samples' images of C cameras,
        ``jpeg_capacity`` the row of bytes one stored JPEG gets; ``maps`` gives per range
        (kept maps, grid shape, cell size [m], frame); L scans of Q points. One chunk per
        image, map layer, voxel map and scan."""
        B = jpeg_capacity
        self.create("samples/jpeg", (S, C, B), chunks=(1, 1, B), flat=True)
        for r, (n, shape, res, frame) in maps.items():
            for name in MAP_LAYERS:
                self.create(f"maps/{r}/{name}", (n, *shape), chunks=(1, *shape), flat=True)
            self.root[f"maps/{r}"].attrs.update({"resolution_m": res, "shape": list(shape), "frame": frame})
        self.create("voxel_maps/points_odom_m", (V, P, 3), chunks=(1, P, 3), flat=True)
        self.create("scans/points_cm", (L, Q, 3), chunks=(1, Q, 3), flat=True)

    def put_image(self, row: NDArray[np.uint8], camera: int, samples: list[int]) -> None:
        """Write the padded JPEG ``row`` at camera index ``camera`` of ``samples`` (one
        chunk file each, as zarr would write it)."""
        path = "samples/jpeg"
        if path not in self._seps:
            self._seps[path] = check_encoded_chunks(self.root[path])[0]
        data = encode_chunk(row.reshape(1, 1, -1))
        for s in samples:
            f = chunk_file(self.path, path, (s, camera, 0), self._seps[path])
            make_parent(f, self._made)
            f.write_bytes(data)

    def map_layer(self, rng: str, layer: str) -> Any:
        """Return the zarr array of map layer ``layer`` (``schema.MAP_LAYERS``) of range ``rng``."""
        return self.root[f"maps/{rng}/{layer}"]

    def voxels(self) -> Any:
        """Return the zarr array of the voxel clouds."""
        return self.root["voxel_maps/points_odom_m"]

    def scan_array(self) -> Any:
        """Return the zarr array of the raw scans."""
        return self.root["scans/points_cm"]

    def _place(self, src: Path, path: str, coords: list[tuple[int, ...]]) -> None:
        """Make the chunks ``coords`` of ``path`` hold staged chunk file ``src`` (the last
        use takes the file, earlier ones link to it)."""
        if path not in self._seps:
            self._seps[path] = check_encoded_chunks(self.root[path])[0]
        for n, c in enumerate(coords):
            place_chunk(src, chunk_file(self.path, path, c, self._seps[path]), move=n == len(coords) - 1, made=self._made)

    def place_map(self, src: Path, rng: str, layer: str, maps: list[int]) -> None:
        """Put staged map-layer chunk ``src`` at kept maps ``maps`` of range ``rng``."""
        self._place(src, f"maps/{rng}/{layer}", [(k, 0, 0) for k in maps])

    def place_voxels(self, src: Path, vs: list[int]) -> None:
        """Put staged voxel-cloud chunk ``src`` at voxel maps ``vs``."""
        self._place(src, "voxel_maps/points_odom_m", [(v, 0, 0) for v in vs])

    def place_scan(self, src: Path, ls: list[int]) -> None:
        """Put staged scan chunk ``src`` at scans ``ls``."""
        self._place(src, "scans/points_cm", [(sc, 0, 0) for sc in ls])

    def finish_large(self, n_points: NDArray, jpeg_nbytes: NDArray, maps: dict[str, tuple[NDArray, NDArray, NDArray, NDArray]],
                     scans: Scans) -> None:
        """Write each voxel map's point count, each stored JPEG's length, per range the kept
        maps' (stamps, centres in odom, yaw in odom, height offset), and the kept scans'
        rows but their points."""
        for name in ("t_ns", "lidar", "n_points", "distance_m", "T_odom_sensor"):
            self.write(f"scans/{name}", getattr(scans, name))
        self.write("voxel_maps/n_points", n_points)
        self.write("samples/jpeg_nbytes", jpeg_nbytes)
        for r, (t, centers, yaws, z0) in maps.items():
            self.write(f"maps/{r}/t_ns", t)
            self.write(f"maps/{r}/center_odom_m", centers)
            self.write(f"maps/{r}/yaw_odom_rad", yaws)
            self.write(f"maps/{r}/z_offset_m", z0)
