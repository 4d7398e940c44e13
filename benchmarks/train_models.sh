#!/usr/bin/env bash
# Train the shipped observers under models/ (CPU; wall times are in each model's card.json).
# Usage: benchmarks/train_models.sh [SYSTEM ...]    (default: duffing vdp fhn rossler)
set -euo pipefail
cd "$(dirname "$0")/.."
systems=("${@:-duffing vdp fhn rossler}")
for s in ${systems[@]}; do
  kklcasadi train --system "$s" --method autonomous --out "models/$s/autonomous" --overwrite --quiet
  kklcasadi train --system "$s" --method inject --out "models/$s/inject" --overwrite --quiet
  kklcasadi train --system "$s" --method obs --out "models/$s/obs" --overwrite --quiet
  kklcasadi train --system "$s" --method dyn --out "models/$s/dyn" --overwrite --quiet
  kklcasadi train --system "$s" --method curriculum --out "models/$s/curriculum" --overwrite --quiet
done
