#!/usr/bin/env bash
# Reproduce the shipped default weights on 2 CPU cores (about 2 h including data generation).
# RUNS (default: ../runs beside the repo) holds data, checkpoints and logs — never the repo.
# Resume an interrupted run by running this script again (it passes --resume when a
# checkpoint exists).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
RUNS=${RUNS:-$here/../../runs}
mkdir -p "$RUNS"
[ -f "$RUNS/valset_kodak24.h5" ] || python "$here/make_valset.py" -o "$RUNS/valset_kodak24.h5"
[ -f "$RUNS/train_128.h5" ] || python "$here/make_trainset.py" -o "$RUNS/train_128.h5" --count 10000 --workers 2
run="$RUNS/shipped-v2"
resume=()
[ -f "$run/checkpoint.safetensors" ] && resume=(--resume)
trmd train --data "$RUNS/train_128.h5" --recipe "$here/recipe.toml" --out "$run" \
  --set "data.val_data=$RUNS/valset_kodak24.h5" "${resume[@]}"
# then: python weights_recipe/ship.py "$run/best.safetensors"
