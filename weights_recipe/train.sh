#!/usr/bin/env bash
# Reproduce the shipped default weights on 2 CPU cores (about 7 h including data).
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
# bright frames, short exposures, little read noise (≈ 12 min on 2 cores): the two sets above
# draw gains 0.25–1 and exposures 10–100 ms, skewed towards dark, noisy frames
bright="$RUNS/train_128_bright.h5"
bright2="$RUNS/train_128_bright2.h5"
brightargs=(--workers 2 --exposure-ms 10 40 --gain 0.6 1.0 --read-noise 0 0.005)
[ -f "$bright" ] || python "$here/make_trainset.py" -o "$bright" --count 4000 --seed 3 "${brightargs[@]}"
[ -f "$bright2" ] || python "$here/make_trainset.py" -o "$bright2" --count 6000 --seed 4 "${brightargs[@]}"

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
stage shipped-v3 "$here/recipe_stage3.toml" --data "$main" --data "$hard" \
  --init-weights "$RUNS/shipped-v2/checkpoint.safetensors"
# stage 4: grow the full-resolution refinement (trmd_small_edi_c_fr) from stage 3's weights;
# stopped after 2,000 steps of its 6,500-step cosine (stage 5 continues from there)
at_step() {  # the step of a run's checkpoint, 0 when there is none
  [ -f "$1/checkpoint.safetensors" ] || { echo 0; return; }
  python -c "import sys; from trmd_cli.train.checkpoint import read_checkpoint_state as r; \
print(r(sys.argv[1])['step'])" "$1/checkpoint.safetensors"
}
s4="$RUNS/shipped-v4"
done4=$(at_step "$s4")
if [ ! -f "$RUNS/shipped-v5/final.safetensors" ] && [ "$done4" -lt 2000 ]; then
  if [ "$done4" -gt 0 ]; then
    trmd train --out "$s4" --resume --stop-after $((2000 - done4))
  else
    trmd train --recipe "$here/recipe_stage4.toml" --out "$s4" --set "data.val_data=$val" \
      --data "$main" --data "$hard" --init-weights "$RUNS/shipped-v3/checkpoint.safetensors" \
      --stop-after 2000
  fi
fi
all=(--data "$main" --data "$hard" --data "$bright" --data "$bright2")
# stage 5: all four sets, a fresh cosine (75 min)
stage shipped-v5 "$here/recipe_stage5.toml" "${all[@]}" --init-weights "$s4/checkpoint.safetensors"
# stage 6: grow the sub-bin timing inputs (trmd_small_edi_c_fr_t) from stage 5's final weights,
# 3,000 steps of a fresh cosine from 1e-4 (45 min): the shipped weights
stage s6-timing "$here/recipe.toml" "${all[@]}" --init-weights "$RUNS/shipped-v5/final.safetensors"
# then: python weights_recipe/ship.py "$RUNS/s6-timing/final.safetensors" --valset "$val"
