"""``kklcasadi evaluate``: score model directories (and the EKF, the particle filter, the MHE) on the
docs/protocol.md cells.

Trials come from the on-disk trial cache (simulated once per cell, while the C compiler builds the
estimators); observers, the EKF and the particle filter run as compiled code mapped over the trials
on threads, with the vectorised exp/tanh and, where the CPU has FMA, mat-vecs summed with fused
multiply-adds (within 1e-12 (1 + |VM|) of the VM, ``FUSED_TOLERANCE``; ``--math libm``: bitwise the VM;
``--vm``: the CasADi VM itself). An observer sees the noise-free and noisy cells of a regime in one
call, so that the work its inputs alone decide is done once for both (the same scores).
``--profile`` prints where the time went.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from ..plant import signals as sig
from ..plant.systems import System
from ..writes import refuse_existing
from .flags import (
    NOISE,
    CommandError,
    add_cache,
    add_dt,
    add_kinds,
    add_noise,
    add_noise_levels,
    add_plant,
    add_roughening,
    check_dt,
    load,
    out_path,
    plant_of,
    positive_int,
    stamp_of,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("evaluate", help="score models on the docs/protocol.md benchmark (SMAPE table, box plots)")
    e.add_argument("models", nargs="+", metavar="MODELS",
                   help="model directories (same system), or shipped models by name SYSTEM/METHOD (e.g. vdp/bank)")
    e.add_argument("--labels", nargs="*", help="row labels, one per model (default: the model directories' names)")
    e.add_argument("--trials", type=positive_int, default=100, help="trials per cell (docs/protocol.md: 100)")
    add_plant(e, "for models of a plant that kklcasadi does not ship")
    add_noise(e)
    add_kinds(e)
    e.add_argument("--regime", default="id", choices=sig.REGIMES,
                   help="the input parameters' ranges (docs/protocol.md): id, the benchmark's (default), or ood")
    add_dt(e, "the protocol's sample time (default 0.05, docs/protocol.md); the models' must equal it")
    add_noise_levels(e, "the noisy column's and the EKF's and MHE's (default docs/protocol.md's 0.1)")
    e.add_argument("--ekf", action="store_true", help="add the EKF baseline")
    e.add_argument("--pf", type=positive_int, metavar="N",
                   help="add the bootstrap particle filter with N particles (row 'PF N=...'; the protocol's noise "
                   "levels, 4 RK4 steps per sample on fhn and rossler, on a plant of yours the fewest that are "
                   "stable over its box). Noisy cells only: the noise-free cells are skipped (its likelihood needs "
                   "measurement noise)")
    add_roughening(e)
    e.add_argument("--mhe", nargs="+", type=positive_int, metavar="N",
                   help="add the exact-model MHE with these horizons (one ipopt solve per sample: slow)")
    e.add_argument("--seed", type=int, default=2026, help="seed of the trials (docs/protocol.md's scored trials: "
                   "2026; choose on another)")
    e.add_argument("--out", help="directory for the JSON scores, table and box plots (refused where they exist)")
    e.add_argument("--consistency", action="store_true",
                   help="also score the covariances on the noisy cells (issue 49): the models' covariance heads "
                   "and, with --ekf and --pf, the EKF's and the particle filter's own, by mean NEES against the "
                   "chi-square band, 1- and 2-sigma coverage per state and the log-likelihood of the truth "
                   "(table; a markdown and a JSON file named after the plant under --out)")
    add_cache(e)
    e.add_argument("--vm", action="store_true", help="run the observers in the CasADi VM instead of compiled C "
                   "(the reference path; same values, slower)")
    e.add_argument("--math", default="vector", choices=("vector", "libm"),
                   help="arithmetic of the compiled observers: vectorised exp/tanh and fused multiply-adds in the "
                   "mat-vecs, within 1e-12 of the VM (default), or the C library's exp/tanh and unfused sums, "
                   "bitwise the VM")
    e.add_argument("--threads", type=positive_int, help="worker threads over trials and C compilers at a time "
                   "(default: the CPU count)")
    e.add_argument("--profile", action="store_true", help="print where the time went (compile, simulate or read "
                   "the trials, estimate, score: wall and CPU seconds) and the machine's load")
    e.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..estimators.ekf import EKF
    from ..estimators.pf import SUBSTEPS
    from ..evaluation.compiled import Compiler, ekf_estimator, observer_estimator, pf_estimator, precompile
    from ..evaluation.protocol import Profile, Protocol
    from ..evaluation.report import markdown_table, save_scores, score, smape_boxplot
    from ..evaluation.trialcache import TrialCache, cache_root
    from ..observer.codegen import axpy_matvec, fast_kernels
    from ..plant.rk4 import substeps_for

    wall, cpu, load_start = time.perf_counter(), time.process_time(), os.getloadavg()
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
    if args.pf and True not in noise:
        raise CommandError("--pf: the particle filter runs on the noisy cells only; pass --noise on or both")
    if args.consistency:
        if True not in noise:
            raise CommandError("--consistency: the covariances are scored on the noisy cells; pass --noise on or both")
        if not (args.ekf or args.pf or any(obs.covariance is not None for obs in observers)):
            raise CommandError("--consistency: expected a model with a covariance head (architecture.covariance), "
                               "--ekf or --pf, received none of them")
    out = out_path(args.out, "--out", directory=True)
    if out is not None:                      # the report's files, refused before any run: never written over
        parts = ["scores.json", "table.md", *(f"smape_{'noisy' if n else 'clean'}.png" for n in noise),
                 *(("consistency.md", "consistency.json") if args.consistency else ())]
        refuse_existing({out / f"{observers[0].system.name}_{part}": "--out" for part in parts})
    kinds = tuple(args.kinds)
    root = Path(args.cache_dir) if args.cache_dir else cache_root()
    trials = TrialCache(None if args.no_cache else root / "trials")
    kernels = {"vector": fast_kernels, "libm": axpy_matvec}[args.math]
    compiler = None if args.vm else Compiler(cache_dir=root / "compiled", postprocess=kernels)
    profile = Profile() if args.profile else None
    print(f"trials: {'simulated, not cached' if trials.directory is None else trials.directory}; observers: "
          f"{'CasADi VM' if compiler is None else 'compiled (' + str(compiler.directory) + ')'}", file=sys.stderr)
    rows: list[tuple[str, Any]] = []                  # (label, estimator of any kind)
    for i, (model, obs) in enumerate(zip(args.models, observers)):
        label = args.labels[i] if args.labels else Path(model).resolve().name
        if args.consistency and obs.covariance is not None:   # one run gives the SMAPE and the covariance
            from ..evaluation.uncertainty import RecordedObserver

            rows.append((label, RecordedObserver(obs, compiler=compiler, n_threads=args.threads)))
        else:
            rows.append((label, observer_estimator(obs, compiler=compiler, n_threads=args.threads, profile=profile)))
    if args.ekf:
        ekf = (EKF.for_noise(plant, protocol.dt, process_std=protocol.process_std,
                             measurement_std=protocol.measurement_std) if levels else EKF(plant, protocol.dt))
        rows.append(("EKF", ekf_estimator(ekf, compiler=compiler, n_threads=args.threads, profile=profile)))
    cells = [(protocol if noisy else protocol.noise_free()).cell(kind) for noisy in noise for kind in kinds]
    precompile([getattr(est, "record", est) for _, est in rows], cells[0].shape()[1], groups=(len(noise),),
               jobs=args.threads,
               meanwhile=lambda: _read_cells(plant, cells, trials, profile))
    scores = []
    for label, estimator in rows:
        t0 = time.perf_counter()
        scores.append(score(label, estimator, plant, protocol, noise=noise, kinds=kinds, trials=trials,
                            progress=True, profile=profile))
        print(f"{label}: evaluated in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    if args.pf:
        t0 = time.perf_counter()
        pf = pf_estimator(plant, protocol.dt, compiler=compiler, n_threads=args.threads, profile=profile,
                          n_particles=args.pf, process_std=protocol.process_std,
                          measurement_std=protocol.measurement_std, substeps=substeps_for(plant, protocol.dt, SUBSTEPS),
                          roughening=args.pf_roughening, seed=protocol.seed)
        scores.append(score(f"PF N={args.pf}", pf, plant, protocol, noise=(True,), kinds=kinds, trials=trials,
                            progress=True, profile=profile))
        print(f"PF N={args.pf}: evaluated in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    for horizon in args.mhe or ():
        scores.append(_mhe_scores(horizon, plant, protocol, noise, kinds, trials))
    print(markdown_table(scores, kinds))
    uncertainty = None
    if args.consistency:
        from ..evaluation.uncertainty import RecordedObserver, filter_uncertainty, score_uncertainty, uncertainty_table

        estimators: list[tuple[str, Any]] = [(label, est.uncertain) for label, est in rows
                                             if isinstance(est, RecordedObserver)]
        if args.ekf:
            estimators.append(("EKF", filter_uncertainty(ekf)))
        if args.pf:
            estimators.append((f"PF N={args.pf}", filter_uncertainty(pf)))
        t0 = time.perf_counter()
        uncertainty = score_uncertainty(estimators, plant, [protocol.cell(kind) for kind in kinds], trials=trials)
        print(f"covariances scored in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        print("\n" + uncertainty_table(uncertainty))
    if out is not None:
        from ..provenance import markdown
        from ..writes import staged

        stamp = stamp_of(args, trials=args.seed)
        with staged(out, argument="--out") as stage:     # the report's files as one, exclusively
            save_scores(scores, stage / f"{plant.name}_scores.json", stamp=stamp)
            for noisy in noise:
                smape_boxplot(scores, stage / f"{plant.name}_smape_{'noisy' if noisy else 'clean'}.png", noisy=noisy,
                              kinds=kinds, stamp=stamp)
            (stage / f"{plant.name}_table.md").write_text(markdown(markdown_table(scores, kinds) + "\n", stamp))
            if uncertainty is not None:
                from ..evaluation.uncertainty import uncertainty_record, uncertainty_table
                from ..provenance import json_record

                (stage / f"{plant.name}_consistency.md").write_text(
                    markdown(uncertainty_table(uncertainty) + "\n", stamp))
                (stage / f"{plant.name}_consistency.json").write_text(
                    json.dumps(json_record(uncertainty_record(uncertainty), stamp), indent=1) + "\n")
        print(f"wrote {out}/", file=sys.stderr)
    if profile is not None:
        children = os.times()
        print(f"\nwhere the time went ({os.cpu_count()} CPUs; load average {load_start[0]:.2f} at the start, "
              f"{os.getloadavg()[0]:.2f} at the end; CPU: this process, its threads and the C compiler):",
              file=sys.stderr)
        print(profile.table(time.perf_counter() - wall,
                            time.process_time() - cpu + children.children_user + children.children_system),
              file=sys.stderr)
    return 0


def _read_cells(plant: System, cells: list, trials: Any, profile: Any) -> None:
    """Read (or simulate and store) every cell's trials, with what CasADi prints about a plant that
    escapes hidden, and say in one line per cell how many trials escaped (they are counted in the
    table, not scored)."""
    from ..evaluation.protocol import read_cells
    from .flags import quiet_casadi

    with quiet_casadi():
        batches = read_cells(plant, cells, trials, profile=profile)
    for cell, batch in zip(cells, batches):
        escaped = int((~batch.ok).sum())
        if escaped:
            print(f"{plant.name} {cell.kind} {'noisy' if cell.protocol.noisy else 'clean'}: {escaped} of "
                  f"{len(batch.ok)} trials escaped (the state left |x| < 1e6 or the integrator failed); the cell "
                  f"is scored on the {len(batch.ok) - escaped} left", file=sys.stderr)


def _mhe_scores(horizon: int, plant: System, protocol: Any, noise: tuple, kinds: tuple, trials: Any) -> Any:
    """The exact-model MHE of ``horizon`` on every cell, weighted by each column's noise levels."""
    from ..estimators.mhe import MHE
    from ..evaluation.compare import MHE_SUBSTEPS
    from ..evaluation.report import MethodScores, score
    from ..plant.rk4 import substeps_for

    label, results = f"MHE N={horizon}", {}
    t0 = time.perf_counter()
    for noisy in noise:
        prot = protocol if noisy else protocol.noise_free()
        mhe = MHE(plant, protocol.dt, horizon, process_std=prot.process_std, measurement_std=prot.measurement_std,
                  substeps=substeps_for(plant, protocol.dt, MHE_SUBSTEPS))
        results.update(score(label, mhe, plant, protocol, noise=(noisy,), kinds=kinds, trials=trials,
                             progress=True).results)
    print(f"{label}: evaluated in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return MethodScores(label, plant.name, results)
