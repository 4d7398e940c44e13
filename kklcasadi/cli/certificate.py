"""``kklcasadi certificate``: Proposition 1 of the paper estimated for models, beside their observed error."""

from __future__ import annotations

import argparse
import json

from ..writes import refuse_existing, write_file
from .flags import (
    add_kinds,
    add_plant,
    flagged,
    load,
    nonnegative_float,
    out_path,
    plant_of,
    positive_float,
    positive_int,
    stamp_of,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser("certificate", help="estimate Proposition 1's error bound for models and compare it with "
                                           "their observed error")
    c.add_argument("models", nargs="+", metavar="MODELS",
                   help="model directories, or shipped models by name SYSTEM/METHOD (e.g. duffing/autonomous)")
    add_kinds(c, "input regimes of the input set and the runs (zero: u = 0 only)")
    c.add_argument("--points", type=positive_int, default=4000, help="domain sample size")
    c.add_argument("--labels", type=positive_int, default=40, help="held-out label trajectories")
    c.add_argument("--trials", type=positive_int, default=10, help="noise-free runs per regime")
    c.add_argument("--T", type=positive_float, default=30.0, help="run duration (s)")
    c.add_argument("--settle", type=nonnegative_float, default=10.0, help="settle time (s)")
    add_plant(c, "for models of a plant that kklcasadi does not ship")
    c.add_argument("--seed", type=int, default=0, help="seed of the domain sample and the runs (default 0)")
    c.add_argument("--out", help="write the certificates to this JSON file (refused where it exists)")
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Print each model's certificate; ``--out`` saves them as JSON."""
    from ..evaluation.certificate import certificate

    out = out_path(args.out, "--out", directory=False)
    if out is not None:
        refuse_existing({out: "--out"})      # before any certificate is computed: never written over
    records, plant = [], plant_of(args)
    for model in args.models:
        cert = flagged("MODELS", certificate, load(model, plant, "MODELS"), kinds=tuple(args.kinds),
                       n_points=args.points, n_labels=args.labels, n_trials=args.trials, T=args.T,
                       t_settle=args.settle, seed=args.seed)
        print(f"{model}\n{cert}\n")
        records.append({"model": str(model), **cert.to_json()})
    if out is not None:
        from ..provenance import json_record

        write_file(out, json.dumps(json_record(records, stamp_of(args, seed=args.seed)), indent=1) + "\n",
                   argument="--out")
    return 0
