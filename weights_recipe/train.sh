#!/usr/bin/env bash
# Reproduce the shipped default weights on 2 CPU cores (about 7 h including data).
# RUNS (default: ../runs beside the repo) holds data, checkpoints and logs — never the repo.
# Run the script again to resume: each stage passes --resume when its checkpoint exists, and
# a finished stage (final.safetensors written) is skipped.
# Stage 6 trains with recipe.toml as it is; stages 1–5 with recipe.toml and the keys of
# stages/stageN.toml passed as `--set KEY=VALUE` (a [model.args] key as `model.args.KEY=…`).
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

overrides() {  # overrides STAGE: stages/stageSTAGE.toml as --set KEY=VALUE arguments, one a line
  python - "$here/stages/stage$1.toml" <<'PY'
import json, sys

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: trmd depends on tomli there
    import tomli as tomllib

def flat(table, prefix=""):
    for key, value in table.items():
        if isinstance(value, dict):
            yield from flat(value, f"{prefix}{key}.")
        else:  # a JSON string, number, boolean or list is also a TOML value
            yield f"{prefix}{key}", json.dumps(value)

with open(sys.argv[1], "rb") as f:
    for key, value in flat(tomllib.load(f)):
        print("--set")
        print(f"{key}={value}")
PY
}

recipe() {  # recipe STAGE: the arguments that give trmd train the recipe of stage 1–6
  echo "--recipe"
  echo "$here/recipe.toml"
  if [ "$1" != 6 ]; then overrides "$1"; fi
}

train() {  # train STAGE RUN ARGS…: a new run of stage STAGE's recipe in $RUNS/RUN
  local stage=$1 run="$RUNS/$2" text args
  shift 2
  text=$(recipe "$stage")
  mapfile -t args <<< "$text"
  trmd train "${args[@]}" --out "$run" --set "data.val_data=$val" "$@"
}

stage() {  # stage STAGE RUN ARGS…: train unless finished, resuming when possible
  local run="$RUNS/$2"
  [ -f "$run/final.safetensors" ] && return 0
  if [ -f "$run/checkpoint.safetensors" ]; then
    trmd train --out "$run" --resume  # the run keeps its own recipe and data
  else
    train "$@"
  fi
}

# stage 1: from scratch on the main set, stopped by its 60-minute budget at a high rate
stage 1 shipped-v2-stage1 --data "$main"
# stage 2: fine-tune stage 1's weights on the heavier-blur set
stage 2 shipped-v2 --data "$hard" --init-weights "$RUNS/shipped-v2-stage1/checkpoint.safetensors"
# stage 3: the ladder around a given c, both sets, a fresh cosine and a weight average (85 min)
stage 3 shipped-v3 --data "$main" --data "$hard" \
  --init-weights "$RUNS/shipped-v2/checkpoint.safetensors"
# stage 4: grow the full-resolution refinement (model.args refine = 3) from stage 3's weights;
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
    train 4 shipped-v4 --data "$main" --data "$hard" \
      --init-weights "$RUNS/shipped-v3/checkpoint.safetensors" --stop-after 2000
  fi
fi
all=(--data "$main" --data "$hard" --data "$bright" --data "$bright2")
# stage 5: all four sets, a fresh cosine (75 min)
stage 5 shipped-v5 "${all[@]}" --init-weights "$s4/checkpoint.safetensors"
# stage 6: grow the sub-bin timing inputs (trmd_small_prior) from stage 5's final weights,
# 3,000 steps of a fresh cosine from 1e-4 (45 min): the shipped weights
stage 6 s6-timing "${all[@]}" --init-weights "$RUNS/shipped-v5/final.safetensors"
# then: python weights_recipe/ship.py "$RUNS/s6-timing/final.safetensors" --valset "$val"
