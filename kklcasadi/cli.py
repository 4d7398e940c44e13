"""The ``kklcasadi`` command line: ``demo``, ``train``, ``evaluate``, ``export``, ``bench``, ``compare``
(the observer beside the EKF and MHE), ``certificate`` (Proposition 1 of the paper for a model).

Every error is one line ``error: ...`` on stderr with exit status 2, naming the command's own
flags (set ``KKLCASADI_DEBUG=1`` to see the traceback instead).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any, NoReturn, Optional, Sequence

import numpy as np

from . import signals as sig
from . import systems, variants
from .systems import System

__all__ = ["main", "build_parser"]

#: Where the shipped observers live: ``models/`` of the working directory, else of the source tree.
MODEL_ROOTS = (Path.cwd() / "models", Path(__file__).resolve().parent.parent / "models")


class CommandError(Exception):
    """A user error of the command line, printed as one line ``error: ...``."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``error: ...`` and exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"error: {message}\n")


def _number(kind: type, lowest: float, strict: bool, what: str):
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, received {text!r}") from None
        if not np.isfinite(value) or value < lowest or (strict and value == lowest):
            raise argparse.ArgumentTypeError(f"expected {what}, received {text!r}")
        return value

    parse.__name__ = what
    return parse


_positive_int = _number(int, 0, True, "a positive integer")
_positive_float = _number(float, 0.0, True, "a positive number")
_nonnegative_float = _number(float, 0.0, False, "a number >= 0")


def _c_name(text: str) -> str:
    from .codegen import check_c_name

    try:
        return check_c_name(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[-1]) from None


def _shipped_models() -> dict[str, list[str]]:
    """The shipped models by system: ``{"duffing": ["autonomous", "inject", ...], ...}``."""
    found: dict[str, list[str]] = {}
    for root in MODEL_ROOTS:
        for card in sorted(root.glob("*/*/card.json")):
            found.setdefault(card.parent.parent.name, [])
            if card.parent.name not in found[card.parent.parent.name]:
                found[card.parent.parent.name].append(card.parent.name)
    return found


def _shipped(system: str, method: str) -> Path:
    for root in MODEL_ROOTS:
        if (root / system / method / "card.json").exists():
            return root / system / method
    shipped = _shipped_models()
    listing = "; ".join(f"{name}: {', '.join(methods)}" for name, methods in shipped.items()) or "none found"
    raise CommandError(f"--system {system} --method {method}: no shipped model models/{system}/{method} "
                       f"(shipped: {listing}); pass --model DIR for another model")


def _plant(args: argparse.Namespace) -> Optional[System]:
    """The plant of ``--plant FILE.py:NAME`` (None without it)."""
    return None if getattr(args, "plant", None) is None else _flagged("--plant", systems.load_plant, args.plant)


def _flagged(flag: str, fn: Any, *fn_args: Any, **kwargs: Any) -> Any:
    """Call ``fn``; a ValueError/TypeError about its argument becomes one about ``flag``."""
    try:
        return fn(*fn_args, **kwargs)
    except (ValueError, TypeError) as exc:
        message = str(exc)
        head, sep, rest = message.partition(": ")
        named = sep and head.isidentifier()         # "argument: expected ..." names a Python argument
        raise CommandError(f"{flag}: {rest}" if named else f"{flag}: {message}") from exc


def _load(model: str | Path, plant: Optional[System], flag: str = "--model") -> Any:
    from .observer import load_observer

    return _flagged(flag, load_observer, model, system=plant)


def _needs_torch(command: str) -> None:
    try:
        import torch  # noqa: F401
    except ImportError:
        raise CommandError(f"{command} needs torch, which is not installed; install the training extra: "
                           "pip install 'kklcasadi[train]'") from None


def _observer_estimator(obs):
    return lambda t, y, u: obs.simulate(t, y, u).xhat


def _ekf_estimator(system, dt):
    from .ekf import EKF

    ekf = EKF(system, dt)
    return lambda t, y, u: ekf.simulate(t, y, u).xhat


