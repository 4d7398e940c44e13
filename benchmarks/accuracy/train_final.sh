#!/bin/sh
# Fit the final bank decoders (the recipe = kklcasadi.train.bank.BankConfig defaults, seed 11), two
# systems at a time with one thread each, then package them as models/<system>/bank.
# Usage: benchmarks/accuracy/train_final.sh [WEIGHTS_DIR]   (default /tmp/bank_weights; logs beside it)
set -eu
cd "$(dirname "$0")/../.."
W="${1:-/tmp/bank_weights}"
mkdir -p "$W"
export PYTHONPATH=. OMP_NUM_THREADS=1
P="${PYTHON:-python} benchmarks/accuracy/probe.py"
$P duffing --recipe --seed 11 --tag bank --save "$W" > "$W/duffing.log" 2>&1 &
$P vdp --recipe --seed 11 --tag bank --save "$W" > "$W/vdp.log" 2>&1
wait
$P rossler --recipe --seed 11 --tag bank --save "$W" > "$W/rossler.log" 2>&1 &
$P fhn --recipe --seed 11 --tag bank --save "$W" > "$W/fhn.log" 2>&1
wait
"${PYTHON:-python}" benchmarks/accuracy/ship_bank.py "$W" --overwrite
