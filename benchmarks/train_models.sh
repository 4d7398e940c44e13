#!/usr/bin/env bash
# Train the shipped observers under models/ (CPU; wall times are in each model's card.json).
# Usage: benchmarks/train_models.sh [SYSTEM ...]    (default: duffing vdp fhn rossler)
# Budgets of the shipped models differ from today's defaults where time ran short (each card.json
# records its own): duffing/dyn ran 100 epochs (--epochs 100, the first 69 on a GPU), rossler/dyn
# 8 (40 lowered its validation loss 3x but raised its SMAPE 3-6 points, see README), the vdp,
# fhn and rossler obs models 15, duffing/obs-inject 15, and rossler/obs_stream 40 (120, today's
# default, lowered its validation loss from 0.233 to 0.199 and moved no SMAPE cell by more than 0.4).
# bank (the observer fit for noisy measurements) is seed 11, one thread (about 15-35 min per system
# on the 2-core machine; its card records the wall time).
# DEVICE=cuda trains the Phase-2 methods on a GPU.
set -euo pipefail
cd "$(dirname "$0")/.."
systems=("${@:-duffing vdp fhn rossler}")
for s in ${systems[@]}; do
  kklcasadi train --system "$s" --method autonomous --out "models/$s/autonomous" --overwrite --quiet
  kklcasadi train --system "$s" --method inject --out "models/$s/inject" --overwrite --quiet
  kklcasadi train --system "$s" --method obs --out "models/$s/obs" --overwrite --quiet --device "${DEVICE:-cpu}"
  kklcasadi train --system "$s" --method dyn --out "models/$s/dyn" --overwrite --quiet --device "${DEVICE:-cpu}"
  kklcasadi train --system "$s" --method curriculum --out "models/$s/curriculum" --overwrite --quiet
  kklcasadi train --system "$s" --method bank --out "models/$s/bank" --overwrite --quiet --seed 11 --threads 1
  # the streaming context ships where it is within 10 % of the window GRU or better
  if [ "$s" != fhn ]; then
    kklcasadi train --system "$s" --method obs_stream --out "models/$s/obs_stream" --overwrite --quiet
  fi
  if [ "$s" = vdp ]; then      # dyn_stream: better than the window dyn in every cell
    kklcasadi train --system "$s" --method dyn_stream --out "models/$s/dyn_stream" --overwrite --quiet
  elif [ "$s" = rossler ]; then  # dyn_stream: 3-7 % behind the window dyn after 40 epochs
    kklcasadi train --system "$s" --method dyn_stream --out "models/$s/dyn_stream" --overwrite --quiet --epochs 40
  fi
done
