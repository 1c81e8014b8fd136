#!/usr/bin/env bash
# Equal-budget A/B runs behind the recipe's choices (results in README.md here).
# Every arm: the stage-1 recipe with one change, the same seed, one CPU thread, the same
# wall-clock budget, all arms at once (so they share the machine equally), validated on the
# pinned Kodak set. Usage: RUNS=../runs bash weights_recipe/ab.sh ROUND
#   round 1: from scratch — the paper's inputs vs the EDI prior; attention normalisation; crop
#   round 2: fine-tuning stage 1's checkpoint ($RUNS/shipped-v2-stage1) — which training data
#   round 3: fine-tuning a first stage-3 attempt stopped at step 2000 ($RUNS/shipped-v3-partial:
#            recipe.toml with model trmd_small_edi) on both sets with
#            a weight average — the fixed contrast ladder vs the ladder around a given c
#   round 4: fine-tuning stage 3's result ($RUNS/shipped-v3) — sensor noise ranges: two
#            2,000-sample sets that differ only in them ($RUNS/ab4/{wide,narrow}.h5, below)
#   round 5: from v5 ($RUNS/shipped-v5/final.safetensors), all four sets, 3,000 steps of a
#            fresh cosine from 1e-4 each — the voxels alone vs the voxels plus their sub-bin
#            timing (trmd_small_edi_c_fr_t, which starts computing exactly what v5 computes).
#            Equal in steps, not minutes: the arms ran one after the other on both threads
#            (the timing arm's data costs ~25 % more per step), with no time budget. A repeat
#            of the timing arm with --set seed=7 --stop-after 1000 checked the gain (ab5/).
#   round 6: from v6 ($RUNS/s6-timing/final.safetensors), all four sets, bfloat16 (amp, on a
#            CPU with AMX), data.num_workers = 1 — v6 continued (a 3,000-step cosine, stopped
#            at step 1,000) vs the U-Net grown 1.5x wider (widths 48–384, refinement 32; a
#            4,000-step cosine, stopped at step 1,000 when it had not moved) (ab6/).
#   round 6-long (session 7): both arms of round 6 resumed from their step-1,000 checkpoints
#            with their schedules stretched to a 5,000-step cosine (ab6/).
#   round 7: the same start and settings, a 2,000-step cosine — the four sets vs the four
#            sets plus 6,000 samples of new content: dead-leaves images and sam2 video frames
#            (make_extra_images.py, then make_trainset.py as below) (ab7/).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
RUNS=${RUNS:-$here/../../runs}
round=${1:-1}
if [ "$round" = 5 ]; then
  mkdir -p "$RUNS/ab5"
  sets=(--data "$RUNS/train_128.h5" --data "$RUNS/train_128_hard.h5"
        --data "$RUNS/train_128_bright.h5" --data "$RUNS/train_128_bright2.h5")
  five=(--set "data.val_data=$RUNS/valset_kodak24.h5" --set optim.lr=1e-4
        --set optim.warmup_steps=100 --set train.steps=3000 --set train.time_budget_minutes=0
        --set train.val_every=1000 --init-weights "$RUNS/shipped-v5/final.safetensors")
  trmd train --recipe "$here/recipe_stage5.toml" "${five[@]}" "${sets[@]}" \
    --out "$RUNS/ab5/control" --overwrite > "$RUNS/ab5/control.log" 2>&1
  trmd train --recipe "$here/recipe_stage5.toml" "${five[@]}" "${sets[@]}" \
    --set 'model.name="trmd_small_edi_c_fr_t"' --out "$RUNS/ab5/timing" --overwrite \
    > "$RUNS/ab5/timing.log" 2>&1
  for name in control timing; do echo "== $name"; grep -v ',,,' "$RUNS/ab5/$name/log.csv"; done
  exit 0
fi
if [ "$round" = 6-long ]; then
  for name in wide control; do
    trmd train --out "$RUNS/ab6/$name" --resume --set train.steps=5000 >> "$RUNS/ab6/$name.log" 2>&1
  done
  for name in control wide; do echo "== $name"; grep -v ',,,' "$RUNS/ab6/$name/log.csv"; done
  exit 0
