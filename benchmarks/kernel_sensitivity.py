"""How far the vectorised exp/tanh move a shipped observer's trajectories from the C library's (bitwise the VM).

    OMP_NUM_THREADS=1 python benchmarks/kernel_sensitivity.py [--systems duffing vdp rossler fhn] [--trials 8]

Per step the two builds differ by at most 1e-14 (1 + |VM|) (tests/test_compiled.py); over a trial the
difference grows as the observer's own dynamics amplify it. For every shipped model, every cell of
docs/protocol.md (noise-free and noisy), the first ``--trials`` trials: the largest
``|xhat_vector - xhat_libm| / (1 + |xhat_libm|)`` over the samples, printed per cell where it is above
1e-12 and per model. A model whose trajectories leave the VM's is scored with ``--math libm``
(benchmarks/evaluate_models.sh).
"""

from __future__ import annotations

import argparse

import numpy as np

import kklcasadi as kc
from kklcasadi.evaluation.compiled import Compiler, observer_estimator
from kklcasadi.evaluation.protocol import Protocol
from kklcasadi.evaluation.trialcache import TrialCache, cache_root
from kklcasadi.model.shipped import shipped_models
from kklcasadi.observer.codegen import axpy_matvec, fast_kernels
from kklcasadi.plant import signals as sig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--systems", nargs="+", default=["duffing", "vdp", "rossler", "fhn"])
    parser.add_argument("--trials", type=int, default=8, help="first trials of each cell")
    args = parser.parse_args()
    root = cache_root()
    protocol, trials = Protocol(n_trials=100), TrialCache(root / "trials")
    vector = Compiler(cache_dir=root / "compiled", postprocess=fast_kernels)
    libm = Compiler(cache_dir=root / "compiled", postprocess=axpy_matvec)
    for system in args.systems:
        for path in shipped_models(system):
            obs = kc.load_observer(path)
            fast, exact = observer_estimator(obs, compiler=vector), observer_estimator(obs, compiler=libm)
            worst = 0.0
            for noisy in (False, True):
                cells = protocol if noisy else protocol.noise_free()
                for kind in sig.BENCHMARK_KINDS:
                    batch = trials.trials(obs.system, cells.cell(kind))
                    y, u = batch.y[batch.ok][:args.trials], batch.u[batch.ok][:args.trials]
                    reference = exact(batch.t, y, u)
                    diff = float(np.max(np.abs(fast(batch.t, y, u) - reference) / (1 + np.abs(reference))))
                    worst = max(worst, diff)
                    if diff > 1e-12:
                        print(f"{system} {path.name} {kind} {'noisy' if noisy else 'clean'}: {diff:.2e}", flush=True)
            print(f"{system} {path.name}: largest relative difference {worst:.2e}", flush=True)


if __name__ == "__main__":
    main()
