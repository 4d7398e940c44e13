#!/usr/bin/env bash
# Score the shipped observers and the EKF on the docs/protocol.md benchmark; writes results/<system>/
# (table.md, per-trial scores.json, SMAPE box plots). The trials of each cell are simulated once and
# kept in the trial cache ($KKLCASADI_CACHE, default ~/.cache/kklcasadi); observers and the EKF run as
# compiled trajectories mapped over the trials (vectorised exp/tanh within 1e-14 of the VM; FitzHugh-Nagumo with
# the C library's, bitwise the VM: see below).
# Usage: benchmarks/evaluate_models.sh [TRIALS [SYSTEM...]]   (default: 100 trials, all four systems)
# The interpreter is $PYTHON (default: python).
set -euo pipefail
cd "$(dirname "$0")/.."
trials="${1:-100}"
if [ $# -gt 0 ]; then shift; fi
systems=("$@")
if [ ${#systems[@]} -eq 0 ]; then systems=(duffing vdp fhn rossler); fi
for s in "${systems[@]}"; do
  models=()
  for m in autonomous inject obs obs-inject obs_stream dyn dyn_stream curriculum bank; do
    if [ -f "models/$s/$m/card.json" ]; then models+=("models/$s/$m"); fi
  done
  # FitzHugh-Nagumo's inject observer amplifies rounding: under a nonzero input its trajectories with the
  # vectorised exp/tanh leave those of the VM (up to 100 % relative), so its table is the C library's
  # exp/tanh, bitwise the VM; every other shipped model stays within 1.5e-14 of the VM either way.
  math=vector
  if [ "$s" = fhn ]; then math=libm; fi
  TIMEFORMAT="$s: $trials trials per cell in %R s wall, %U s user + %S s system CPU"
  time "${PYTHON:-python}" -m kklcasadi evaluate "${models[@]}" --trials "$trials" --ekf --math "$math" --out "results/protocol/$s"
done
