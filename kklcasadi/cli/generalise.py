"""``kklcasadi generalise``: score models on inputs and noise levels they were not fit on (docs/protocol.md
"Generalisation"), beside the EKF (and the particle filter) on the same trials, with the domain monitor.

Trials come from the trial cache; observers and the EKF run compiled (``--vm``: the CasADi VM).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from ..plant import signals as sig
from .flags import (
    CommandError,
    add_cache,
    add_plant,
    add_roughening,
    benchmark_caches,
    labelled_models,
    plant_of,
    positive_float,
    positive_int,
    stamp_of,
)

#: ``--regimes`` choices: the protocol's ``id`` and ``ood`` ranges, and the held-out families' ranges.
REGIMES = ("id", "ood", "held_out")


def add_parser(sub: argparse._SubParsersAction) -> None:
    g = sub.add_parser("generalise", help="score models on input families, ranges and noise levels they were not fit "
                                          "on, beside the EKF (and PF), with the domain monitor's precision and recall")
    g.add_argument("models", nargs="+", metavar="MODELS",
                   help="model directories (same system), or shipped models by name SYSTEM/METHOD (e.g. vdp/bank)")
    g.add_argument("--labels", nargs="*", help="row labels, one per model (default: the model directories' names)")
    g.add_argument("--families", nargs="+", default=list(sig.FAMILIES), choices=sig.FAMILIES,
                   help="input families (default: all: the benchmark's four, chirp, random steps, feedback)")
    g.add_argument("--regimes", nargs="+", default=list(REGIMES), choices=REGIMES,
                   help="parameter ranges: the protocol's id and ood ranges, the held-out families' ranges "
                   "(default: all)")
    g.add_argument("--noise-levels", nargs="+", type=positive_float, default=[0.05, 0.1, 0.2], metavar="STD",
                   help="process and measurement noise std of the cases (default: 0.05 0.1 0.2)")
    g.add_argument("--trials", type=positive_int, default=100, help="trials per case (default 100)")
    g.add_argument("--pf", type=positive_int, metavar="N", help="add the particle filter with N particles")
    add_roughening(g)
    add_plant(g, "for models of a plant that kklcasadi does not ship")
    g.add_argument("--seed", type=int, default=2026, help="seed of the trials (docs/protocol.md: 2026)")
    g.add_argument("--out", help="directory for the JSON report and the markdown tables")
    add_cache(g)
    g.add_argument("--vm", action="store_true", help="run the observers and the EKF in the CasADi VM instead of "
                   "compiled C")
    g.add_argument("--threads", type=positive_int, help="worker threads over trials (default: the CPU count)")
    g.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..evaluation import generalisation as gen

    case_list = gen.cases(args.families, args.noise_levels, args.regimes)
    if not case_list:
        raise CommandError(f"--families, --regimes: no case: the families {args.families} have no regime among "
                           f"{args.regimes} (chirp, random and feedback are held_out; zero is id)")
    trials, compiler = benchmark_caches(args)
    observers = labelled_models(args, plant_of(args))
    settings = gen.Settings(n_trials=args.trials, seed=args.seed)
    t0 = time.perf_counter()
    report = gen.run(observers, case_list, settings, trials=trials, pf_particles=args.pf,
                     pf_roughening=args.pf_roughening, compiler=compiler, n_threads=args.threads, progress=True)
    print(f"{len(case_list)} cases x {args.trials} trials in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    tables = report.markdown() + "\n\nDomain monitor:\n\n" + report.monitor_markdown()
    print(tables)
    if args.out:
        from ..provenance import json_record, markdown

        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        stamp = stamp_of(args, trials=args.seed)
        (out / f"{report.system}_generalisation.md").write_text(markdown(tables + "\n", stamp))
        (out / f"{report.system}_generalisation.json").write_text(
            json.dumps(json_record(report.to_json(), stamp), indent=1) + "\n")
        print(f"wrote {out}/", file=sys.stderr)
    return 0
