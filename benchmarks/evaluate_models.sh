#!/usr/bin/env bash
# Score the shipped observers and the EKF on the PROTOCOL.md benchmark; writes results/<system>/
# (table.md, per-trial scores.json, SMAPE box plots). Usage: benchmarks/evaluate_models.sh [TRIALS]
set -euo pipefail
cd "$(dirname "$0")/.."
trials="${1:-20}"
for s in duffing vdp fhn rossler; do
  models=(); labels=()
  for m in autonomous inject obs obs-inject dyn curriculum; do
    if [ -f "models/$s/$m/card.json" ]; then models+=("models/$s/$m"); labels+=("$m"); fi
  done
  kklcasadi evaluate "${models[@]}" --labels "${labels[@]}" --trials "$trials" --ekf --out "results/$s"
done
