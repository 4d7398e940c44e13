"""``kklcasadi estimate``: run an observer (and the EKF) over a recorded CSV log and write the estimates.

``kklcasadi estimate MODEL --data LOG.csv --time-col time --y-cols theta,alpha [--u-cols Vm] --out EST.csv``:
the log is put on the model's grid (:func:`kklcasadi.plant.logs.read_log`: ``y`` linear, angle
columns unwrapped, ``u`` zero-order hold), the estimates, the domain flags and with ``--ekf`` the
EKF's estimates are written (:meth:`kklcasadi.evaluation.logged.LogEstimate.write`), and
``--reference-cols`` scores them against recorded states. A bad log is one line naming its row
and column. The observer and the EKF run their compiled steps a chunk of samples per call
(:mod:`kklcasadi.evaluation.chunked`: a log of any length in memory proportional to its estimates,
with a progress bar), with the vectorised exp/tanh (within 1e-14 per step of the VM; ``--math
libm``: bitwise :meth:`KKLObserver.simulate`); ``--vm`` (or no C compiler) runs the CasADi VM the
same way.
"""

from __future__ import annotations

import argparse
from typing import Optional

from .flags import (
    CommandError,
    add_noise_levels,
    add_plant,
    flagged,
    levels_text,
    load,
    model_label,
    nonnegative_float,
    plant_of,
    stamp_of,
)


def _columns(text: str) -> tuple[str, ...]:
    """``a,b,c`` -> ("a", "b", "c"); an empty string -> ()."""
    names = tuple(name.strip() for name in text.split(",")) if text.strip() else ()
    if any(not name for name in names):
        raise argparse.ArgumentTypeError(f"expected comma-separated column names, received {text!r}")
    return names


def add_parser(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("estimate", help="run an observer (and the EKF) over a recorded CSV log, write the estimates")
    e.add_argument("model", metavar="MODEL", help="a model directory, or a shipped model by name SYSTEM/METHOD")
    add_plant(e, "for a model of a plant that kklcasadi does not ship")
    e.add_argument("--data", required=True, metavar="LOG.csv", help="the log: a CSV file with a header row")
    e.add_argument("--time-col", default="time", help="the column of sample times in seconds (default time)")
    e.add_argument("--y-cols", required=True, type=_columns, metavar="NAMES",
                   help="the measured outputs' columns, comma-separated, in the plant's output order")
    e.add_argument("--u-cols", type=_columns, default=(), metavar="NAMES",
                   help="the inputs' columns (held zero-order); without them u = 0")
    e.add_argument("--angle-cols", type=_columns, metavar="NAMES",
                   help="columns to unwrap as angles (default: those of the plant's angle outputs and states; "
                   "'' for none)")
    e.add_argument("--reference-cols", type=_columns, default=(), metavar="NAMES",
                   help="recorded states to score against: one column per state in order, '-' for a state the log "
                   "does not record (errors of angle states wrapped)")
    e.add_argument("--ekf", action="store_true", help="run the EKF beside the observer (noise: the card's levels "
                   "unless --process-std/--measurement-std)")
    add_noise_levels(e, "the EKF's (default: the card's)")
    e.add_argument("--settle", type=nonnegative_float, default=0.0, help="seconds left out of the scores (default 0)")
    e.add_argument("--state-names", type=_columns, metavar="NAMES", help="column names of the states in EST.csv "
                   "(default x1, ..., xn)")
    e.add_argument("--out", required=True, metavar="EST.csv", help="the estimates to write (CSV)")
    e.add_argument("--vm", action="store_true", help="run the CasADi VM instead of the compiled steps (the reference "
                   "path; same values as --math libm, slower)")
    e.add_argument("--math", default="vector", choices=("vector", "libm"),
                   help="exp/tanh of the compiled steps: vectorised, within 1e-14 per step of the VM (default), or the "
                   "C library's, bitwise the VM")
    e.set_defaults(func=run)


def _check_count(flag: str, names: tuple, expected: int, what: str, allow_empty: bool = False) -> None:
    if len(names) != expected and not (allow_empty and not names):
        raise CommandError(f"{flag}: expected {expected} column(s) ({what}), received {len(names)}: "
                           f"{','.join(names) or 'none'}")


def run(args: argparse.Namespace) -> int:
    """Estimate the log's states; write EST.csv; print the grid, the domain monitor and the scores."""
    from ..evaluation.chunked import BITWISE, FAST
    from ..evaluation.logged import ekf_for_model, estimate_log, read_plant_log

    obs = load(args.model, plant_of(args), "MODEL")
    plant = obs.system
    _check_count("--y-cols", args.y_cols, plant.ny, f"the outputs of {plant.name!r}")
    _check_count("--u-cols", args.u_cols, plant.nu, f"the inputs of {plant.name!r}, or none for u = 0", True)
    _check_count("--reference-cols", args.reference_cols, plant.nx, f"one per state of {plant.name!r}, '-' for "
                 "none", True)
    if args.state_names is not None:
        _check_count("--state-names", args.state_names, plant.nx, f"the states of {plant.name!r}")
    reference: tuple[Optional[str], ...] = tuple(None if name == "-" else name for name in args.reference_cols)
    log, columns = flagged("--data", read_plant_log, args.data, obs, time_col=args.time_col, y_cols=args.y_cols,
                           u_cols=args.u_cols, reference_cols=reference, angle_cols=args.angle_cols)
    ekf = False
    if args.ekf:
        ekf, levels = flagged("--ekf", ekf_for_model, obs, process_std=args.process_std,
                              measurement_std=args.measurement_std)
    compiler = None if args.vm else {"vector": FAST, "libm": BITWISE}[args.math]
    result = flagged("--settle", estimate_log, obs, log, ekf=ekf, settle=args.settle, reference=columns,
                     compiler=compiler, progress=True)
    r = log.resampling
    print(f"model    {model_label(args.model)}  ({obs.method}, system {plant.name}, dt {obs.dt:g} s)")
    print(f"log      {log.source}: {r.n_raw} rows over {r.t_last - r.t_first:.6g} s (spacing {r.dt_min:.4g} to "
          f"{r.dt_max:.4g} s, mean {r.dt_mean:.4g}) -> {log.t.size} samples every {obs.dt:g} s; y {r.y_method}, "
          f"u {'zero (no --u-cols)' if not args.u_cols else r.u_method}"
          + (f"; angles unwrapped: {', '.join(r.angle_cols)}" if r.angle_cols else ""))
    if result.in_domain is not None:
        print(f"domain   {int(result.in_domain.sum())} of {log.t.size} estimates in the domain the maps were "
              "trained on")
    if args.ekf:
        q = levels_text(levels[0])
        print(f"EKF      Q = ({q} dt)^2 I, R = {levels[1]:g}^2 I" if "(" not in q else
              f"EKF      Q = diag({q[1:-1]})^2 dt^2, R = {levels[1]:g}^2 I")
    if columns:
        print(result.table(args.state_names))
    path = flagged("--out", result.write, args.out, state_names=args.state_names, stamp=stamp_of(args))
    print(f"wrote    {path}")
    return 0
