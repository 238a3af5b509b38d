#!/usr/bin/env bash
# One check of training where users train, run as it is on a machine with a CUDA GPU:
# the paper preset for a few hundred steps in mixed precision, eval on the GPU, and the
# inference latency; prints steps/s, samples/s, peak GPU memory and eval time per sample.
# Without a GPU it runs a small CPU version of the same (tiny preset, a few steps), so CI
# keeps it working.
#
#   scripts/gpu_check.sh [DATASET]
#
# DATASET defaults to a 30 s synthetic drive built in $GPU_CHECK_OUT (default gpu_check/).
# GPU_CHECK_STEPS overrides the steps (300 on a GPU, 20 on the CPU); PYTHON the interpreter
# (default .venv/bin/python); GPU_CHECK_WEIGHTS a local torchvision efficientnet_b0 state
# dict for the paper preset's ImageNet start.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
PY=${PYTHON:-$ROOT/.venv/bin/python}
OUT=$(mkdir -p "${GPU_CHECK_OUT:-gpu_check}" && cd "${GPU_CHECK_OUT:-gpu_check}" && pwd)
DATASET=${1:-}
# no GPU driver's tool (nvidia-smi, or rocm-smi for torch's ROCm build): the CPU mode,
# without importing torch (2 s) to ask it
if { command -v nvidia-smi || command -v rocm-smi; } > /dev/null && "$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)"; then
  MODE=gpu PRESET=paper DEVICE=cuda STEPS=${GPU_CHECK_STEPS:-300}
  printf 'train: {val_every: 100, ckpt_every: 100%s}\n' "${GPU_CHECK_WEIGHTS:+, backbone_weights: $GPU_CHECK_WEIGHTS}" > "$OUT/check.yaml"
else
  MODE=cpu PRESET=tiny DEVICE=cpu STEPS=${GPU_CHECK_STEPS:-20}
  printf 'train: {val_every: 10, val_max_samples: 8}\n' > "$OUT/check.yaml"
fi
echo "gpu_check: $MODE mode ($PRESET preset, $STEPS steps on $DEVICE)"
if [ -z "$DATASET" ]; then
  DATASET=$OUT/ws/dataset.zarr
  if [ ! -d "$DATASET" ]; then
    rm -rf "$OUT/drive" "$OUT/ws"
    "$PY" -m gtgen synth "$OUT/drive" --duration 30 --format mcap --seed 3 > /dev/null
    "$PY" -m gtgen extract "$OUT/drive/drive.mcap" -o "$OUT/ws/drive.zarr" > /dev/null
    "$PY" -m gtgen fuse "$OUT/ws/drive.zarr" > /dev/null
    "$PY" -m gtgen dem-align "$OUT/ws/drive.zarr" --dem "$OUT/drive/dem" > /dev/null
  fi
fi
RUN=$OUT/runs/$PRESET
rm -rf "$RUN"
"$PY" -m gtgen train "$DATASET" --preset "$PRESET" --steps "$STEPS" --device "$DEVICE" --run-dir "$RUN" --config "$OUT/check.yaml" > "$OUT/train.txt"
"$PY" -m gtgen eval "$DATASET" --ckpt "$RUN/ckpt.pt" --split all --device "$DEVICE" -o "$OUT/eval.json" > "$OUT/eval.txt"
"$PY" "$ROOT/scripts/gpu_check.py" "$RUN" "$OUT/eval.json" "$DEVICE"
