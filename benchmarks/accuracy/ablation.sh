#!/bin/sh
# Lever ablation on Duffing with a cheap configuration (1000 rollouts, 10 epochs, 3x128 decoder),
# two runs at a time. Results: results/levers/duffing/duffing_abl_*.json, summary: tables.py; the runs' logs
# go to LOGS (default: a new temporary folder).
set -e
cd "$(dirname "$0")/../.."
LOGS=${LOGS:-$(mktemp -d -t kklcasadi-ablation-XXXXXX)}
echo "logs in $LOGS"
P="env PYTHONPATH=. ${PYTHON:-python} benchmarks/accuracy/probe.py duffing --n-traj 1000 --epochs 10 --hidden 128,128,128"
G="--y-poles 0.2,0.4,0.8,1.5,3,6,12,25"
$P --tag abl_kkl --y-poles 1,2,3,4,5 --u-poles "" > $LOGS/abl_kkl.log 2>&1 &
$P --tag abl_kkl_u --y-poles 1,2,3,4,5 --u-poles 0.3,1,3 > $LOGS/abl_kkl_u.log 2>&1
wait
$P --tag abl_wide_u $G --u-poles 0.3,1,3 > $LOGS/abl_wide_u.log 2>&1 &
$P --tag abl_wide_u_clock $G --u-poles 0.3,1,3 --clock 0.2 > $LOGS/abl_wide_u_clock.log 2>&1
wait
$P --tag abl_smape $G --u-poles 0.3,1,3 --clock 0.2 --loss mse+smape --smape-weight 0.1 > $LOGS/abl_smape.log 2>&1 &
$P --tag abl_nowhiten $G --u-poles 0.3,1,3 --clock 0.2 --no-whiten > $LOGS/abl_nowhiten.log 2>&1
wait
$P --tag abl_reson $G --u-poles 0.3,1,3 --clock 0.2 --resonators 0.2:1.0,0.2:1.6 > $LOGS/abl_reson.log 2>&1 &
$P --tag abl_wide_u_clock_s2 $G --u-poles 0.3,1,3 --clock 0.2 --seed 12 > $LOGS/abl_s2.log 2>&1
wait
