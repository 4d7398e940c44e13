"""``kklcasadi bench``: speed benchmarks, each against its alternative in the same run."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional

from ..model.shipped import shipped as shipped_listing
from .flags import CommandError, add_system, flagged, needs_torch, nonnegative_int, positive_int, shipped, stamp_of


def add_parser(sub: argparse._SubParsersAction) -> None:
    b = sub.add_parser("bench", help="speed benchmarks, each against its alternative in the same run")
    b.add_argument("what", nargs="?", default="all",
                   choices=("all", "simulation", "observer", "training", "protocol", "scaling"),
                   help="which benchmark ('all' is every one but scaling, which trains an observer per size)")
    add_system(b, with_models=False, what="the system benchmarked (default duffing; the observer and protocol "
               "benchmarks need its shipped models)", default="duffing")
    b.add_argument("--model", nargs="+", help="observer benchmark: model directories or shipped models by name "
                   "SYSTEM/METHOD (default: the system's shipped obs)")
    b.add_argument("--write", metavar="OUT_MD",
                   help="observer or protocol benchmark: also write its tables, stamped, to OUT_MD, a markdown file "
                   "(the observer benchmark: the step figures of each model, microseconds per step of the C builds "
                   "and the CasADi VM and the default build's instructions, with its card's digest; the protocol "
                   "benchmark: what it prints; results/speed/SYSTEM/ is what docs/results/speed.md reads)")
    b.add_argument("--overwrite", action="store_true", help="with --write: replace OUT_MD if it exists; with "
                   "scaling's --out: replace its files")
    b.add_argument("--models", nargs="+", help="protocol benchmark: model directories (default: the shipped ones)")
    b.add_argument("--trials", type=positive_int,
                   help="trials: simulation benchmark (default 32), protocol benchmark per cell (default 100), "
                        "scaling benchmark's accuracy (default 10)")
    b.add_argument("--sizes", type=positive_int, nargs="+", default=[1, 2, 4, 8, 16, 32],
                   help="scaling benchmark: chain lengths n, nx = 2n (default 1 2 4 8 16 32)")
    b.add_argument("--runs", type=positive_int, default=200,
                   help="scaling benchmark: training runs of the observer (default 200)")
    b.add_argument("--epochs", type=positive_int, default=10,
                   help="scaling benchmark: training epochs of the observer (default 10)")
    b.add_argument("--out", help="scaling benchmark: where to write scaling.md and scaling.png")
    b.add_argument("--vm-trials", type=positive_int, default=4,
                   help="protocol benchmark: trials per cell also run in the CasADi VM (default 4)")
    b.add_argument("--plain-trials", type=nonnegative_int, default=10,
                   help="protocol benchmark: trials per cell also run with the plain observer step folded, 1000 steps "
                   "per trial (default 10; 0: not timed)")
    b.add_argument("--instructions", action="store_true",
                   help="protocol benchmark: count the instructions per trial with valgrind (repeatable on a loaded "
                   "machine; about a minute per method)")
    b.add_argument("--no-ekf", action="store_true", help="protocol benchmark: leave the EKF out")
    b.add_argument("--flags", help="protocol benchmark: C compiler flags, one string (default '-O3 "
                                   "-ffp-contract=off'; write --flags='-O2')")
    b.add_argument("--math", default="vector", choices=("vector", "libm"),
                   help="protocol benchmark: exp/tanh of the compiled code, vectorised (default) or the C library's")
    b.add_argument("--matvec", default="axpy", choices=("axpy", "casadi"),
                   help="protocol benchmark: the axpy mat-vec kernels (default) or CasADi's own loops (with --math "
                   "libm)")
    b.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where the training benchmark runs")
    b.add_argument("--threads", type=positive_int,
                   help="training and scaling benchmarks: torch CPU threads; protocol benchmark: worker threads over "
                   "trials and C compilers at a time")
    b.set_defaults(func=run)


def _compiler(args: argparse.Namespace):
    from ..evaluation.compiled import DEFAULT_FLAGS, Compiler
    from ..observer.codegen import axpy_matvec, fast_kernels

    if args.matvec == "casadi" and args.math == "vector":
        raise CommandError("--matvec casadi: CasADi's own loops keep the C library's exp/tanh; pass --math libm")
    hook = {("axpy", "vector"): fast_kernels, ("axpy", "libm"): axpy_matvec, ("casadi", "libm"): None}
    flags = DEFAULT_FLAGS if args.flags is None else tuple(args.flags.split())
    return flagged("--flags", Compiler, flags=flags, postprocess=hook[(args.matvec, args.math)])


def _bench_observer(args: argparse.Namespace) -> None:
    """The observer step of each ``--model``; with ``--write`` its figures as a stamped table."""
    import os

    from ..evaluation.bench.observer_step import bench_observer_step, card_digest, step_table
    from ..model.shipped import is_shipped, resolve

    out = _write_target(args)
    results = []
    for given in args.model or [shipped(args.system, "obs")]:
        path = flagged("--model", resolve, given)
        print(f"== observer step of {given}: generated C vs CasADi VM vs torch eager ==")
        name = "/".join(path.resolve().parts[-2:]) if is_shipped(path) else str(given)
        results.append((name, card_digest(path), bench_observer_step(path)))
    if out is not None:
        _write(args, out, step_table(results, os.getloadavg()))


def _write_target(args: argparse.Namespace) -> Optional[Path]:
    """``--write``'s file, refused before any work where it exists without ``--overwrite``."""
    if args.write is None:
        return None
    out = Path(args.write)
    if out.is_dir() or (out.exists() and not args.overwrite):
        what = "a directory" if out.is_dir() else "exists; pass --overwrite to replace it"
        raise CommandError(f"--write: {out} {what}")
    return out