fi
if [ "$round" = 6 ] || [ "$round" = 7 ]; then
  mkdir -p "$RUNS/ab$round"
  sets=(--data "$RUNS/train_128.h5" --data "$RUNS/train_128_hard.h5"
        --data "$RUNS/train_128_bright.h5" --data "$RUNS/train_128_bright2.h5")
  six=(--set "data.val_data=$RUNS/valset_kodak24.h5" --set train.amp=true
       --set data.num_workers=1 --set train.time_budget_minutes=0 --set train.val_every=1000
       --init-weights "$RUNS/s6-timing/final.safetensors")
  if [ "$round" = 6 ]; then
    trmd train --recipe "$here/recipe.toml" "${six[@]}" "${sets[@]}" --set train.steps=3000 \
      --stop-after 1000 --out "$RUNS/ab6/control" --overwrite > "$RUNS/ab6/control.log" 2>&1
    trmd train --recipe "$here/recipe.toml" "${six[@]}" "${sets[@]}" --set train.steps=4000 \
      --set 'model.args={widths=[48, 96, 192, 384], refine_width=32}' --stop-after 1000 \
      --out "$RUNS/ab6/wide" --overwrite > "$RUNS/ab6/wide.log" 2>&1
    for name in control wide; do echo "== $name"; grep -v ',,,' "$RUNS/ab6/$name/log.csv"; done
    exit 0
  fi
  extra="$RUNS/train_128_extra.h5"
  if [ ! -f "$extra" ]; then
    python "$here/make_extra_images.py" "$RUNS/extra_root"
    python "$here/make_trainset.py" "$RUNS/extra_root" -o "$extra" --count 6000 --seed 5 \
      --workers 2 --exposure-ms 10 40 --gain 0.6 1.0 --read-noise 0 0.005
  fi
  trmd train --recipe "$here/recipe.toml" "${six[@]}" "${sets[@]}" --set train.steps=2000 \
    --out "$RUNS/ab7/control" --overwrite > "$RUNS/ab7/control.log" 2>&1
  trmd train --recipe "$here/recipe.toml" "${six[@]}" "${sets[@]}" --data "$extra" \
    --set train.steps=2000 --out "$RUNS/ab7/diverse" --overwrite > "$RUNS/ab7/diverse.log" 2>&1
  for name in control diverse; do echo "== $name"; grep -v ',,,' "$RUNS/ab7/$name/log.csv"; done
  exit 0
fi
minutes=${AB_MINUTES:-16}
main="$RUNS/train_128.h5"
hard="$RUNS/train_128_hard.h5"
recipe="$here/recipe_stage1.toml"  # round 4 starts from stage 3's recipe instead
common=(--set "data.val_data=$RUNS/valset_kodak24.h5" --set train.threads=1
        --set "train.time_budget_minutes=$minutes" --set train.steps=700
        --set optim.warmup_steps=50 --set train.val_every=100 --set train.checkpoint_every=100)
declare -A arms
case "$round" in
  1)
    # (round 1 ran with the stage-1 recipe at 128×128 crops × 8 and model trmd_small_edi)
    base="--data $main --set data.crop=128 --set data.batch_size=8"
    arms[paper_inputs]="$base --set model.name=\"trmd_small\""
    arms[edi_prior]="$base"
    arms[edi_prior_attn_none]="$base --set model.args.attn_norm=\"none\""
    arms[edi_prior_crop96]="--data $main --set data.crop=96 --set data.batch_size=14"
    ;;
  2)
    ft="--init-weights $RUNS/shipped-v2-stage1/checkpoint.safetensors --set optim.lr=3e-4"
    arms[main]="--data $main $ft"
    arms[main_hard]="--data $main --data $hard $ft"
    arms[hard]="--data $hard $ft"
    ;;
  3)
    ft="--init-weights $RUNS/shipped-v3-partial/checkpoint.safetensors --data $main --data $hard"
    ft="$ft --set optim.lr=2e-4 --set optim.ema=0.999 --set train.steps=800"
    ft="$ft --set train.val_every=200"
    arms[ladder_fixed]="$ft"
    arms[ladder_given_c]="$ft --set model.name=\"trmd_small_edi_c\""
    ;;
  4)
    # python weights_recipe/make_trainset.py -o $RUNS/ab4/wide.h5 --count 2000 --seed 4
    # the same with --sensor-range contrast_sigma 0.02 0.04 --sensor-range refractory_us 50 150
    #   --sensor-range shot_noise_hz 0 0.2 --sensor-range leak_hz 0 0.1
    #   --sensor-range hot_pixel_fraction 0 4e-5   (-o $RUNS/ab4/narrow.h5)
    recipe="$here/recipe.toml"
    ft="--init-weights $RUNS/shipped-v3/checkpoint.safetensors"
    ft="$ft --set optim.lr=1e-4 --set train.steps=700 --set train.val_every=350"
    arms[noise_wide]="$ft --data $RUNS/ab4/wide.h5"
    arms[noise_narrow]="$ft --data $RUNS/ab4/narrow.h5"
    ;;
  *) echo "unknown round $round" >&2; exit 2 ;;
esac
mkdir -p "$RUNS/ab$round"
for name in "${!arms[@]}"; do
  # shellcheck disable=SC2086
  nohup trmd train --recipe "$recipe" "${common[@]}" ${arms[$name]} --out "$RUNS/ab$round/$name" --overwrite \
    > "$RUNS/ab$round/$name.log" 2>&1 &
done
wait
for name in "${!arms[@]}"; do
  echo "== $name"; tail -n 3 "$RUNS/ab$round/$name/log.csv"
done