def cmd_demo(args: argparse.Namespace) -> int:
    """Estimate one noisy trajectory with a shipped observer and the EKF; print SMAPE, write a PNG."""
    from . import metrics
    from .report import trajectory_plot
    from .simulate import simulate

    if args.model is None and args.plant is not None:
        raise CommandError("--plant: give the model trained for it with --model DIR")
    model = Path(args.model) if args.model else _shipped(args.system or "duffing", args.method)
    obs = _load(model, _plant(args))
    plant = obs.system
    if args.system is not None and args.system != plant.name:
        raise CommandError(f"--system {args.system}: the model {model} is for the system {plant.name!r}; "
                           f"drop --system or pass a model for {args.system!r}")
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
    settle = min(5.0, round(tr.t[-1] / 2, 2))
    print(f"RMSE t>{settle:g} KKL ({obs.method}) {metrics.rmse_after(tr.t, tr.x, est.xhat, settle):6.3f}     "
          f"EKF {metrics.rmse_after(tr.t, tr.x, ekf, settle):6.3f}")
    if est.in_domain is not None:
        print(f"domain   {int(est.in_domain.sum())} of {len(tr.t)} estimates in the domain the maps were trained on")
    print(f"time     {t_obs * 1e3:.1f} ms for {len(tr.t)} samples ({t_obs / len(tr.t) * 1e6:.1f} us/step, CasADi VM)")
    out = Path(args.out)
    trajectory_plot(tr.t, tr.x, {f"KKL {obs.method}": est.xhat, "EKF": ekf}, out, u=tr.u,
                    title=f"{plant.name}: {args.input} input, noise std {args.noise}")
    print(f"plot     {out}")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    if (args.plant is None) == (args.system is None):
        raise CommandError("--system/--plant: give exactly one: a shipped system name or your plant FILE.py:NAME")
    plant = _plant(args) or systems.get(args.system)
    _needs_torch("kklcasadi train")
    from .train import default_config, train_observer

    out = Path(args.out)
    if (out / "card.json").exists() and not (args.overwrite or args.resume):
        raise CommandError(f"--out {out}: a model already exists there; pass --overwrite to replace it")
    overrides = {}
    if args.method == "autonomous" and args.noise is not None:
        overrides["measurement_std"] = args.noise
    if args.method == "autonomous" and args.width is not None:
        overrides["width"] = args.width
    if args.on_inject:
        if args.method != "obs":
            raise CommandError(f"--on-inject: only --method obs takes it, received --method {args.method}")
        overrides["model_based_injection"] = True
    variant = variants.get(args.method)
    config = None if variant.config is None else default_config(plant.name, args.method, **overrides)
    path = _flagged("--" + args.method, train_observer, plant, args.method, out, config=config, base=args.base,
                    seed=args.seed, device=args.device, resume=args.resume, overwrite=args.overwrite,
                    progress=not args.quiet, threads=args.threads, epochs=args.epochs)
    print(f"wrote {path}/weights.npz and card.json")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Score model directories (and the EKF) on the docs/protocol.md cells: table, JSON, box plots.

    Trials come from the on-disk trial cache (simulated once per cell); observers and the EKF run
    as compiled trajectories mapped over the trials, with the vectorised exp/tanh (within 1e-14 of
    the VM; ``--math libm``: bitwise the VM; ``--vm``: the CasADi VM itself).
    """
    from .codegen import axpy_matvec, fast_kernels
    from .compiled import Compiler, ekf_estimator, observer_estimator
    from .ekf import EKF
    from .protocol import Protocol
    from .report import markdown_table, save_scores, score, smape_boxplot
    from .trialcache import TrialCache, cache_root

    if args.labels is not None and len(args.labels) != len(args.models):
        raise CommandError(f"--labels: expected one label per model ({len(args.models)}), "
                           f"received {len(args.labels)}")
    protocol = Protocol(n_trials=args.trials, seed=args.seed, regime=args.regime)
    noise = {"on": (True,), "off": (False,), "both": (False, True)}[args.noise]
    kinds = tuple(args.kinds)
    root = Path(args.cache_dir) if args.cache_dir else cache_root()
    trial_cache = None if args.no_cache else TrialCache(root / "trials")
    kernels = {"vector": fast_kernels, "libm": axpy_matvec}[args.math]
    compiler = None if args.vm else Compiler(cache_dir=root / "compiled", postprocess=kernels)
    print(f"trials: {'simulated, not cached' if trial_cache is None else trial_cache.directory}; observers: "
          f"{'CasADi VM' if compiler is None else 'compiled (' + str(compiler.directory) + ')'}", file=sys.stderr)
    scores = []
    cache: dict = {}
    plant, own_plant = None, _plant(args)
    for i, model in enumerate(args.models):
        obs = _load(model, own_plant, "MODELS")
        if plant is not None and obs.system.fingerprint != plant.fingerprint:
            raise CommandError(f"MODELS: expected models of one plant, received {model} for {obs.system.name!r} "
                               f"after models for {plant.name!r}")
        plant = obs.system
        label = args.labels[i] if args.labels else Path(model).resolve().name
        estimator = observer_estimator(obs, compiler=compiler, n_threads=args.threads)
        t0 = time.perf_counter()
        scores.append(score(label, estimator, plant, protocol, noise=noise, kinds=kinds, cache=cache,
                            trial_cache=trial_cache, progress=True))
        print(f"{label}: evaluated in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    for horizon in args.mhe or ():
        scores.append(_mhe_scores(horizon, plant, protocol, noise, kinds, cache, trial_cache))
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


def _mhe_scores(horizon: int, plant: System, protocol: Any, noise: tuple, kinds: tuple, cache: dict,
                trial_cache: Any) -> Any:
    """The exact-model MHE of ``horizon`` on every cell, weighted by each column's noise levels."""
    from .mhe import MHE
    from .pipelines import MHE_SUBSTEPS
    from .report import MethodScores, score

    label, results = f"MHE N={horizon}", {}
    t0 = time.perf_counter()
    for noisy in noise:
        prot = protocol if noisy else protocol.noise_free()
        mhe = MHE(plant, protocol.dt, horizon, process_std=prot.process_std, measurement_std=prot.measurement_std,
                  substeps=MHE_SUBSTEPS.get(plant.name, 1))
        results.update(score(label, mhe, plant, protocol, noise=(noisy,), kinds=kinds, cache=cache,
                             trial_cache=trial_cache, progress=True).results)
    print(f"{label}: evaluated in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return MethodScores(label, plant.name, results)


def cmd_export(args: argparse.Namespace) -> int:
    if not (args.c or args.casadi):
        raise CommandError("export: nothing to export; give --c OUT_DIR and/or --casadi FILE")
    obs = _load(args.model, _plant(args), "MODEL")
    if args.c:
        existing = Path(args.c)
        if existing.exists() and any(existing.iterdir()) and not args.overwrite:
            raise CommandError(f"--c {existing}: the directory is not empty; pass --overwrite to replace its files")
        for path in obs.generate_c(args.c, name=args.name, overwrite=args.overwrite):
            print(f"wrote {path}")
    if args.casadi:
        target = Path(args.casadi)
        if target.exists() and not args.overwrite:
            raise CommandError(f"--casadi {target}: the file exists; pass --overwrite to replace it")
        obs.step.save(str(target))
        print(f"wrote {target} (ca.Function.load it: {obs.step.name_in()} -> {obs.step.name_out()})")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from .bench.simulation import bench_simulation

    if args.what in ("observer", "training"):
        _needs_torch(f"kklcasadi bench {args.what} (it times torch beside CasADi)")
    if args.what in ("all", "simulation"):
        print("== data generation: trajectories per second ==")
        bench_simulation(args.system, n_trials=args.trials or 32)
    if args.what in ("all", "observer"):
        from .bench.observer_step import bench_observer_step

        print("== observer step: generated C vs CasADi VM vs torch eager ==")
        bench_observer_step(args.model or _shipped(args.system, "obs"))
    if args.what in ("all", "training"):
        from .bench.training import bench_training

        print("== training throughput: samples per second per stage ==")
        bench_training(args.system, device=args.device, threads=args.threads)
        if "autonomous" in _shipped_models().get(args.system, []):
            from .bench.training import bench_phase2_epoch

            print("== one default Phase-2 epoch: validation on all held-out samples vs the default subset ==")
            bench_phase2_epoch(args.system, _shipped(args.system, "autonomous"), device=args.device,
                               threads=args.threads)
    if args.what in ("all", "protocol"):
        from .bench.protocol import bench_protocol

        print("== the full protocol of one system: trial cache, compiled observers, the VM beside them ==")
        print(_flagged("--system", bench_protocol, args.system, n_trials=args.trials or 100).table())
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="kklcasadi", description="Learned KKL observers (HyperKKL) in CasADi and C.")
    sub = p.add_subparsers(dest="command", required=True)
    plant_help = "your plant: FILE.py:NAME or MODULE:NAME, NAME a kklcasadi.System or a function returning one"

    d = sub.add_parser("demo", help="estimate a noisy run with a shipped observer and the EKF, write a PNG")
    d.add_argument("--system", choices=systems.names(), help="shipped system (default duffing)")
    d.add_argument("--method", default="bank",
                   help="shipped model under models/SYSTEM/ (default: bank, the observer fit for noisy measurements)")
    d.add_argument("--model", help="a model directory instead of a shipped one")
    d.add_argument("--plant", help=plant_help + " (with --model)")
    d.add_argument("--input", default="square", choices=sig.BENCHMARK_KINDS)
    d.add_argument("--amplitude", type=_nonnegative_float, default=0.8)
    d.add_argument("--omega", type=_positive_float, default=1.0, help="rad/s")
    d.add_argument("--noise", type=_nonnegative_float, default=0.1,
                   help="process and measurement noise std (docs/protocol.md: 0.1)")
    d.add_argument("--T", type=_positive_float, default=50.0, help="horizon, seconds")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--out", default="demo.png")
    d.set_defaults(func=cmd_demo)

    t = sub.add_parser("train", help="train an observer variant and write its model directory")
    t.add_argument("--system", choices=systems.names(), help="a shipped system")
    t.add_argument("--plant", help=plant_help)
    t.add_argument("--method", required=True, choices=variants.trainable(),
                   help="; ".join(f"{v.name}: {v.summary}" for v in variants.VARIANTS.values()))
    t.add_argument("--out", required=True, help="model directory to write")
    t.add_argument("--base", help="Phase-1 model (default OUT/../autonomous for Phase-2 methods)")
    t.add_argument("--noise", type=_nonnegative_float,
                   help="autonomous: train the decoder for this measurement-noise std")
    t.add_argument("--width", type=_positive_int, help="autonomous: hidden width of T and T* (default 150; the "
                   "paper uses 350 for rossler and fhn)")
    t.add_argument("--on-inject", action="store_true",
                   help="obs: learn the residual on top of the model-based injection of 'inject'")
    t.add_argument("--epochs", type=_positive_int, help="override the number of epochs of every stage")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    t.add_argument("--resume", action="store_true", help="continue from the checkpoints in OUT/.train")
    t.add_argument("--overwrite", action="store_true")
    t.add_argument("--quiet", action="store_true", help="no progress bars")
    t.add_argument("--threads", type=_positive_int, help="torch CPU threads (1 per process on a shared machine)")
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("evaluate", help="score models on the docs/protocol.md benchmark (SMAPE table, box plots)")
    e.add_argument("models", nargs="+", help="model directories (same system)")
    e.add_argument("--labels", nargs="*", help="row labels, one per model (default: the model directories' names)")
    e.add_argument("--trials", type=_positive_int, default=100)
    e.add_argument("--plant", help=plant_help + " (for models of a plant that kklcasadi does not ship)")
    e.add_argument("--noise", default="both", choices=("on", "off", "both"))
    e.add_argument("--kinds", nargs="+", default=list(sig.BENCHMARK_KINDS), choices=sig.BENCHMARK_KINDS)
    e.add_argument("--regime", default="id", choices=sig.REGIMES)
    e.add_argument("--ekf", action="store_true", help="add the EKF baseline")
    e.add_argument("--mhe", nargs="+", type=_positive_int, metavar="N",
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
    e.add_argument("--threads", type=_positive_int, help="worker threads over trials (default: the CPU count)")
    e.set_defaults(func=cmd_evaluate)

    x = sub.add_parser("export", help="export an observer as C code and/or a serialised CasADi Function")
    x.add_argument("model", metavar="MODEL")
    x.add_argument("--plant", help=plant_help + " (for a model of a plant that kklcasadi does not ship)")
    x.add_argument("--c", metavar="OUT_DIR", help="write C code of the observer step here")
    x.add_argument("--name", type=_c_name, default="kkl_obs", help="C name prefix (a C identifier)")
    x.add_argument("--casadi", metavar="FILE", help="write the step as a ca.Function (Function.save)")
    x.add_argument("--overwrite", action="store_true")
    x.set_defaults(func=cmd_export)

    b = sub.add_parser("bench", help="speed benchmarks, each against its alternative in the same run")
    b.add_argument("what", nargs="?", default="all", choices=("all", "simulation", "observer", "training", "protocol"))
    b.add_argument("--system", default="duffing", choices=systems.names())
    b.add_argument("--model", help="model directory for the observer benchmark")
    b.add_argument("--trials", type=_positive_int,
                   help="trials: simulation benchmark (default 32), protocol benchmark per cell (default 100)")
    b.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where the training benchmark runs")
    b.add_argument("--threads", type=_positive_int, help="torch CPU threads of the training benchmarks")
    b.set_defaults(func=cmd_bench)

    from .certificate import add_certificate_parser
    from .pipelines import add_compare_parser

    add_compare_parser(sub)        # kklcasadi compare  [--systems ...] [--trials 100] [--out results/estimators]
    add_certificate_parser(sub)    # kklcasadi certificate MODEL... [--kinds zero] [--json FILE]
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; a user error prints one line ``error: ...`` and returns 2."""
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (CommandError, ValueError, TypeError, FileExistsError, FileNotFoundError) as exc:
        if os.environ.get("KKLCASADI_DEBUG"):
            raise
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
