"""Raw lidar scans: the synthetic ray-cast rate, the seconds scans add to ``gtgen synth``
of a 30 s drive, and the bytes a scan takes in the drive store.

- ray-cast rate: rays per second of ``synth.lidar.cast`` (shared azimuth-bin profiles over
  the render raster, then 12 bisection halvings along each ray) at the default 32 beams x
  1.0 deg (11,520 rays a lidar), one core; a tick of the three lidars is 34,560 rays, at
  10 Hz 345,600 rays per drive second.
- synth: the 30 s drive at the defaults with scans (synth.scan_rate_hz 10) and without
  (0); the difference is what the scans cost (2 workers).
- extract: that drive's kept scans (every shards.scan_travel_m = 2 m of travel per lidar,
  and each sample's newest), their compressed bytes per scan and per point in
  scans/points_cm (int16 cm + zstd), against the 20 bytes a point of the published
  PointCloud2 (x, y, z, intensity float32, ring uint16).
- dem-align: the N-scan input's bytes per sample (inputs/scan_*).

Measured on a loaded machine (load 10-12 on 2 cores, so only a bound): 0.23 M rays/s at
0.4 deg (123 ms a lidar scan); alone, cProfile of one lidar scan: 31 ms at 0.4 deg, i.e.
about 0.9 M rays/s. Expected idle: about 1 M rays/s per core, 0.35 s of casting per drive
second at the defaults (10 Hz), 0.07 s at the demo's --scan-rate 2. At 0.4 deg and 10 Hz
the 30 s drive's MCAP was 733 MB (about 800 KB a scan): why the defaults thin to 1.0 deg
and the demo to 2 Hz. GTGEN_BENCH_SCAN_AZ (deg) and GTGEN_BENCH_SCAN_HZ set the scans.
"""

from __future__ import annotations

import os
import shutil
import time

import numpy as np

from _common import OUT, dir_size_mb, fresh_workspace, header, run_measured

AZ = float(os.environ.get("GTGEN_BENCH_SCAN_AZ", "1.0"))
HZ = float(os.environ.get("GTGEN_BENCH_SCAN_HZ", "10"))


def cast_rate() -> None:
    from gtgen.config import SynthConfig
    from gtgen.geometry import make_transform, quat_to_matrix, rpy_to_quat
    from gtgen.synth import lidar
    from gtgen.synth.camera import RenderRaster
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
    cfg.write_text(f"synth: {{scan_azimuth_deg: {AZ}, scan_rate_hz: {HZ}}}\n")
    off = ws / "off.yaml"
    off.write_text("synth: {scan_rate_hz: 0}\n")
    t_on, _ = run_measured(["synth", str(ws / "on"), "--duration", "30", "--format", "mcap", "--config", str(cfg)])
    t_off, _ = run_measured(["synth", str(ws / "off"), "--duration", "30", "--format", "mcap", "--config", str(off)])
    print(f"synth 30 s drive: {t_on:.1f} s with scans (3 lidars, {HZ} Hz, {AZ} deg), {t_off:.1f} s without: "
          f"+{t_on - t_off:.1f} s ({(t_on - t_off) / 30:.2f} s per drive second)")
    print(f"  bag: {dir_size_mb(ws / 'on' / 'drive.mcap'):.0f} MiB with scans, {dir_size_mb(ws / 'off' / 'drive.mcap'):.0f} MiB without")
    t_ex, _ = run_measured(["extract", str(ws / "on" / "drive.mcap"), "--config", str(cfg)], cwd=ws / "on")
    store = ws / "on" / "gtgen_ws" / "drive.zarr"
    from gtgen.storage.drive import DriveStore

    s = DriveStore(store).scans
    files = list((store / "scans" / "points_cm").glob("c.*"))
    size = sum(f.stat().st_size for f in files)
    print(f"extract: {t_ex:.1f} s; {len(s)} scans kept of {3 * 30 * HZ:.0f} published, {s.n_points.mean():.0f} points each; "
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
