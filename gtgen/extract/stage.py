"""Staging: the single pass keeps what the plan will likely want.

The plan (sample times, kept maps) needs every stamp of the drive, so it exists only
once all slices are read. Rather than read the bags a second time, each slice stages
what the plan will likely keep while it reads: every image, every voxel cloud and raw scan, the
earliest map of each thinning period and, for each frame of the reference sensor (a
sample time is always one: ``extract.reference``), the latest map stamped at or before it. Maps and voxel clouds are
written as the encoded chunk files they will be in the store
(``storage.codecs.encode_chunk``), and once the plan exists the kept ones are moved into
place by rename; images are kept as the camera sent them (``extract.images``: their
stored form needs the CameraInfo, which may come later) and converted on the pool once
the plan exists; anything the plan wants but no
slice staged (stamps far out of record order) is read in a second, targeted pass. The
store does not depend on what was staged.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.bag.decode.gridmap import decode_gridmap
from gtgen.config import RANGES, GtgenConfig
from gtgen.extract.images import Source, write_source
from gtgen.extract.lidar import compact
from gtgen.extract.voxels import padded, thinned_points
from gtgen.runtime.pool import BackgroundWrites
from gtgen.storage.chunks import make_parent
from gtgen.storage.codecs import encode_chunk
from gtgen.storage.schema import DRIVE, MAP_LAYERS

STAGE = "stage"  # folder of the partial store holding staged chunks; removed before the store completes


def period_ns(cfg: GtgenConfig) -> int:
    return int(1e9 / cfg.extract.map_rate_hz)


@dataclass
class Staged:
    """What one slice staged: the slice ordinals staged per role (chunk files named by
    ordinal), map poses as stamped (frames resolved later), voxel point counts (voxel
    maps in frames other than odom are kept raw in .npy files, for the TF buffer to place)."""

    k: int
    dir: str
    ordinals: dict[str, set[int]] = field(default_factory=lambda: defaultdict(set))
    map_pose: dict[tuple[str, int], tuple[NDArray, float, str]] = field(default_factory=dict)
    map_shape: dict[str, tuple[int, int]] = field(default_factory=dict)
    voxels: dict[int, tuple[int, int, str]] = field(default_factory=dict)  # ordinal -> (points, stamp, frame); -1 points: raw .npy
    scans: dict[tuple[str, int], tuple[int, NDArray]] = field(default_factory=dict)  # (lidar role, ordinal) -> (points, row origin shift); -1 points: raw .npy (to deskew)

    def chunk(self, role: str, i: int, layer: str = "") -> Path:
        """Return the staged chunk file of message ``i`` of ``role`` (map layer ``layer``)."""
        return Path(self.dir) / (f"{role}.{layer}" if layer else role) / str(i)

    def image(self, role: str, i: int) -> Path:
        """Return the file of staged frame ``i`` of camera ``role`` (``extract.images.write_source``)."""
        f = Path(self.dir) / role / str(i)
        return f if f.exists() else f.with_name(f"{i}.npy")

    def raw_voxels(self, i: int) -> Path:
        """Return the .npy file of voxel map ``i`` staged in its own frame (base_link)."""
        return Path(self.dir) / "voxel_map.raw" / f"{i}.npy"

    def raw_scan(self, role: str, i: int) -> Path:
        """Return the .npy file of scan ``i`` of ``role`` staged with its per-point times
        (x, y, z [m], dt [s]): motion-corrected once the TF buffer is known."""
        return Path(self.dir) / f"{role}.raw" / f"{i}.npy"


class Stager:
    """Stages images, voxel clouds and likely maps of one slice as encoded chunk files in
    ``<store>/stage/<k>`` (written on threads)."""

    def __init__(self, store: str, k: int, cfg: GtgenConfig, reference: str) -> None:
        self.cfg = cfg
        self.reference = reference  # the role whose stamps are the sample times
        self.result = Staged(k, str(Path(store) / STAGE / str(k)))
        tp = cfg.topics
        self.layer_names = [tp.layers.elevation, tp.layers.risk, tp.layers.confidence]
        self.period = period_ns(cfg)
        self.bin_first: dict[str, dict[int, int]] = defaultdict(dict)  # role -> {period: earliest stamp staged}
        self.held: dict[str, list[tuple[int, int, object]]] = defaultdict(list)  # role -> [(stamp, ordinal, msg)]
        self.pending: dict[str, list[int]] = defaultdict(list)  # role -> reference stamps awaiting their map
        self.made: set[Path] = set()

    def __enter__(self) -> Stager:
        self.writes = BackgroundWrites().__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            if exc[0] is None:
                for role in list(self.held):
                    for h in self.held[role]:  # the next slice's first frames may want them
                        self._stage_map(role, h)
        finally:
            self.writes.__exit__(*exc)

    def _write(self, file: Path, value: NDArray, codec: str = "zstd") -> None:
        make_parent(file, self.made)
        self.writes.submit(lambda: file.write_bytes(encode_chunk(value, codec)))

    def add_image(self, role: str, i: int, t: int, src: Source) -> None:
        """Stage frame ``i`` (slice ordinal) of camera ``role`` stamped ``t`` as it came."""
        file = self.result.chunk(role, i)
        make_parent(file, self.made)
        self.writes.submit(write_source, file, src)
        self.result.ordinals[role].add(i)
        if role == self.reference:
            self._sample_time(t)

    def _sample_time(self, t: int) -> None:
        """A reference frame at ``t``: a sample may be there, and want each range's map at t."""
        for r in RANGES:
            self.pending[f"map.{r}"].append(t)
            self._resolve(f"map.{r}")

    def add_voxels(self, i: int, t: int, pts: NDArray[np.float32], frame: str) -> None:
        """Stage voxel map ``i`` (slice ordinal) stamped ``t``: its points in ``frame``."""
        if frame not in ("", self.cfg.topics.odom_frame):  # to odom once the whole TF buffer is known
            f = self.result.raw_voxels(i)
            make_parent(f, self.made)
            np.save(f, pts)
            self.result.voxels[i] = (-1, t, frame)
            return
        pts = thinned_points(pts, self.cfg.shards.max_voxel_points, self.cfg.shards.far_voxel_m)
        self._write(self.result.chunk("voxel_map", i), padded(pts, self.cfg.shards.max_voxel_points))
        self.result.voxels[i] = (len(pts), t, frame)

    def add_scan(self, role: str, i: int, t: int, pts: NDArray[np.float32], dt_s: NDArray[np.float32] | None) -> None:
        """Stage raw scan ``i`` (slice ordinal) of lidar ``role`` stamped ``t``: its points in
        its sensor frame, and each point's time after the stamp [s] if the cloud has them."""
        if role == self.reference:
            self._sample_time(t)
        if dt_s is not None and len(dt_s) and float(np.ptp(dt_s)) > 0:
            f = self.result.raw_scan(role, i)
            make_parent(f, self.made)
            np.save(f, np.column_stack([pts, dt_s]).astype(np.float32))
            self.result.scans[(role, i)] = (-1, np.zeros(3))
            return
        row, n, shift = compact(pts, self.cfg.extract.max_scan_points)
        self._write(self.result.chunk(role, i), row)
        self.result.scans[(role, i)] = (n, shift)

    def add_map(self, role: str, i: int, t: int, msg: object, ok: bool) -> None:
        """Take GridMap ``i`` (slice ordinal) of ``role`` stamped ``t``; ``ok`` is False for
        a map the plan cannot use."""
        if not ok:
            return
        b = t // self.period
        if t < self.bin_first[role].get(b, t + 1):
            self.bin_first[role][b] = t
            self._stage_map(role, (t, i, msg))
        self.held[role].append((t, i, msg))
        self._resolve(role)

    def _resolve(self, role: str) -> None:
        """Stage, for each reference frame older than the newest map, the latest map stamped at
        or before it; keep held only the maps a later frame may still want."""
        held = self.held[role]
        if not held:
            return
        newest = max(h[0] for h in held)
        still = []
        for tf in self.pending[role]:
            if tf < newest:
                before = [h for h in held if h[0] <= tf]
                if before:
                    self._stage_map(role, max(before, key=lambda h: h[0]))
            else:
                still.append(tf)
        self.pending[role] = still
        m = min(still) if still else newest
        floor = max((h[0] for h in held if h[0] <= m), default=min(h[0] for h in held))
        self.held[role] = [h for h in held if h[0] >= floor]

    def _stage_map(self, role: str, h: tuple[int, int, object]) -> None:
        _, i, msg = h
        if i in self.result.ordinals[role]:
            return
        g = decode_gridmap(msg, self.layer_names)  # it decodes: the scan checked it
        if g.shape != self.result.map_shape.setdefault(role, g.shape):
            return  # a size change: the targeted pass reports it if the plan wants this map
        rng = role.split(".")[1]
        for name, layer in zip(MAP_LAYERS, self.layer_names):
            self._write(self.result.chunk(role, i, name), g.layers[layer], DRIVE.spec(f"maps/{rng}/{name}").codec)
        self.result.ordinals[role].add(i)
        self.result.map_pose[(role, i)] = (g.center_m, g.yaw_rad, g.frame_id)
