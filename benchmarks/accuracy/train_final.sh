#!/bin/sh
# Train the final bank observers (recipes.py), two systems at a time, one thread each.
# Weights and records: results/accuracy/weights/<system>_bank.{npz,json}; logs: /tmp/acc_final_<system>.log
export PYTHONPATH=. OMP_NUM_THREADS=1
P="/work/main/.venv/bin/python benchmarks/accuracy/probe.py"
$P duffing --recipe --tag bank --save results/accuracy/weights > /tmp/acc_final_duffing.log 2>&1 &
$P vdp --recipe --tag bank --save results/accuracy/weights > /tmp/acc_final_vdp.log 2>&1
wait
$P rossler --recipe --tag bank --save results/accuracy/weights > /tmp/acc_final_rossler.log 2>&1 &
$P fhn --recipe --tag bank --save results/accuracy/weights > /tmp/acc_final_fhn.log 2>&1
wait
