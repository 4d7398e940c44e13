"""``kklcasadi compare``: the learned observer beside the EKF, the MHE and the KKL-primed MHE on the
docs/protocol.md benchmark (SMAPE and time per sample)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..plant import systems
from ..writes import refuse_existing, write_dir
from .flags import (
    NOISE,
    CommandError,
    add_dt,
    add_kinds,
    add_noise,
    add_noise_levels,
    add_system,
    check_dt,
    load,
    out_path,
    positive_float,
    positive_int,
    shipped,
    stamp_of,
)

#: The systems compared by default, in the order of docs/results/estimators.md's table.
SYSTEMS = ("duffing", "vdp", "fhn", "rossler")


def add_parser(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser("compare", help="KKL observer vs EKF vs MHE vs KKL-primed MHE on the docs/protocol.md "
                                       "benchmark (SMAPE and time per sample)")
    add_system(c, with_models=False, flag="--systems", nargs="+", default=list(SYSTEMS),
               what=f"the systems compared (default {' '.join(SYSTEMS)}; without --models-root each needs its shipped "
               "model)")
    c.add_argument("--method", default="bank", help="the learned observer: shipped model models/SYSTEM/METHOD "
                                                     "of every system (default bank)")
    c.add_argument("--models-root", help="directory holding SYSTEM/METHOD model directories (default: the shipped "
                                         "models)")
    c.add_argument("--trials", type=positive_int, default=100, help="trials per cell (docs/protocol.md: 100)")
    c.add_argument("--T", type=positive_float, default=50.0, help="horizon in seconds (docs/protocol.md: 50)")
    c.add_argument("--seed", type=int, default=2026, help="seed of the trials (default 2026; the KKL-primed MHE's "
                   "calibration runs use seed + 1)")
    add_noise(c)
    add_noise_levels(c, "the noisy column's and the EKF's and MHE's (default docs/protocol.md's 0.1)")
    add_dt(c, "the protocol's sample time (default 0.05, docs/protocol.md); the models' must equal it")
    add_kinds(c)
    c.add_argument("--horizons", nargs="+", type=positive_int, default=[10, 30], help="MHE horizons N")
    c.add_argument("--primed-horizon", type=positive_int, default=5, help="KKL-primed MHE horizon")
    c.add_argument("--calibration-trials", type=positive_int, default=5,
                   help="runs per regime (seed + 1) calibrating the KKL error profile")
    c.add_argument("--out", default="results/estimators/all", help="folder of the per-system JSON and the table "
                   "(default results/estimators/all)")
    c.add_argument("--quiet", action="store_true", help="no progress lines")
    c.set_defaults(func=run)


def _model_dir(root: str | None, system: str, method: str) -> Path:
    if root is None:
        return shipped(system, method)
    path = Path(root) / system / method
    if not (path / "card.json").exists():
        raise CommandError(f"--models-root {root}: no model {system}/{method} there")
    return path


def _saved(out: Path, fresh: dict[str, str]) -> list:
    """Every system's comparison in ``out``, those of ``fresh`` ({system: its JSON}, about to be written) in their
    place."""
    from ..evaluation.compare import SystemComparison

    names = [*SYSTEMS, *(n for n in systems.names() if n not in SYSTEMS)]
    saved = []
    for name in names:
        if name in fresh:
            saved.append(SystemComparison.from_json(json.loads(fresh[name])))
        elif (out / f"{name}.json").exists():
            path = out / f"{name}.json"
            try:
                saved.append(SystemComparison.from_json(json.loads(path.read_text())))
            except (ValueError, KeyError, TypeError) as exc:       # said in one line, naming the flag
                raise CommandError(f"--out: expected {path} to be a comparison kklcasadi compare wrote, received a "
                                   f"file it cannot read ({type(exc).__name__}: {exc}); move it away or choose "
                                   "another --out") from None
    return saved


def run(args: argparse.Namespace) -> int:
    """Run :func:`kklcasadi.evaluation.compare.compare_system` per ``--systems`` entry; write JSON and the table."""
    from ..estimators.ekf import EKF
    from ..evaluation.compare import compare_system
    from ..evaluation.protocol import Protocol
    from ..evaluation.report import markdown_table
    from ..provenance import json_record, markdown

    out = out_path(args.out, "--out", directory=True)
    if out is None:                          # the flag has a default: only a Namespace built by hand lacks it
        raise CommandError("--out: expected a folder for the comparisons and their table, received none")
    out.mkdir(parents=True, exist_ok=True)
    _saved(out, {})                          # the comparisons the table gathers, read before any run
    refuse_existing({out / f"{name}.json": "--out" for name in args.systems})     # a comparison is never written over
    kinds = tuple(args.kinds)
    levels = {name: getattr(args, name) for name in ("process_std", "measurement_std")
              if getattr(args, name) is not None}
    for name in args.systems:
        model = _model_dir(args.models_root, name, args.method)
        observer = load(model, None)
        protocol = Protocol(n_trials=args.trials, T=args.T, seed=args.seed,
                            **({} if args.dt is None else {"dt": args.dt}), **levels)
        check_dt(protocol.dt, protocol.T, {str(model): observer.dt})
        ekf = EKF.for_noise(observer.system, protocol.dt, process_std=protocol.process_std,
                            measurement_std=protocol.measurement_std) if levels else None
        log = (lambda line: print(line, file=sys.stderr, flush=True)) if not args.quiet else None
        comparison = compare_system(observer, protocol, horizons=tuple(args.horizons),
                                    primed_horizon=args.primed_horizon, calibration_trials=args.calibration_trials,
                                    kinds=kinds, noise=NOISE[args.noise], log=log, ekf=ekf)
        stamp = stamp_of(args, trials=args.seed, calibration=args.seed + 1)
        record = json.dumps(json_record(comparison.to_json(), stamp), indent=1) + "\n"
        every = [s for saved in _saved(out, {name: record}) for s in saved.scores]
        # the table gathers every system's saved comparison: its stamp is this command's, the rows name their files;
        # the system's record and the table are written as one
        write_dir(out, {f"{name}.json": record,                  # the table is rebuilt from every saved one
                        "table.md": markdown(markdown_table(every, kinds, timing=True) + "\n", stamp)},
                  overwrite=True, argument="--out")
        print(markdown_table(comparison.scores, kinds, timing=True))
    print(f"wrote {out}/", file=sys.stderr)
    return 0
