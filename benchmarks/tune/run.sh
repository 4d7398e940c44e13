#!/usr/bin/env bash
# kklcasadi tune on a plant kklcasadi does not ship (README, "Design searches"): two workers on one
# SQLite study of the bank observer with the budget capped at 400 runs and 15 epochs, the recipe
# trained at the same caps as the baseline, then the best trial and the baseline scored again on
# fresh validation trials (another seed) beside the EKF.
# Usage: benchmarks/tune/run.sh [PLANT [OUT [TRIALS]]]
#        (default examples/two_masses.py:make_plant, a new temporary folder, 32)
set -euo pipefail
PLANT=${1:-examples/two_masses.py:make_plant}
OUT=${2:-$(mktemp -d -t kklcasadi-tune-XXXXXX)}
TRIALS=${3:-32}
ARGS=(--plant "$PLANT" --method bank --trials "$TRIALS" --runs 400 --epochs 15 --out "$OUT" --quiet --threads 1)
mkdir -p "$OUT"
python -m kklcasadi tune "${ARGS[@]}" --baseline --sampler-seed 1 > "$OUT/worker1.log" 2>&1 &
sleep 30                  # the first worker creates Optuna's tables; then the second joins
python -m kklcasadi tune "${ARGS[@]}" --sampler-seed 2 > "$OUT/worker2.log" 2>&1 &
wait
python benchmarks/tune/confirm.py "$OUT" --plant "$PLANT"
