#!/usr/bin/env bash
# kklcasadi tune on a plant kklcasadi does not ship (the damped pendulum of examples/own_plant.py):
# two workers on one SQLite study with the budget capped at 400 runs and 15 epochs, the recipe
# trained at the same caps as the baseline, then the best trial and the baseline scored again on
# fresh validation trials (another seed) beside the EKF (README, "Design searches").
# Usage: benchmarks/tune/pendulum.sh [OUT]   (default /tmp/kklcasadi-tune-pendulum)
set -euo pipefail
OUT=${1:-/tmp/kklcasadi-tune-pendulum}
ARGS=(--plant examples/own_plant.py:make_plant --method bank --trials 24 --runs 400 --epochs 15 --out "$OUT"
      --quiet --threads 1)
mkdir -p "$OUT"
python -m kklcasadi tune "${ARGS[@]}" --baseline --sampler-seed 1 > "$OUT/worker1.log" 2>&1 &
sleep 30                  # the first worker creates Optuna's tables; then the second joins
python -m kklcasadi tune "${ARGS[@]}" --sampler-seed 2 > "$OUT/worker2.log" 2>&1 &
wait
python benchmarks/tune/confirm.py "$OUT" --plant examples/own_plant.py:make_plant
