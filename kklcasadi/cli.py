"""The ``kklcasadi`` command line: ``demo``, ``train``, ``evaluate``, ``export``, ``bench``."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from . import signals as sig
from . import systems

__all__ = ["main"]

#: Where the shipped observers live: ``models/`` of the working directory, else of the source tree.
MODEL_ROOTS = (Path.cwd() / "models", Path(__file__).resolve().parent.parent / "models")


def _shipped(system: str, method: str) -> Path:
    for root in MODEL_ROOTS:
        if (root / system / method / "card.json").exists():
            return root / system / method
    raise SystemExit(f"error: no shipped model {system}/{method} under {' or '.join(map(str, MODEL_ROOTS))}; "
                     "run from the repository root or pass --model DIR")


def _observer_estimator(obs):
    return lambda t, y, u: obs.simulate(t, y, u).xhat


def _ekf_estimator(system, dt):
    from .ekf import EKF

    ekf = EKF(system, dt)
    return lambda t, y, u: ekf.simulate(t, y, u).xhat


def cmd_demo(args: argparse.Namespace) -> int:
    """Estimate one noisy trajectory with a shipped observer and the EKF; print SMAPE, write a PNG."""
    from . import metrics
    from .observer import load_observer
    from .report import trajectory_plot
    from .simulate import simulate

    model = Path(args.model) if args.model else _shipped(args.system, args.method)
    obs = load_observer(model)
    plant = obs.system
    if args.input == "zero":
        u = sig.Zero(plant.nu)
    elif args.input == "constant":
        u = sig.Constant(np.full(plant.nu, args.amplitude))
    else:
        u = sig.make(args.input, amplitude=np.full(plant.nu, args.amplitude), omega=args.omega)

    x0 = plant.sample_box(1, args.seed)[0]
    tr = simulate(plant, x0, u, T=args.T, dt=obs.dt, process_std=args.noise, measurement_std=args.noise,
                  seed=args.seed)
    t0 = time.perf_counter()
    est = obs.simulate(tr.t, tr.y, tr.u)
    t_obs = time.perf_counter() - t0
    ekf = _ekf_estimator(plant, obs.dt)(tr.t, tr.y, tr.u)
    print(f"model    {model}  ({obs.method}, system {plant.name}, nz {obs.nz}, window {obs.window})")
    print(f"input    {args.input} (amplitude {args.amplitude}, omega {args.omega} rad/s), noise std {args.noise}, "
          f"x0 {np.round(x0, 3).tolist()}, T {args.T} s")
    print(f"SMAPE    KKL ({obs.method}) {metrics.smape(tr.x, est.xhat):6.2f} %   EKF {metrics.smape(tr.x, ekf):6.2f} %")
    print(f"RMSE t>5 KKL ({obs.method}) {metrics.rmse_after(tr.t, tr.x, est.xhat):6.3f}     "
          f"EKF {metrics.rmse_after(tr.t, tr.x, ekf):6.3f}")
    print(f"time     {t_obs * 1e3:.1f} ms for {len(tr.t)} samples ({t_obs / len(tr.t) * 1e6:.1f} us/step, CasADi VM)")
    out = Path(args.out)
    trajectory_plot(tr.t, tr.x, {f"KKL {obs.method}": est.xhat, "EKF": ekf}, out, u=tr.u,
                    title=f"{plant.name}: {args.input} input, noise std {args.noise}")
    print(f"plot     {out}")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from .train import default_config, train_observer

    overrides = {}
    if args.method == "autonomous" and args.noise is not None:
        overrides["measurement_std"] = args.noise
    if args.method == "autonomous" and args.width is not None:
        overrides["width"] = args.width
    if args.method == "obs" and args.on_inject:
        overrides["model_based_injection"] = True
    config = None if args.method == "inject" else default_config(args.system, args.method, **overrides)
    if args.epochs is not None and config is not None:
        config = _with_epochs(config, args.epochs)
    path = train_observer(args.system, args.method, args.out, config=config, base=args.base, seed=args.seed,
                          device=args.device, resume=args.resume, overwrite=args.overwrite, progress=not args.quiet,
                          threads=args.threads)
    print(f"wrote {path}/weights.npz and card.json")
    return 0


def _with_epochs(config, epochs: int):
    """``config`` with every optimisation stage set to ``epochs`` epochs."""
    from dataclasses import replace

    from .train import LoopConfig

    changes = {}
    for name in ("encoder", "decoder", "loop"):
        loop = getattr(config, name, None)
        if isinstance(loop, LoopConfig):
            changes[name] = replace(loop, epochs=epochs)
    return replace(config, **changes)


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Score model directories (and the EKF) on the PROTOCOL.md cells: table, JSON, box plots.

    Trials come from the on-disk trial cache (simulated once per cell); observers and the EKF run
    as compiled trajectories mapped over the trials (``--vm``: the CasADi VM, same values).
    """
    from .compiled import Compiler, ekf_estimator, observer_estimator
    from .ekf import EKF
    from .observer import load_observer
    from .protocol import Protocol
    from .report import markdown_table, save_scores, score, smape_boxplot
    from .trialcache import TrialCache, cache_root

    if args.labels is not None and len(args.labels) != len(args.models):
        raise SystemExit(f"error: --labels: expected one label per model ({len(args.models)}), "
                         f"received {len(args.labels)}")
    protocol = Protocol(n_trials=args.trials, seed=args.seed, regime=args.regime)
    noise = {"on": (True,), "off": (False,), "both": (False, True)}[args.noise]
    kinds = tuple(args.kinds)
    root = Path(args.cache_dir) if args.cache_dir else cache_root()
    trial_cache = None if args.no_cache else TrialCache(root / "trials")
    compiler = None if args.vm else Compiler(cache_dir=root / "compiled")
    print(f"trials: {'simulated, not cached' if trial_cache is None else trial_cache.directory}; observers: "
          f"{'CasADi VM' if compiler is None else 'compiled (' + str(compiler.directory) + ')'}", file=sys.stderr)
    scores = []
    cache: dict = {}
    plant = None
    for i, model in enumerate(args.models):
        obs = load_observer(model)
        if plant is not None and obs.system.name != plant.name:
            raise SystemExit(f"error: {model} is for {obs.system.name!r}, the other models for {plant.name!r}")
        plant = obs.system
        label = args.labels[i] if args.labels else Path(model).resolve().name
        estimator = observer_estimator(obs, compiler=compiler, n_threads=args.threads)
        t0 = time.perf_counter()
        scores.append(score(label, estimator, plant, protocol, noise=noise, kinds=kinds, cache=cache,
                            trial_cache=trial_cache, progress=True))
        print(f"{label}: evaluated in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    if args.ekf:
        estimator = ekf_estimator(EKF(plant, protocol.dt), compiler=compiler, n_threads=args.threads)
        t0 = time.perf_counter()
        scores.append(score("EKF", estimator, plant, protocol, noise=noise, kinds=kinds, cache=cache,
                            trial_cache=trial_cache, progress=True))
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


def cmd_export(args: argparse.Namespace) -> int:
    from .observer import load_observer

    obs = load_observer(args.model)
    if not (args.c or args.casadi):
        raise SystemExit("error: nothing to export; give --c OUT_DIR and/or --casadi FILE")
    if args.c:
        for path in obs.generate_c(args.c, name=args.name, overwrite=args.overwrite):
            print(f"wrote {path}")
    if args.casadi:
        target = Path(args.casadi)
        if target.exists() and not args.overwrite:
            raise SystemExit(f"error: {target} exists; pass --overwrite to replace it")
        obs.step.save(str(target))
        print(f"wrote {target} (ca.Function.load it: {obs.step.name_in()} -> {obs.step.name_out()})")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from .bench import bench_simulation

    if args.what in ("all", "simulation"):
        print("== data generation: trajectories per second ==")
        bench_simulation(args.system, n_trials=args.trials)
    if args.what in ("all", "observer"):
        from .bench_observer import bench_observer_step

        print("== observer step: generated C vs CasADi VM vs torch eager ==")
        bench_observer_step(args.model or _shipped(args.system, "obs"))
    if args.what in ("all", "training"):
        from .bench import bench_training

        print("== training throughput: samples per second per stage ==")
        bench_training(args.system, device=args.device)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="kklcasadi", description="Learned KKL observers (HyperKKL) in CasADi and C.")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="estimate a noisy run with a shipped observer and the EKF, write a PNG")
    d.add_argument("--system", default="duffing", choices=systems.names())
    d.add_argument("--method", default="inject", help="shipped model under models/SYSTEM/ (default: inject)")
    d.add_argument("--model", help="a model directory instead of a shipped one")
    d.add_argument("--input", default="square", choices=sig.BENCHMARK_KINDS)
    d.add_argument("--amplitude", type=float, default=0.8)
    d.add_argument("--omega", type=float, default=1.0, help="rad/s")
    d.add_argument("--noise", type=float, default=0.1, help="process and measurement noise std (PROTOCOL.md: 0.1)")
    d.add_argument("--T", type=float, default=50.0)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--out", default="demo.png")
    d.set_defaults(func=cmd_demo)

    t = sub.add_parser("train", help="train an observer variant and write its model directory")
    t.add_argument("--system", required=True, choices=systems.names())
    t.add_argument("--method", required=True, choices=("autonomous", "obs", "dyn", "curriculum", "inject"))
    t.add_argument("--out", required=True, help="model directory to write")
    t.add_argument("--base", help="Phase-1 model (default OUT/../autonomous for Phase-2 methods)")
    t.add_argument("--noise", type=float, help="autonomous: train the decoder for this measurement-noise std")
    t.add_argument("--width", type=int, help="autonomous: hidden width of T and T* (default 150; the paper "
                   "uses 350 for rossler and fhn)")
    t.add_argument("--on-inject", action="store_true",
                   help="obs: learn the residual on top of the model-based injection of 'inject'")
    t.add_argument("--epochs", type=int, help="override the number of epochs of every stage")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    t.add_argument("--resume", action="store_true", help="continue from the checkpoints in OUT/.train")
    t.add_argument("--overwrite", action="store_true")
    t.add_argument("--quiet", action="store_true", help="no progress bars")
    t.add_argument("--threads", type=int, help="torch CPU threads (1 per process on a shared machine)")
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("evaluate", help="score models on the PROTOCOL.md benchmark (SMAPE table, box plots)")
    e.add_argument("models", nargs="+", help="model directories (same system)")
    e.add_argument("--labels", nargs="*", help="row labels, one per model (default: the model directories' names)")
    e.add_argument("--trials", type=int, default=100)
    e.add_argument("--noise", default="both", choices=("on", "off", "both"))
    e.add_argument("--kinds", nargs="+", default=list(sig.BENCHMARK_KINDS), choices=sig.BENCHMARK_KINDS)
    e.add_argument("--regime", default="id", choices=sig.REGIMES)
    e.add_argument("--ekf", action="store_true", help="add the EKF baseline")
    e.add_argument("--seed", type=int, default=2026)
    e.add_argument("--out", help="directory for the JSON scores, table and box plots")
    e.add_argument("--cache-dir", help="root of the trial and compiled-code caches (default: $KKLCASADI_CACHE, "
                   "else ~/.cache/kklcasadi)")
    e.add_argument("--no-cache", action="store_true", help="simulate the trials instead of reading/writing the "
                   "trial cache")
    e.add_argument("--vm", action="store_true", help="run the observers in the CasADi VM instead of compiled C "
                   "(the reference path; same values, slower)")
    e.add_argument("--threads", type=int, help="worker threads over trials (default: the CPU count)")
    e.set_defaults(func=cmd_evaluate)

    x = sub.add_parser("export", help="export an observer as C code and/or a serialised CasADi Function")
    x.add_argument("model")
    x.add_argument("--c", metavar="OUT_DIR", help="write C code of the observer step here")
    x.add_argument("--name", default="kkl_obs", help="C name prefix (a C identifier)")
    x.add_argument("--casadi", metavar="FILE", help="write the step as a ca.Function (Function.save)")
    x.add_argument("--overwrite", action="store_true")
    x.set_defaults(func=cmd_export)

    b = sub.add_parser("bench", help="speed benchmarks, each against its alternative in the same run")
    b.add_argument("what", nargs="?", default="all", choices=("all", "simulation", "observer", "training"))
    b.add_argument("--system", default="duffing", choices=systems.names())
    b.add_argument("--model", help="model directory for the observer benchmark")
    b.add_argument("--trials", type=int, default=32)
    b.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where the training benchmark runs")
    b.set_defaults(func=cmd_bench)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
