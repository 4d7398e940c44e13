"""The estimator comparison of the README: KKL observer vs EKF vs MHE (N = 10, 30) vs KKL-primed MHE.

docs/protocol.md benchmark (four systems, four input regimes, noise off and on, fixed seed 2026), with
the computation time per sample of every estimator measured in the same run. The full protocol
(100 trials per cell) is

    python benchmarks/compare_estimators.py --trials 100

and takes several CPU-hours (about 1000 ipopt solves per trial per MHE); systems may run in
separate processes (``--systems duffing vdp`` and ``--systems fhn rossler``): each writes
``results/estimators/<system>.json`` and rewrites ``results/estimators/table.md`` from all of them.
Same as ``kklcasadi compare`` (see ``kklcasadi compare --help``).
"""

import sys

from kklcasadi.pipelines import main

if __name__ == "__main__":
    sys.exit(main(["compare", *sys.argv[1:]]))
