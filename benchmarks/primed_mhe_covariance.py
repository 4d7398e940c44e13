"""The KKL-primed MHE with the observer's covariance as its arrival cost against the constant error profile.

    python benchmarks/primed_mhe_covariance.py SYSTEM --out DIR [--trials 100] [--T 50] [--kinds ...] [--horizon 5]

Both MHEs (:class:`kklcasadi.estimators.mhe.KKLPrimedMHE`, horizon ``--horizon``, the protocol's noise levels) are
primed by the shipped ``SYSTEM/bank`` on the same noisy protocol trials (seed 2026): one with the error profile
:func:`kklcasadi.estimators.mhe.kkl_error_profile` calibrated on 5 runs per regime of seed 2027 (what
``kklcasadi compare`` runs), the other with the observer's covariance head (``error_std=None``). Writes
``DIR/SYSTEM_primed_mhe.md`` and ``.json`` (stamped, written together; refused before any run where one exists):
mean SMAPE and RMSE after 5 s per regime, and the observer's.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from kklcasadi import metrics, provenance
from kklcasadi.estimators.kkl_mhe import KKLPrimedMHE, kkl_error_profile
from kklcasadi.evaluation.compare import MHE_SUBSTEPS
from kklcasadi.evaluation.protocol import Protocol
from kklcasadi.observer.kkl import load_observer
from kklcasadi.plant import signals as sig
from kklcasadi.writes import refuse_existing, write_dir


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("system")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--T", type=float, default=50.0)
    p.add_argument("--kinds", nargs="+", default=list(sig.BENCHMARK_KINDS), choices=sig.BENCHMARK_KINDS)
    p.add_argument("--horizon", type=int, default=5)
    args = p.parse_args()
    names = {ext: f"{args.system}_primed_mhe.{ext}" for ext in ("md", "json")}
    refuse_existing({args.out / name: "--out" for name in names.values()})     # before any run, never over a file
    obs = load_observer(f"{args.system}/bank")
    protocol = Protocol(n_trials=args.trials, T=args.T)
    calibration = Protocol(n_trials=5, T=args.T, seed=protocol.seed + 1)
    profile = kkl_error_profile(obs, calibration, args.kinds)
    options = {"process_std": protocol.process_std, "measurement_std": protocol.measurement_std,
               "substeps": MHE_SUBSTEPS.get(args.system, 1)}
    estimators = {"primed MHE, constant profile": KKLPrimedMHE(obs, profile, args.horizon, **options),
                  "primed MHE, covariance head": KKLPrimedMHE(obs, None, args.horizon, **options)}
    rows = []
    for kind in args.kinds:
        batch = protocol.trials(obs.system, kind)
        ok = batch.ok
        x, y, u = batch.x[ok], batch.y[ok], batch.u[ok]
        runs = {"observer": obs.simulate(batch.t, y, u).xhat}
        for label, mhe in estimators.items():
            runs[label] = mhe(batch.t, y, u)
            print(f"{args.system} {kind} {label}: failed solves {mhe.last_stats.n_failed}", flush=True)
        for label, xhat in runs.items():
            rows.append({"system": args.system, "kind": kind, "estimator": label, "trials": int(ok.sum()),
                         "smape": float(np.mean(metrics.smape(x, xhat))),
                         "rmse_after": float(np.mean(metrics.rmse_after(batch.t, x, xhat, protocol.t_settle)))})
    lines = ["| system | regime | estimator | trials | SMAPE % | RMSE after 5 s |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['system']} | {r['kind']} | {r['estimator']} | {r['trials']} | {r['smape']:.2f} | "
              f"{r['rmse_after']:.4f} |" for r in rows]
    text = "\n".join(lines)
    print(text)
    stamp = provenance.stamp(seeds={"trials": protocol.seed, "calibration": calibration.seed})
    record = {"settings": {k: str(v) for k, v in vars(args).items()}, "rows": rows}
    write_dir(args.out, {names["md"]: provenance.markdown(text + "\n", stamp),           # the two as one
                         names["json"]: json.dumps(provenance.json_record(record, stamp), indent=1) + "\n"},
              argument="--out")


if __name__ == "__main__":
    main()
