#!/usr/bin/env bash
# The main job end to end on a synthetic drive, in the folder given (default demo/),
# using exactly the user's verbatim commands inside one workspace folder.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
OUT=${1:-demo}
GT="$ROOT/.venv/bin/gtgen"
rm -rf "$OUT" && mkdir -p "$OUT"
cd "$OUT"
"$GT" synth drive --duration 120 --format mcap --seed 7 --scan-rate 2
"$GT" extract drive/drive.mcap
"$GT" fuse --window 60
"$GT" dem-align
"$GT" report
"$GT" viz --sample 5 -o sample5.png
"$GT" train --preset tiny
"$GT" eval --ckpt runs/latest/ckpt.pt --viz 5
echo "demo: outputs in $OUT/ (figures: $OUT/report/*.png, $OUT/sample5.png, predictions: $OUT/runs/tiny/pred_5.png)"
