"""``kklcasadi evaluate``: score model directories (and the EKF, the MHE) on the docs/protocol.md cells.

Trials come from the on-disk trial cache (simulated once per cell); observers and the EKF run as
compiled trajectories mapped over the trials, with the vectorised exp/tanh (within 1e-14 of the
VM; ``--math libm``: bitwise the VM; ``--vm``: the CasADi VM itself).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from ..plant import signals as sig
from ..plant.systems import System
from .flags import (
    NOISE,
    CommandError,
    add_dt,
    add_kinds,
    add_noise,
    add_noise_levels,
    add_plant,
    check_dt,
    load,
    plant_of,
    positive_int,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("evaluate", help="score models on the docs/protocol.md benchmark (SMAPE table, box plots)")
    e.add_argument("models", nargs="+", metavar="MODELS", help="model directories (same system)")
    e.add_argument("--labels", nargs="*", help="row labels, one per model (default: the model directories' names)")
    e.add_argument("--trials", type=positive_int, default=100, help="trials per cell (docs/protocol.md: 100)")
    add_plant(e, "for models of a plant that kklcasadi does not ship")
    add_noise(e)
    add_kinds(e)
    e.add_argument("--regime", default="id", choices=sig.REGIMES)
    add_dt(e, "the protocol's sample time (default 0.05, docs/protocol.md); the models' must equal it")
    add_noise_levels(e, "the noisy column's and the EKF's and MHE's (default docs/protocol.md's 0.1)")
    e.add_argument("--ekf", action="store_true", help="add the EKF baseline")
    e.add_argument("--mhe", nargs="+", type=positive_int, metavar="N",
                   help="add the exact-model MHE with these horizons (one ipopt solve per sample: slow)")
    e.add_argument("--seed", type=int, default=2026)
    e.add_argument("--out", help="directory for the JSON scores, table and box plots")
    e.add_argument("--cache-dir", help="root of the trial and compiled-code caches (default: $KKLCASADI_CACHE, "
                   "else ~/.cache/kklcasadi)")
    e.add_argument("--no-cache", action="store_true", help="simulate the trials instead of reading/writing the "
                   "trial cache")
    e.add_argument("--vm", action="store_true", help="run the observers in the CasADi VM instead of compiled C "
                   "(the reference path; same values, slower)")
    e.add_argument("--math", default="vector", choices=("vector", "libm"),
                   help="exp/tanh of the compiled observers: vectorised, within 1e-14 of the VM (default), or the C "
                   "library's, bitwise the VM")
    e.add_argument("--threads", type=positive_int, help="worker threads over trials (default: the CPU count)")
    e.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..estimators.ekf import EKF
    from ..evaluation.compiled import Compiler, ekf_estimator, observer_estimator
    from ..evaluation.protocol import Protocol
    from ..evaluation.report import markdown_table, save_scores, score, smape_boxplot
    from ..evaluation.trialcache import TrialCache, cache_root
    from ..observer.codegen import axpy_matvec, fast_kernels

    if args.labels is not None and len(args.labels) != len(args.models):
        raise CommandError(f"--labels: expected one label per model ({len(args.models)}), "
                           f"received {len(args.labels)}")
    levels = {name: getattr(args, name) for name in ("process_std", "measurement_std")
              if getattr(args, name) is not None}
    protocol = Protocol(n_trials=args.trials, seed=args.seed, regime=args.regime,
                        **({} if args.dt is None else {"dt": args.dt}), **levels)
    plant, own_plant = None, plant_of(args)
    observers = [load(model, own_plant, "MODELS") for model in args.models]
    check_dt(protocol.dt, protocol.T, {model: obs.dt for model, obs in zip(args.models, observers)})
    for model, obs in zip(args.models, observers):
        if plant is not None and obs.system.fingerprint != plant.fingerprint:
            raise CommandError(f"MODELS: expected models of one plant, received {model} for {obs.system.name!r} "
                               f"after models for {plant.name!r}")
        plant = obs.system
    noise = NOISE[args.noise]
    kinds = tuple(args.kinds)
    root = Path(args.cache_dir) if args.cache_dir else cache_root()
    trials = TrialCache(None if args.no_cache else root / "trials")
    kernels = {"vector": fast_kernels, "libm": axpy_matvec}[args.math]
    compiler = None if args.vm else Compiler(cache_dir=root / "compiled", postprocess=kernels)
    print(f"trials: {'simulated, not cached' if trials.directory is None else trials.directory}; observers: "
          f"{'CasADi VM' if compiler is None else 'compiled (' + str(compiler.directory) + ')'}", file=sys.stderr)
    scores = []
    _simulate_cells(plant, protocol, noise, kinds, trials)
    for i, (model, obs) in enumerate(zip(args.models, observers)):
        label = args.labels[i] if args.labels else Path(model).resolve().name
        estimator = observer_estimator(obs, compiler=compiler, n_threads=args.threads)
        t0 = time.perf_counter()
        scores.append(score(label, estimator, plant, protocol, noise=noise, kinds=kinds, trials=trials,
                            progress=True))
        print(f"{label}: evaluated in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    for horizon in args.mhe or ():
        scores.append(_mhe_scores(horizon, plant, protocol, noise, kinds, trials))
    if args.ekf:
        ekf = (EKF.for_noise(plant, protocol.dt, process_std=protocol.process_std,
                             measurement_std=protocol.measurement_std) if levels else EKF(plant, protocol.dt))
        estimator = ekf_estimator(ekf, compiler=compiler, n_threads=args.threads)
        t0 = time.perf_counter()
        scores.append(score("EKF", estimator, plant, protocol, noise=noise, kinds=kinds, trials=trials,
                            progress=True))
        print(f"EKF: evaluated in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    print(markdown_table(scores, kinds))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        save_scores(scores, out / f"{plant.name}_scores.json")
        for noisy in noise:
            smape_boxplot(scores, out / f"{plant.name}_smape_{'noisy' if noisy else 'clean'}.png", noisy=noisy,
                          kinds=kinds)
        (out / f"{plant.name}_table.md").write_text(markdown_table(scores, kinds) + "\n")
        print(f"wrote {out}/", file=sys.stderr)
    return 0


def _simulate_cells(plant: System, protocol: Any, noise: tuple, kinds: tuple, trials: Any) -> None:
    """Simulate (or read) every cell's trials, with what CasADi prints about a plant that escapes hidden,
    and say in one line per cell how many trials escaped (they are counted in the table, not scored)."""
    from .flags import quiet_casadi

    for noisy in noise:
        prot = protocol if noisy else protocol.noise_free()
        for kind in kinds:
            with quiet_casadi():
                batch = trials.trials(plant, prot.cell(kind))
            escaped = int((~batch.ok).sum())
            if escaped:
                print(f"{plant.name} {kind} {'noisy' if noisy else 'clean'}: {escaped} of {len(batch.ok)} trials "
                      "escaped (the state left |x| < 1e6 or the integrator failed); the cell is scored on the "
                      f"{len(batch.ok) - escaped} left", file=sys.stderr)


def _mhe_scores(horizon: int, plant: System, protocol: Any, noise: tuple, kinds: tuple, trials: Any) -> Any:
    """The exact-model MHE of ``horizon`` on every cell, weighted by each column's noise levels."""
    from ..estimators.mhe import MHE
    from ..evaluation.compare import MHE_SUBSTEPS
    from ..evaluation.report import MethodScores, score

    label, results = f"MHE N={horizon}", {}
    t0 = time.perf_counter()
    for noisy in noise:
        prot = protocol if noisy else protocol.noise_free()
        mhe = MHE(plant, protocol.dt, horizon, process_std=prot.process_std, measurement_std=prot.measurement_std,
                  substeps=MHE_SUBSTEPS.get(plant.name, 1))
        results.update(score(label, mhe, plant, protocol, noise=(noisy,), kinds=kinds, trials=trials,
                             progress=True).results)
    print(f"{label}: evaluated in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return MethodScores(label, plant.name, results)
