#!/usr/bin/env bash
# Equal-budget A/B runs behind the recipe's choices (results in README.md here).
# Every arm: the recipe.toml of the shipped weights with one change, the same data, the same
# seed, one CPU thread, the same wall-clock budget, all arms at once (so they share the machine
# equally). Usage: RUNS=../runs bash weights_recipe/ab.sh ROUND  (ROUND: 1)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
RUNS=${RUNS:-$here/../../runs}
round=${1:-1}
minutes=${AB_MINUTES:-16}
common=(--data "$RUNS/train_128.h5" --recipe "$here/recipe.toml"
        --set "data.val_data=$RUNS/valset_kodak24.h5" --set train.threads=1
        --set "train.time_budget_minutes=$minutes" --set train.steps=700
        --set optim.warmup_steps=50 --set train.val_every=100 --set train.checkpoint_every=100)
declare -A arms
case "$round" in
  1)
    arms[paper_inputs]='--set model.name="trmd_small"'
    arms[edi_prior]='--set model.name="trmd_small_edi"'
    arms[edi_prior_attn_none]='--set model.name="trmd_small_edi" --set model.args.attn_norm="none"'
    arms[edi_prior_crop96]='--set model.name="trmd_small_edi" --set data.crop=96 --set data.batch_size=14'
    ;;
  *) echo "unknown round $round" >&2; exit 2 ;;
esac
mkdir -p "$RUNS/ab$round"
for name in "${!arms[@]}"; do
  # shellcheck disable=SC2086
  nohup trmd train "${common[@]}" ${arms[$name]} --out "$RUNS/ab$round/$name" --overwrite \
    > "$RUNS/ab$round/$name.log" 2>&1 &
done
wait
for name in "${!arms[@]}"; do
  echo "== $name"; tail -n 3 "$RUNS/ab$round/$name/log.csv"
done
