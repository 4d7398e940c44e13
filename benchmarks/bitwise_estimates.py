"""Record every shipped model's estimates (and the EKF's, the particle filter's, the MHEs' and an NMPC loop's) on
the first trials of every protocol cell, or compare two such records bit for bit.

    OMP_NUM_THREADS=1 python benchmarks/bitwise_estimates.py record OUT.npz [--trials 2] [--systems ...]
    python benchmarks/bitwise_estimates.py compare BEFORE.npz AFTER.npz

A refactor that moves code without changing what it computes leaves these arrays bitwise equal
(``numpy.array_equal``, NaN equal to NaN). ``record`` runs, for each system (default the four shipped ones)
and each protocol cell (the benchmark's input kinds, regimes ``id`` and ``ood``, noise on and off;
``Protocol(n_trials=--trials)``, seed 2026):

* every shipped model (``models/<system>/*``): ``simulate`` (``xhat``, ``z``, ``in_domain``), the compiled
  estimator (:func:`kklcasadi.evaluation.compiled.observer_estimator`) and, on the first trial, the
  step-by-step estimator (``obs.estimator().make_step``);
* the EKF of the cell's noise (:meth:`kklcasadi.EKF.for_noise`; ``simulate`` and the compiled estimator);
* the particle filter (500 particles, seed 0, the benchmark's substeps and roughening; ``simulate`` and the
  compiled one);

and on the first trial of the noisy ``id`` sinusoid cell, over its first ``--mhe-samples`` samples, the MHE
(horizon 10) and the ``bank`` model's KKL-primed MHE (horizon 5), and a short NMPC loop with the EKF, the
``bank`` observer and the true state as estimators. Each array is stored under
``system/source/noise/regime/kind/field``; the file's ``meta`` entry names the command, the commit and the seeds.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from kklcasadi.writes import refuse_existing, write_file

ROOT = Path(__file__).resolve().parents[1]
SYSTEMS = ("duffing", "vdp", "rossler", "fhn")
REGIMES = ("id", "ood")
PARTICLES = 500


def _arrays(prefix: str, result: Any, names: tuple[str, ...]) -> Iterator[tuple[str, np.ndarray]]:
    """The named array fields of an estimate (``stats`` entries too where the field is not on the result)."""
    for name in names:
        value = getattr(result, name, None)
        if value is None and getattr(result, "stats", None) is not None:
            stats = result.stats
            value = stats.get(name) if isinstance(stats, dict) else getattr(stats, name, None)
        if value is not None:
            yield f"{prefix}/{name}", np.asarray(value)


def _commit() -> str:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, check=True).stdout.strip()
        return out.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError) as exc:
        return f"unknown ({exc})"


def record(out: Path, systems: tuple[str, ...], n_trials: int, mhe_samples: int) -> None:
    import kklcasadi as kc
    from kklcasadi.estimators import KKLPrimedMHE, ParticleFilter
    from kklcasadi.estimators.nmpc import NMPC, EKFEstimator, TrueState, closed_loop, steady_state
    from kklcasadi.estimators.pf import ROUGHENING, SUBSTEPS
    from kklcasadi.evaluation.compiled import ekf_estimator, observer_estimator, pf_estimator
    from kklcasadi.evaluation.protocol import Protocol

    refuse_existing({out: "OUT.npz"})                             # before any run; written whole at the end
    store: dict[str, np.ndarray] = {}
    t0 = time.perf_counter()
    for name in systems:
        plant = kc.systems.get(name)
        models = sorted(p for p in (ROOT / "models" / name).iterdir() if (p / "card.json").exists())
        observers = {m.name: kc.load_observer(m) for m in models}
        compiled = {label: observer_estimator(obs) for label, obs in observers.items()}
        for noisy in (True, False):
            noise = "on" if noisy else "off"
            for regime in REGIMES:
                protocol = Protocol(n_trials=n_trials, regime=regime)
                protocol = protocol if noisy else protocol.noise_free()
                ekf = kc.EKF.for_noise(plant, protocol.dt, process_std=protocol.process_std,
                                       measurement_std=protocol.measurement_std)
                pf_options = dict(n_particles=PARTICLES, process_std=max(protocol.process_std, 0.01),
                                  measurement_std=max(protocol.measurement_std, 0.01), substeps=SUBSTEPS.get(name, 1),
                                  seed=0, roughening=ROUGHENING)
                pf = ParticleFilter(plant, protocol.dt, **pf_options)
                for kind in ("zero", "constant", "sinusoid", "square"):
                    batch = protocol.trials(plant, kind)
                    t, y, u = np.asarray(batch.t), np.asarray(batch.y), np.asarray(batch.u)
                    cell = f"{noise}/{regime}/{kind}"
                    store[f"{name}/trials/{cell}/x"] = np.asarray(batch.x)
                    for label, obs in observers.items():
                        key = f"{name}/{label}/{cell}"
                        store.update(_arrays(key, obs.simulate(t, y, u), ("xhat", "z", "in_domain")))
                        store[f"{key}/compiled"] = np.asarray(compiled[label](t, y, u))
                        est = obs.estimator()
                        store[f"{key}/make_step"] = np.array([est.make_step(y[0, k], u[0, k]) for k in range(t.size)])
                    store.update(_arrays(f"{name}/ekf/{cell}", ekf.simulate(t, y, u), ("xhat", "var")))
                    store[f"{name}/ekf/{cell}/compiled"] = np.asarray(ekf_estimator(ekf)(t, y, u))
                    store.update(_arrays(f"{name}/pf/{cell}", pf.simulate(t, y, u), ("xhat", "var", "ess")))
                    compiled_pf = pf_estimator(plant, protocol.dt, **pf_options)
                    store[f"{name}/pf/{cell}/compiled"] = np.asarray(compiled_pf(t, y, u))
                    if noisy and regime == "id" and kind == "sinusoid":
                        ts, ys, us = t[:mhe_samples], y[0, :mhe_samples], u[0, :mhe_samples]
                        mhe = kc.MHE(plant, protocol.dt, 10, process_std=protocol.process_std,
                                     measurement_std=protocol.measurement_std)
                        store.update(_arrays(f"{name}/mhe/{cell}", mhe.simulate(ts, ys, us), ("xhat", "iterations")))
                        primed = KKLPrimedMHE(observers["bank"], np.full(plant.nx, 0.2), 5,
                                              process_std=protocol.process_std,
                                              measurement_std=protocol.measurement_std)
                        store.update(_arrays(f"{name}/kkl_mhe/{cell}", primed.simulate(ts, ys, us),
                                             ("xhat", "iterations")))
                    print(f"{name} {cell}: {time.perf_counter() - t0:.0f} s", flush=True)
        if plant.nu == 1 and name in ("duffing", "vdp"):
            target = steady_state(plant, 0.5)
            for label, estimator in (("ekf", EKFEstimator(plant, 0.05)), ("bank", observers["bank"].estimator()),
                                     ("true", TrueState())):
                run = closed_loop(NMPC(plant, 0.05, 8), estimator, lambda _t: target, plant.x0_box.mean(axis=1), 1.0,
                                  seed=3)
                store[f"{name}/nmpc/{label}/x"], store[f"{name}/nmpc/{label}/xhat"] = run.x, run.xhat
                store[f"{name}/nmpc/{label}/u"] = run.u
    meta = {"command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]), "commit": _commit(),
            "seeds": {"protocol": 2026, "particle_filter": 0, "nmpc_noise": 3}, "trials": n_trials,
            "systems": list(systems), "seconds": round(time.perf_counter() - t0, 1),
            "threads": os.environ.get("OMP_NUM_THREADS")}
    archive = io.BytesIO()
    np.savez(archive, meta=np.array(json.dumps(meta)), **store)
    write_file(out, archive.getvalue(), argument="OUT.npz")          # whole, and never over a file written meanwhile
    print(f"wrote {out}: {len(store)} arrays, {meta['seconds']} s")


def compare(before: Path, after: Path) -> int:
    a, b = np.load(before), np.load(after)
    keys_a, keys_b = set(a.files) - {"meta"}, set(b.files) - {"meta"}
    differ = [k for k in sorted(keys_a & keys_b)
              if a[k].shape != b[k].shape or not np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f")]
    for k in differ:
        da, db = a[k], b[k]
        gap = (float(np.nanmax(np.abs(da - db))) if da.shape == db.shape and da.dtype.kind == "f" else "shape/type")
        print(f"differs: {k} (largest difference {gap})")
    for k in sorted(keys_a - keys_b):
        print(f"only in {before}: {k}")
    for k in sorted(keys_b - keys_a):
        print(f"only in {after}: {k}")
    same = len(keys_a & keys_b) - len(differ)
    print(f"{same} of {len(keys_a | keys_b)} arrays bitwise equal ({json.loads(str(a['meta']))['commit']} -> "
          f"{json.loads(str(b['meta']))['commit']})")
    return 0 if same == len(keys_a | keys_b) else 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="run the estimators and save their estimates")
    rec.add_argument("out", type=Path, help="the .npz file to write (must not exist)")
    rec.add_argument("--trials", type=int, default=2, help="trials per cell (default 2)")
    rec.add_argument("--systems", nargs="+", default=list(SYSTEMS), choices=SYSTEMS, help="systems (default all four)")
    rec.add_argument("--mhe-samples", type=int, default=40, help="samples of the MHE runs (default 40)")
    cmp = sub.add_parser("compare", help="compare two records bit for bit (exit status 1 where any array differs)")
    cmp.add_argument("before", type=Path, help="the record before the change")
    cmp.add_argument("after", type=Path, help="the record after it")
    args = parser.parse_args()
    if args.command == "record":
        record(args.out, tuple(args.systems), args.trials, args.mhe_samples)
    else:
        raise SystemExit(compare(args.before, args.after))


if __name__ == "__main__":
    main()
