"""``kklcasadi generalise``: score models on inputs and noise levels they were not fit on (docs/protocol.md
"Generalisation"), beside the EKF (and the particle filter) on the same trials, with the domain monitor.

Trials come from the trial cache; observers and the EKF run compiled (``--vm``: the CasADi VM).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from ..plant import signals as sig
from ..writes import refuse_existing, write_dir
from .flags import (
    CommandError,
    add_cache,
    add_plant,
    add_roughening,
    benchmark_caches,
    labelled_models,
    out_path,
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
    g.add_argument("--out", help="directory for the JSON report and the markdown tables (refused where they exist)")
    g.add_argument("--consistency", action="store_true",
                   help="also score the covariances (issue 49): the models' covariance heads and the EKF's own on "
                   "every case (mean NEES against the chi-square band, 1- and 2-sigma coverage per state, "
                   "log-likelihood of the truth; a markdown and a JSON file named after the plant under --out)")
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
    headed = [(label, obs) for label, obs in observers if obs.covariance is not None]
    if args.consistency and not headed:
        raise CommandError("--consistency: expected a model with a covariance head (architecture.covariance), "
                           "received none")
    out = out_path(args.out, "--out", directory=True)
    if out is not None:                      # the report's files, refused before any run: never written over
        system = observers[0][1].system.name
        parts = ("", *(("_consistency",) if args.consistency else ()))
        refuse_existing({out / f"{system}_generalisation{part}.{ext}": "--out"
                         for part in parts for ext in ("md", "json")})
    settings = gen.Settings(n_trials=args.trials, seed=args.seed)
    t0 = time.perf_counter()
    report = gen.run(observers, case_list, settings, trials=trials, pf_particles=args.pf,
                     pf_roughening=args.pf_roughening, compiler=compiler, n_threads=args.threads, progress=True)
    print(f"{len(case_list)} cases x {args.trials} trials in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    tables = report.markdown() + "\n\nDomain monitor:\n\n" + report.monitor_markdown()
    print(tables)
    uncertainty = None
    if args.consistency:
        from ..evaluation.uncertainty import score_cases, uncertainty_table

        uncertainty = score_cases(headed, case_list, settings, trials=trials, compiler=compiler,
                                  n_threads=args.threads)
        print("\n" + uncertainty_table(uncertainty))
    if out is not None:
        from ..provenance import json_record, markdown

        stamp = stamp_of(args, trials=args.seed)
        files = {f"{report.system}_generalisation.md": markdown(tables + "\n", stamp),
                 f"{report.system}_generalisation.json": json.dumps(json_record(report.to_json(), stamp),
                                                                    indent=1) + "\n"}
        if uncertainty is not None:
            from ..evaluation.uncertainty import uncertainty_record, uncertainty_table

            files[f"{report.system}_generalisation_consistency.md"] = markdown(uncertainty_table(uncertainty) + "\n",
                                                                              stamp)
            files[f"{report.system}_generalisation_consistency.json"] = json.dumps(
                json_record(uncertainty_record(uncertainty), stamp), indent=1) + "\n"
        write_dir(out, files, argument="--out")                    # the report's files as one, exclusively
        print(f"wrote {out}/", file=sys.stderr)
    return 0