def _write(args: argparse.Namespace, out: Path, table: str, **seeds: int) -> None:
    """``table`` under the stamp of this command (``seeds`` by role, of what it drew), written atomically to ``out``."""
    from ..provenance import markdown
    from ..writes import write_file

    flagged("--write", write_file, out, markdown(table, stamp_of(args, **seeds)), overwrite=args.overwrite,
            argument="--write")
    print(f"wrote {out}")


def run(args: argparse.Namespace) -> int:
    from ..evaluation.bench.simulation import bench_simulation

    if args.write is not None and args.what not in ("observer", "protocol"):
        raise CommandError(f"--write: the observer and protocol benchmarks write a table; received the {args.what!r} "
                           "benchmark (name observer or protocol)")
    if args.what in ("observer", "training", "scaling"):
        needs_torch(f"kklcasadi bench {args.what} (it times torch beside CasADi, or trains)")
    if args.what == "scaling":
        from ..evaluation.bench.scaling import bench_scaling

        print("== the cost as the plant grows: chains of coupled oscillators ==")
        result = flagged("--sizes", bench_scaling, args.sizes, runs=args.runs, epochs=args.epochs,
                         trials=args.trials or 10, threads=args.threads or 1, out=args.out,
                         stamp=stamp_of(args, training_and_trials=0), overwrite=args.overwrite, argument="--out")
        print(result.table())
        return 0
    if args.what in ("all", "simulation"):
        print("== data generation: trajectories per second ==")
        bench_simulation(args.system, n_trials=args.trials or 32)
    if args.what in ("all", "observer"):
        _bench_observer(args)
    if args.what in ("all", "training"):
        from ..evaluation.bench.training import bench_phase2_epoch, bench_training

        print("== training throughput: samples per second per stage ==")
        bench_training(args.system, device=args.device, threads=args.threads)
        if "autonomous" in shipped_listing().get(args.system, []):
            print("== one default Phase-2 epoch: validation on all held-out samples vs the default subset ==")
            bench_phase2_epoch(args.system, shipped(args.system, "autonomous"), device=args.device,
                               threads=args.threads)
    if args.what in ("all", "protocol"):
        from ..evaluation.bench.protocol import bench_protocol

        out = _write_target(args)

        print("== the full protocol of one system, cold and warm caches: every method, the plain step and the VM "
              "beside them ==")
        result = flagged("--system", bench_protocol, args.system, models=args.models, n_trials=args.trials or 100,
                         vm_trials=args.vm_trials, plain_trials=args.plain_trials, ekf=not args.no_ekf,
                         compiler=_compiler(args), n_threads=args.threads, instructions=args.instructions)
        print(result.table())
        if out is not None:
            from ..evaluation.protocol import Protocol

            _write(args, out, result.table(), trials=Protocol().seed)      # the protocol's trials, its seed
    return 0
