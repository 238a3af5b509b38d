"""Extract speed against merely iterating the bag with rosbags, against real time; RSS 1x vs 4x."""

from __future__ import annotations

from _common import drive, fresh_workspace, header, run_measured

ITERATE = """
import sys
from rosbags.highlevel import AnyReader
from pathlib import Path
from gtgen.bag.msgdefs import typestore
with AnyReader([Path(sys.argv[1])], default_typestore=typestore(False)) as r:
    for c, t, raw in r.messages():
        r.deserialize(raw, c.msgtype)
"""

if __name__ == "__main__":
    header("bench/extract.py")
    rss = {}
    for dur in (30, 60, 120):  # 60 s is the default synth duration
        d = drive(dur)
        ws = fresh_workspace(f"ws_extract_{dur}")
        t_ex, rss[dur] = run_measured(["extract", str(d / "drive.mcap"), "-o", str(ws / "drive.zarr")])
        t_it, _ = run_measured(["-c", ITERATE.replace("sys.argv[1]", repr(str(d / "drive.mcap")))])
        print(f"{dur:4d} s drive: extract {t_ex:.1f} s; rosbags iterate+deserialize {t_it:.1f} s; "
              f"extract / iterate = {t_ex / t_it:.2f}x; faster than real time: {dur / t_ex:.1f}x (goal >= 10x); peak RSS {rss[dur]:.0f} MiB")
    print(f"peak RSS ratio 4x / 1x duration: {rss[120] / rss[30]:.2f} (goal <= 1.2)")
