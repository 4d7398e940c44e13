"""``kklcasadi robustness``: score models where the EKF's model or noise is wrong (docs/protocol.md
"Robustness"): parameters at the corners of their box and inside it, effects outside the family,
heavy-tailed noise, outliers, quantisation; beside the EKF, the tuned EKF, the augmented EKF and the
particle filter over states and parameters, on the same trials.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import time

from ..plant import systems
from ..writes import write_dir
from .flags import (
    CommandError,
    add_cache,
    add_plant,
    add_roughening,
    benchmark_caches,
    flagged,
    labelled_models,
    out_path,
    plant_of,
    positive_float,
    positive_int,
    stamp_of,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    from ..evaluation.robustness import DEFAULT_NOISE_MODELS, KINDS

    g = sub.add_parser("robustness", help="score models where the EKF's model or noise is wrong (parameters in "
                       "a box, unmodelled effects, heavy-tailed noise, outliers, quantisation) beside the EKF, the "
                       "tuned EKF, the augmented EKF (and the particle filter over states and parameters)")
    g.add_argument("models", nargs="+", metavar="MODELS", help="model directories (one plant)")
    g.add_argument("--labels", nargs="*", help="row labels, one per model (default: the model directories' names)")
    g.add_argument("--param-spread", type=positive_float, default=0.3, metavar="S",
                   help="the family of a shipped plant: every coefficient in nominal (1 -+ S) (default 0.3; "
                   f"plants with a parameterised form: {', '.join(systems.families())}); --plant gives your own "
                   "family instead (a System with params=)")
    add_plant(g, "a plant with parameters: kc.System(..., params=P, param_box=...)")
    g.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS,
                   help="which cases: exact, corner (every corner of the box), inside (drawn per trial), outside "
                   "(damping, input gain), noise (the noise models) (default: all)")
    g.add_argument("--damping", type=float, default=0.3, metavar="C",
                   help="unmodelled damping -C x_i on the rows the input enters (default 0.3; 0: no case)")
    g.add_argument("--input-gain", type=float, default=0.7, metavar="G",
                   help="the actuator's real gain (default 0.7; 1: no case)")
    g.add_argument("--noise-models", nargs="*", default=list(DEFAULT_NOISE_MODELS), metavar="MODEL",
                   help="the noise cases (gauss | student-t:NU | outliers:P,K | quantised:STEP, combined with '+'; "
                   f"default: {' '.join(DEFAULT_NOISE_MODELS)})")
    g.add_argument("--noise", type=positive_float, default=0.1, metavar="STD",
                   help="process and measurement noise std of every case (default 0.1)")
    g.add_argument("--trials", type=positive_int, default=100, help="scored trials per case (default 100)")
    g.add_argument("--tuning-trials", type=positive_int, default=40,
                   help="tuning trials per case, on which the tuned and the augmented EKF choose (default 40)")
    g.add_argument("--seed", type=int, default=2026, help="seed of the scored trials (default 2026)")
    g.add_argument("--tuning-seed", type=int, default=4242, help="seed of the tuning trials (default 4242)")
    g.add_argument("--pf", type=positive_int, metavar="N",
                   help="add the particle filter over states and parameters with N particles")
    g.add_argument("--pf-trials", type=positive_int, metavar="M",
                   help="run the particle filter on the first M scored trials of each case only (default: all; "
                   "the table says so, and its ratios are on those trials)")
    add_roughening(g)
    g.add_argument("--consistency", action="store_true",
                   help="also score the covariances (issue 49) on every case: the models' covariance heads (models "
                   "without one have none), the EKF's, the tuned EKF's, the augmented EKF's (its plant states) and "
                   "the particle filter's (mean NEES against the chi-square band, 1- and 2-sigma coverage per state, "
                   "log-likelihood of the truth; a table in the markdown, records in the JSON)")
    g.add_argument("--out", help="directory for the markdown table, the JSON report and the plot")
    add_cache(g)
    g.add_argument("--vm", action="store_true", help="run the observers in the CasADi VM instead of compiled C")
    g.add_argument("--threads", type=positive_int, help="worker threads over trials (default: the CPU count)")
    g.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..evaluation import robustness as rb

    plant = plant_of(args)
    if plant is not None and not plant.n_params:
        raise CommandError(f"--plant: expected a plant with parameters (kc.System(..., params=P, param_box=...)), "
                           f"received {args.plant} without any")
    observers = labelled_models(args, plant)
    family = plant or flagged("--param-spread", systems.get, observers[0][1].system.name,
                              param_spread=args.param_spread)
    case_list = flagged("--kinds", rb.cases, family, damping=args.damping, input_gain=args.input_gain,
                        noise_models=args.noise_models, kinds=args.kinds)
    if not case_list:
        raise CommandError(f"--kinds: no case among {args.kinds} (outside needs --damping or --input-gain, noise "
                           "needs --noise-models)")
    settings = flagged("--tuning-seed", rb.Settings, n_trials=args.trials, n_tuning=args.tuning_trials,
                       seed=args.seed, tuning_seed=args.tuning_seed, noise=args.noise)
    out = out_path(args.out, "--out", directory=True)
    paths = [] if out is None else [out / f"{family.name}_robustness.{ext}" for ext in ("md", "json", "png")]
    existing = [p for p in paths if p.exists()]
    if existing:
        raise CommandError(f"--out: expected a directory without a report of {family.name!r}, received "
                           f"{out} with {existing[0].name}; choose another --out or move it")
    trials, compiler = benchmark_caches(args)
    t0 = time.perf_counter()
    if args.pf_trials is not None and args.pf is None:
        raise CommandError(f"--pf-trials: runs the particle filter of --pf N on fewer trials, received --pf-trials "
                           f"{args.pf_trials} without --pf")
    report = flagged("MODELS", rb.run, observers, family, case_list, settings, trials=trials, pf_particles=args.pf,
                     pf_trials=args.pf_trials, pf_roughening=args.pf_roughening, compiler=compiler,
                     n_threads=args.threads, consistency=args.consistency, progress=True)
    wall = time.perf_counter() - t0
    print(f"{len(case_list)} cases x {args.trials} trials in {wall:.1f} s", file=sys.stderr)
    table = report.markdown()
    print(table)
    if args.out:
        from ..provenance import json_record, markdown

        stamp = stamp_of(args, trials=args.seed, tuning=args.tuning_seed,
                         **({} if args.pf is None else {"pf": args.seed}))
        record = json_record({**report.to_json(), "wall_s": round(wall, 1)}, stamp)
        png = io.BytesIO()
        report.plot(png, stamp=stamp)
        # the three files as one: never over a report written meanwhile, never a half-written set
        texts = (markdown(table + "\n", stamp), json.dumps(record, indent=1) + "\n", png.getvalue())
        write_dir(out, {path.name: text for path, text in zip(paths, texts)}, argument="--out")
        print(f"wrote {', '.join(str(p) for p in paths)}", file=sys.stderr)
    return 0
