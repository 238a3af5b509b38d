"""Raw lidar scans: the synthetic ray-cast rate, the seconds scans add to ``gtgen synth``
of a 30 s drive, and the bytes a scan takes in the drive store.

- ray-cast rate: rays per second of ``synth.lidar.cast`` (march over the render raster,
  8 bisection halvings) at the default 32 beams x 0.4 deg (28,800 rays a lidar), one
  core; a tick of the three lidars is 86,400 rays, at 10 Hz 864,000 rays per drive second.
- synth: the 30 s drive at the defaults with scans (synth.scan_rate_hz 10) and without
  (0); the difference is what the scans cost (2 workers).
- extract: that drive's kept scans (every shards.scan_travel_m = 2 m of travel per lidar,
  and each sample's newest), their compressed bytes per scan and per point in
  scans/points_cm (int16 cm + zstd), against the 20 bytes a point of the published
  PointCloud2 (x, y, z, intensity float32, ring uint16).
- dem-align: the N-scan input's bytes per sample (inputs/scan_*).

Expected on an idle 2-core machine: a few million rays/s per core; scans add well under
the drive's duration to synth (demo: 120 s drive). Set GTGEN_BENCH_SCAN_AZ (deg) to
measure a thinner scan (the demo may use synth.scan_azimuth_deg 0.8 if 0.4 is too slow).
"""

from __future__ import annotations

import os
import shutil
import time

import numpy as np

from _common import OUT, dir_size_mb, fresh_workspace, header, run_measured

AZ = float(os.environ.get("GTGEN_BENCH_SCAN_AZ", "0.4"))


def cast_rate() -> None:
    from gtgen.config import SynthConfig
    from gtgen.geometry import make_transform, quat_to_matrix, rpy_to_quat
    from gtgen.synth import lidar
    from gtgen.synth.sensors import RenderRaster
    from gtgen.synth.world import SynthWorld

    sc = SynthConfig(duration_s=30, scan_azimuth_deg=AZ)
    world = SynthWorld(sc)
    raster = RenderRaster(world.terrain, world.bounds)
    rays, _ = lidar.beam_rays(sc)
    n, t0 = 0, time.perf_counter()
    for k in range(0, len(world.t_ns), len(world.t_ns) // 10):
        T_wb = make_transform(quat_to_matrix(rpy_to_quat(*world.poses.rpy[k])), world.poses.pos[k])
        for name in lidar.MOUNTS:
            hits = lidar.cast(raster, T_wb @ lidar.T_base_lidar(name), rays, sc.scan_range_m)
            n += len(rays)
    dt = time.perf_counter() - t0
    print(f"ray cast: {n} rays in {dt:.2f} s = {n / dt / 1e6:.2f} M rays/s (one core); {len(rays)} rays a lidar, "
          f"{dt / (n / len(rays)) * 1e3:.0f} ms a scan; last scan {np.isfinite(hits.range_m).mean():.0%} returns")


if __name__ == "__main__":
    header("bench/lidar.py")
    cast_rate()
    ws = fresh_workspace("lidar")
    cfg = ws / "az.yaml"
    cfg.write_text(f"synth: {{scan_azimuth_deg: {AZ}}}\n")
    off = ws / "off.yaml"
    off.write_text("synth: {scan_rate_hz: 0}\n")
    t_on, _ = run_measured(["synth", str(ws / "on"), "--duration", "30", "--format", "mcap", "--config", str(cfg)])
    t_off, _ = run_measured(["synth", str(ws / "off"), "--duration", "30", "--format", "mcap", "--config", str(off)])
    print(f"synth 30 s drive: {t_on:.1f} s with scans (3 lidars, 10 Hz, {AZ} deg), {t_off:.1f} s without: "
          f"+{t_on - t_off:.1f} s ({(t_on - t_off) / 30:.2f} s per drive second)")
    print(f"  bag: {dir_size_mb(ws / 'on' / 'drive.mcap'):.0f} MiB with scans, {dir_size_mb(ws / 'off' / 'drive.mcap'):.0f} MiB without")
    t_ex, _ = run_measured(["extract", str(ws / "on" / "drive.mcap"), "--config", str(cfg)], cwd=ws / "on")
    store = ws / "on" / "gtgen_ws" / "drive.zarr"
    from gtgen.storage.drive import DriveStore

    s = DriveStore(store).scans
    files = list((store / "scans" / "points_cm").glob("c.*"))
    size = sum(f.stat().st_size for f in files)
    print(f"extract: {t_ex:.1f} s; {len(s)} scans kept of {3 * 30 * 10} published, {s.n_points.mean():.0f} points each; "
          f"{size / len(s) / 1024:.1f} KiB per scan = {size / s.n_points.sum():.2f} bytes per point "
          f"(int16 raw 6, PointCloud2 20)")
    t_fu, _ = run_measured(["fuse", "--config", str(cfg)], cwd=ws / "on")
    t_da, _ = run_measured(["dem-align", "--config", str(cfg)], cwd=ws / "on")
    ds = ws / "on" / "gtgen_ws" / "dataset.zarr"
    from gtgen.storage.dataset import DatasetStore

    n = DatasetStore(ds).n_samples
    sz = sum(dir_size_mb(ds / "inputs" / a) for a in ("scan_points_m", "scan_counts"))
    print(f"dem-align: {t_da:.1f} s; N-scan input {sz * 1024 / max(n, 1):.0f} KiB per sample over {n} samples")
    shutil.rmtree(OUT / "lidar", ignore_errors=True)
