"""``kklcasadi tune``: one worker of an Optuna search of a method's design (``kklcasadi.evaluation.tune``).

Start it several times with the same ``--study`` and ``--storage`` (on one machine, or on several
with a PostgreSQL URL) for several workers; run it again to resume the study.
"""

from __future__ import annotations

import argparse

from ..plant import systems
from .flags import (
    CommandError,
    add_plant,
    add_system,
    flagged_by,
    needs_torch,
    out_path,
    plant_of,
    positive_int,
    stamp_of,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    from ..evaluation.tune import SPACES

    t = sub.add_parser("tune", help="search a method's design on Optuna (SQLite here, PostgreSQL across machines)",
                       description=__doc__.split("\n\n", 1)[1])
    add_system(t, with_models=False, what="a system kklcasadi ships (its plant; or --plant for yours)")
    add_plant(t)
    t.add_argument("--method", default="bank", choices=sorted(SPACES), help="the observer variant (default bank)")
    t.add_argument("--trials", type=positive_int, required=True,
                   help="complete trials the study stops at, over all its workers")
    t.add_argument("--study", help="the study's name (default SYSTEM-METHOD)")
    t.add_argument("--storage", help="SQLAlchemy URL of the study, e.g. postgresql://user@host:5432/db (default: "
                                     "the SQLite file OUT/study.db)")
    t.add_argument("--copy-from", help="copy the study from this storage URL first, where --storage has no study "
                                       "of that name (continue a SQLite study on PostgreSQL)")
    t.add_argument("--out", required=True, help="where this worker writes: trials/, best/, summary.md, search.png")
    t.add_argument("--base", help="the Phase-1 model, for methods that build on one")
    t.add_argument("--runs", type=positive_int, help="budget cap: training runs or trajectories (default: the "
                                                     "method's default)")
    t.add_argument("--epochs", type=positive_int, help="budget cap: epochs (default: the method's default)")
    t.add_argument("--val-trials", type=positive_int, default=20, help="validation trials per cell (default 20)")
    t.add_argument("--baseline", action="store_true",
                   help="also train the method's default configuration at the caps and record its score (once per "
                        "study)")
    t.add_argument("--heartbeat", type=positive_int, default=30,
                   help="seconds between a trial's heartbeats; a trial silent for 3 is failed and retried (default "
                        "30)")
    t.add_argument("--seed", type=int, default=0, help="training seed of every trial")
    t.add_argument("--sampler-seed", type=int, help="seed of this worker's TPE sampler (workers must differ)")
    t.add_argument("--threads", type=positive_int, default=1, help="torch threads per training (default 1)")
    t.add_argument("--quiet", action="store_true", help="no log line per trial")
    t.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if (args.plant is None) == (args.system is None):
        raise CommandError("--system/--plant: give exactly one: a shipped system name or your plant FILE.py:NAME")
    out = out_path(args.out, "--out", directory=True)
    plant = plant_of(args) or systems.get(args.system)
    needs_torch("kklcasadi tune")
    try:
        import optuna  # noqa: F401
    except ImportError:
        raise CommandError("kklcasadi tune needs optuna, which is not installed; install the tune extra: "
                           "pip install 'kklcasadi[tune]'") from None
    from ..evaluation.tune import VALIDATION_SEED, tune

    caps = {name: value for name, value in (("runs", args.runs), ("epochs", args.epochs)) if value is not None}
    flags = {"storage": "--storage", "copy_from": "--copy-from", "out_dir": "--out", "study": "--study",
             "base": "--base"}
    result = flagged_by(flags, "--method " + args.method, tune, plant, args.method, out, n_trials=args.trials,
                        study=args.study, storage=args.storage, caps=caps, base=args.base, seed=args.seed,
                        threads=args.threads, val_trials=args.val_trials, heartbeat=args.heartbeat,
                        baseline=args.baseline, copy_from=args.copy_from, sampler_seed=args.sampler_seed,
                        progress=not args.quiet, stamp=stamp_of(args, training=args.seed, sampler=args.sampler_seed,
                                                                validation=VALIDATION_SEED))
    print(result.summary.read_text())
    print(f"wrote {result.summary}, {result.plot}" + ("" if result.best_dir is None else f", {result.best_dir}/"))
    return 0
