"""SMAPE per state of observers and the EKF on one ``kklcasadi generalise`` case: which state carries a gap.

    PYTHONPATH=. python benchmarks/accuracy/per_state.py rossler zero id 0.05 MODEL_DIR [MODEL_DIR ...] \\
        --seed 3030 --trials 20

The trials are the case's (:class:`kklcasadi.evaluation.generalisation.Case`, seed ``--seed``, from the trial
cache), the EKF the one ``kklcasadi generalise`` runs beside the models
(:func:`kklcasadi.evaluation.generalisation.case_ekf`).
Prints the mean over the trials of :func:`kklcasadi.metrics.smape` with ``per_state=True`` (their mean over the
states is the protocol's number) for the EKF and each model.
"""

from __future__ import annotations

import argparse

import numpy as np

import kklcasadi as kc
from kklcasadi import metrics
from kklcasadi.evaluation.compiled import ekf_estimator, observer_estimator
from kklcasadi.evaluation.generalisation import Case, Settings, case_ekf
from kklcasadi.evaluation.trialcache import TrialCache, cache_root


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("system")
    p.add_argument("family")
    p.add_argument("regime", choices=("id", "ood", "held_out"))
    p.add_argument("noise", type=float)
    p.add_argument("models", nargs="+", help="model directories of the system")
    p.add_argument("--seed", type=int, default=3030, help="seed of the trials (validation: 3030)")
    p.add_argument("--trials", type=int, default=20)
    args = p.parse_args()
    plant = kc.systems.get(args.system)
    observers = [kc.load_observer(m) for m in args.models]
    settings = Settings(n_trials=args.trials, seed=args.seed)
    case = Case(args.family, args.regime, args.noise)
    batch = TrialCache(cache_root() / "trials").trials(plant, case.cell(settings))
    x, y, u = batch.x[batch.ok], batch.y[batch.ok], batch.u[batch.ok]
    ekf = case_ekf(plant, args.noise, settings.dt)
    rows = [("EKF", ekf_estimator(ekf)(batch.t, y, u))]
    rows += [(m, observer_estimator(obs)(batch.t, y, u)) for m, obs in zip(args.models, observers)]
    print(f"{args.system}, {case.label}, seed {args.seed}, {len(x)} trials: SMAPE % per state (mean)")
    for name, xhat in rows:
        per = np.mean(metrics.smape(x, xhat, per_state=True), axis=0)
        print(f"  {name}: " + "/".join(f"{v:.2f}" for v in per) + f"  (mean {per.mean():.2f})")


if __name__ == "__main__":
    main()
