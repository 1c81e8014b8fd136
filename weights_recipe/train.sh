#!/usr/bin/env bash
# Reproduce the shipped default weights on 2 CPU cores (about 2 h 40 min including data).
# RUNS (default: ../runs beside the repo) holds data, checkpoints and logs — never the repo.
# Run the script again to resume: each stage passes --resume when its checkpoint exists, and
# a finished stage (final.safetensors written) is skipped.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
RUNS=${RUNS:-$here/../../runs}
mkdir -p "$RUNS"
val="$RUNS/valset_kodak24.h5"
main="$RUNS/train_128.h5"
hard="$RUNS/train_128_hard.h5"
[ -f "$val" ] || python "$here/make_valset.py" -o "$val"
[ -f "$main" ] || python "$here/make_trainset.py" -o "$main" --count 10000 --workers 2
# more blur than the main set: larger motion, more detail per pixel (≈ 48 min on 2 cores)
[ -f "$hard" ] || python "$here/make_trainset.py" -o "$hard" --count 6000 --workers 2 \
  --seed 2 --motion-px 100 --zoom 1.5 3.0

stage() {  # stage NAME RECIPE ARGS…: train unless finished, resuming when possible
  local run="$RUNS/$1" recipe="$2"
  shift 2
  [ -f "$run/final.safetensors" ] && return 0
  if [ -f "$run/checkpoint.safetensors" ]; then
    trmd train --out "$run" --resume  # the run keeps its own recipe and data
  else
    trmd train --recipe "$recipe" --out "$run" --set "data.val_data=$val" "$@"
  fi
}

# stage 1: from scratch on the main set, stopped by its 60-minute budget at a high rate
stage shipped-v2-stage1 "$here/recipe_stage1.toml" --data "$main"
# stage 2: fine-tune stage 1's weights on the heavier-blur set (A/B round 2)
stage shipped-v2 "$here/recipe_stage2.toml" --data "$hard" \
  --init-weights "$RUNS/shipped-v2-stage1/checkpoint.safetensors"
# stage 3: the ladder around a given c (A/B round 3), both sets, a fresh cosine and a weight
# average (85 min)
stage shipped-v3 "$here/recipe.toml" --data "$main" --data "$hard" \
  --init-weights "$RUNS/shipped-v2/checkpoint.safetensors"
# then: python weights_recipe/ship.py "$RUNS/shipped-v3/final.safetensors" --valset "$val"
