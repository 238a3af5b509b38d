"""Map one raw lidar scan of a bag that has no poses and draw its layers (ground, top,
risk, confidence per range) into a PNG: a quick look at what gtgen.mapping makes of a
sensor before a whole drive is extracted.

    python scripts/map_scan.py ../shared/realdata/swri_hdl64_single_scan.bag \
        --origin 429.1 -1226.2 0 --sensor-height 1.8 -o hdl64.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from gtgen.bag.decode.pointcloud import decode_pointcloud
from gtgen.bag.reader import BagSet
from gtgen.config import load_config
from gtgen.errors import GtgenError
from gtgen.mapping.mapper import map_scan


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--topic", help="PointCloud2 topic (default: the bag's first)")
    ap.add_argument("--origin", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"), help="the sensor's position in the cloud's frame [m]")
    ap.add_argument("--sensor-height", type=float, default=1.8, help="the sensor above the vehicle's base [m]")
    ap.add_argument("--config", type=Path, help="gtgen config (grids, mapping)")
    ap.add_argument("-o", "--out", type=Path, default=Path("scan_map.png"))
    a = ap.parse_args()
    try:
        cfg = load_config(a.config)
        with BagSet([a.bag]) as bags:
            topics = [t for t, i in bags.topics().items() if i.msgtype == "sensor_msgs/msg/PointCloud2"]
            topic = a.topic or (topics[0] if topics else None)
            if topic not in topics:
                raise GtgenError(f"PointCloud2 topic {topic!r} not in {a.bag}; found: {topics}")
            msg = next(m for _, _, _, m, _ in bags.messages([topic]) if m is not None)
        pts = decode_pointcloud(msg)
        maps = map_scan(pts, np.array(a.origin), a.sensor_height, cfg)
    except (GtgenError, StopIteration) as err:
        print(f"error: {err or 'no decodable message'}", file=sys.stderr)
        return 1
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 4, figsize=(16, 8), constrained_layout=True)
    for row, (r, lay) in enumerate(maps.items()):
        half = 0.5 * lay.elevation.shape[0] * cfg.grids.get(r).resolution_m
        ext = (-half, half, -half, half)
        base_z = a.origin[2] - a.sensor_height
        for col, (name, arr, cmap, lim) in enumerate((("ground - base [m]", lay.elevation - base_z, "terrain", (-2, 3)),
                                                      ("top - ground [m]", lay.top - lay.elevation, "viridis", (0, 3)),
                                                      ("risk", lay.risk, "RdYlGn_r", (0, 1)), ("confidence", lay.confidence, "gray", (0, 1)))):
            im = ax[row, col].imshow(arr.T, origin="lower", extent=ext, cmap=cmap, vmin=lim[0], vmax=lim[1])
            ax[row, col].set_title(f"{r}: {name}")
            fig.colorbar(im, ax=ax[row, col], shrink=0.8)
    fig.suptitle(f"{a.bag.name} {topic}: {len(pts)} points, one scan mapped at the sensor (x right, y up, metres from it)")
    fig.savefig(a.out, dpi=80)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
