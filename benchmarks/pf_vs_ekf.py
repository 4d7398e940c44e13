"""The particle filter beside the EKF on the docs/protocol.md benchmark (noise on), with the PF's run time.

    OMP_NUM_THREADS=1 python benchmarks/pf_vs_ekf.py --system duffing --trials 100 --particles 1000

Per input regime: mean SMAPE (%) of ``kklcasadi.estimators.ParticleFilter`` (protocol noise levels, uniform prior
on the X0 box, systematic resampling at ESS < N/2, seed 0) and of the EKF (docs/protocol.md
settings) on the same trials, their ratio, the fraction of trials where the PF's SMAPE is lower,
the mean RMSE (whole horizon) of both and its ratio, and the PF's wall time (build excluded, one
thread: the per-sample Function runs serially). Trials come from the on-disk trial cache
(``$KKLCASADI_CACHE``), simulated once.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import kklcasadi as kc
from kklcasadi.estimators.ekf import EKF
from kklcasadi.estimators.pf import ParticleFilter
from kklcasadi.evaluation.protocol import Protocol
from kklcasadi.evaluation.trialcache import TrialCache
from kklcasadi.plant.signals import BENCHMARK_KINDS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--system", default="duffing")
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--substeps", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kinds", nargs="+", default=list(BENCHMARK_KINDS))
    args = parser.parse_args()

    system = kc.systems.get(args.system)
    protocol = Protocol(n_trials=args.trials)
    t0 = time.perf_counter()
    pf = ParticleFilter(system, protocol.dt, n_particles=args.particles, process_std=protocol.process_std,
                        measurement_std=protocol.measurement_std, substeps=args.substeps, seed=args.seed)
    print(f"PF build (jit={pf.jit}): {time.perf_counter() - t0:.2f} s")
    ekf = EKF(system, protocol.dt)
    print("| regime | SMAPE PF | SMAPE EKF | PF / EKF | PF better | RMSE PF | RMSE EKF | PF / EKF | PF time (s) | "
          "mean ESS |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    cache = TrialCache.default()
    for kind in args.kinds:
        batch = cache.trials(system, protocol.cell(kind))
        x, y, u = batch.x[batch.ok], batch.y[batch.ok], batch.u[batch.ok]
        t0 = time.perf_counter()
        est = pf.simulate(batch.t, y, u)
        elapsed = time.perf_counter() - t0
        s_pf = kc.metrics.smape(x, est.xhat)
        xhat_ekf = ekf.simulate(batch.t, y, u).xhat
        s_ekf = kc.metrics.smape(x, xhat_ekf)
        r_pf, r_ekf = kc.metrics.rmse(x, est.xhat).mean(), kc.metrics.rmse(x, xhat_ekf).mean()
        print(f"| {kind} | {s_pf.mean():.2f} | {s_ekf.mean():.2f} | {s_pf.mean() / s_ekf.mean():.4f} | "
              f"{np.mean(s_pf < s_ekf):.2f} | {r_pf:.4f} | {r_ekf:.4f} | {r_pf / r_ekf:.4f} | {elapsed:.1f} | "
              f"{est.stats.ess.mean():.0f} |")


if __name__ == "__main__":
    main()
