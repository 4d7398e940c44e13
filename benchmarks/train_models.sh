#!/usr/bin/env bash
# Train the shipped observers under models/ (CPU; wall times are in each model's card.json).
# Usage: benchmarks/train_models.sh [SYSTEM ...]    (default: duffing vdp fhn rossler)
# The shipped duffing/dyn ran 100 epochs (--epochs 100, first 69 on a GPU with --device cuda);
# the other dyn models use the default 60. Pass --device cuda through DEVICE=cuda to train dyn on a GPU.
set -euo pipefail
cd "$(dirname "$0")/.."
systems=("${@:-duffing vdp fhn rossler}")
for s in ${systems[@]}; do
  kklcasadi train --system "$s" --method autonomous --out "models/$s/autonomous" --overwrite --quiet
  kklcasadi train --system "$s" --method inject --out "models/$s/inject" --overwrite --quiet
  kklcasadi train --system "$s" --method obs --out "models/$s/obs" --overwrite --quiet
  kklcasadi train --system "$s" --method dyn --out "models/$s/dyn" --overwrite --quiet --device "${DEVICE:-cpu}"
  kklcasadi train --system "$s" --method curriculum --out "models/$s/curriculum" --overwrite --quiet
done
