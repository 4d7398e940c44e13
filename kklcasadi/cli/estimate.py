"""``kklcasadi estimate``: run an observer (and the EKF) over a recorded CSV log and write the estimates.

``kklcasadi estimate MODEL --data LOG.csv --time-col time --y-cols theta,alpha --u-cols Vm --out EST.csv``
(``--u-zero`` instead of ``--u-cols`` for a log taken at zero input): the log's columns are taken by
name and put on the model's grid (:func:`kklcasadi.plant.logs.read_log`: ``y`` sampled at the grid
times, angle columns unwrapped, ``u`` zero-order hold, or averaged over each interval from a faster
log), the outputs checked against the model's training domain (``--no-range-check`` skips it), the
estimates, the domain flags and with ``--ekf`` the EKF's estimates are written
(:meth:`kklcasadi.evaluation.logged.LogEstimate.write`), and ``--reference-cols`` scores them against
recorded states. Every error is one line naming a flag (a bad log: ``--data`` with its row and column),
exit status 2; a sample the guard did not feed to the observer (:mod:`kklcasadi.observer.guard`) is
flagged in the ``status`` column, and the command then ends with exit status 3. The log is read, estimated
and written a block of samples at a time (:mod:`kklcasadi.evaluation.streamed`: memory independent of its
length, with a progress bar), or read whole where it must be (a log faster than the model, a sample the
guard acts on: :func:`kklcasadi.evaluation.logged.estimate_log`); the observer and the EKF run their compiled
steps a chunk of samples per call (:mod:`kklcasadi.evaluation.chunked`), with the vectorised
exp/tanh and fused multiply-adds (within 1e-12 per step of the VM; ``--math libm``: bitwise
:meth:`KKLObserver.simulate`);
``--vm`` (or no C compiler) runs the CasADi VM the same way.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any, Optional

from ..validation import ArgumentError
from ..writes import refuse_existing
from .flags import (
    CommandError,
    add_noise_levels,
    add_plant,
    columns,
    flagged,
    levels_text,
    load,
    model_label,
    nonnegative_float,
    plant_of,
    stamp_of,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("estimate", help="run an observer (and the EKF) over a recorded CSV log, write the estimates")
    e.add_argument("model", metavar="MODEL", help="a model directory, or a shipped model by name SYSTEM/METHOD")
    add_plant(e, "for a model of a plant that kklcasadi does not ship")
    e.add_argument("--data", required=True, metavar="LOG.csv", help="the log: a CSV file with a header row")
    e.add_argument("--time-col", default="time", help="the column of sample times in seconds (default time)")
    e.add_argument("--y-cols", required=True, type=columns, metavar="NAMES",
                   help="the measured outputs' columns, comma-separated, in the plant's output order")
    e.add_argument("--u-cols", type=columns, default=(), metavar="NAMES",
                   help="the inputs' columns, in the plant's input order (held zero-order; from a log faster than "
                   "the model, averaged over each interval)")
    e.add_argument("--u-zero", action="store_true", help="the plant's input was zero throughout the log (a plant "
                   "with inputs needs --u-cols or this)")
    e.add_argument("--angle-cols", type=columns, metavar="NAMES",
                   help="columns to unwrap as angles (default: those of the plant's angle outputs and states; "
                   "'' for none)")
    e.add_argument("--reference-cols", type=columns, default=(), metavar="NAMES",
                   help="recorded states to score against: one column per state in order, '-' for a state the log "
                   "does not record (errors of angle states wrapped)")
    e.add_argument("--no-range-check", action="store_true", help="accept outputs outside the model's training "
                   "domain (by default a value more than 10%% of its range outside is refused)")
    e.add_argument("--ekf", action="store_true", help="run the EKF beside the observer (noise: the card's levels "
                   "unless --process-std/--measurement-std)")
    add_noise_levels(e, "the EKF's (default: the card's)")
    e.add_argument("--settle", type=nonnegative_float, default=0.0, help="seconds left out of the scores (default 0)")
    e.add_argument("--state-names", type=columns, metavar="NAMES", help="column names of the states in EST.csv "
                   "(default x1, ..., xn)")
    e.add_argument("--out", required=True, metavar="EST.csv", help="the estimates to write (CSV; never one of the "
                   "command's input files)")
    e.add_argument("--vm", action="store_true", help="run the CasADi VM instead of the compiled steps (the reference "
                   "path; same values as --math libm, slower)")
    e.add_argument("--math", default="vector", choices=("vector", "libm"),
                   help="arithmetic of the compiled steps: vectorised exp/tanh and fused multiply-adds, within 1e-12 "
                   "per step of the VM (default), or the C library's exp/tanh and unfused sums, bitwise the VM")
    e.set_defaults(func=run)


def _check_count(flag: str, names: tuple, expected: int, what: str, allow_empty: bool = False) -> None:
    if len(names) != expected and not (allow_empty and not names):
        raise CommandError(f"{flag}: expected {expected} column(s) ({what}), received {len(names)}: "
                           f"{','.join(names) or 'none'}")


#: The arguments of :func:`kklcasadi.evaluation.logged.read_plant_log` that are flags of this command.
_FLAGS = {"time_col": "--time-col", "y_cols": "--y-cols", "u_cols": "--u-cols", "u_zero": "--u-zero",
          "reference_cols": "--reference-cols", "angle_cols": "--angle-cols"}


def _read(args: argparse.Namespace, obs: Any, reference: tuple[Optional[str], ...]) -> Any:
    """The log on the model's grid; an error about a column argument names its flag, any other ``--data``."""
    from ..evaluation.logged import read_plant_log

    try:
        return read_plant_log(args.data, obs, time_col=args.time_col, y_cols=args.y_cols, u_cols=args.u_cols,
                              u_zero=args.u_zero, reference_cols=reference, angle_cols=args.angle_cols,
                              range_check=not args.no_range_check)
    except (ValueError, TypeError) as exc:
        return _read_error(exc)


def _read_error(exc: Exception) -> Any:
    """An error reading the log as the command's: a column argument names its flag, any other ``--data``."""
    message = str(exc)
    head, sep, rest = message.partition(": ")
    if sep and head in _FLAGS:
        raise CommandError(f"{_FLAGS[head]}: {rest}") from exc
    raise CommandError(f"--data: {rest}" if sep and head.isidentifier() else f"--data: {message}") from exc


def _inputs(args: argparse.Namespace) -> dict[str, Path]:
    """The files the command reads, by flag: the log, the plant file, the model's files."""
    files = {"--data": Path(args.data)}
    if args.plant is not None and ":" in args.plant:
        plant_file = Path(args.plant.rsplit(":", 1)[0])
        if plant_file.suffix == ".py":
            files["--plant"] = plant_file
    model = Path(args.model)
    if model.is_dir():
        files.update({f"MODEL ({p.name})": p for p in model.iterdir() if p.is_file()})
    return files


def _check_out(args: argparse.Namespace) -> None:
    """``--data`` is an existing file; ``--out`` a file path that is none of the inputs, not inside the model and not
    an existing file."""
    if not Path(args.data).is_file():       # before the streamed run, whose writer's "path" errors name --out
        raise CommandError(f"--data: expected an existing CSV file, received {args.data!r}")
    out = Path(args.out)
    if out.is_dir():
        raise CommandError(f"--out: expected a file path for the estimates, received {args.out!r}, a folder")
    resolved = out.resolve()
    if Path(args.model).resolve() in resolved.parents:
        raise CommandError(f"--out: expected a file outside the model MODEL, received {args.out!r}")
    for flag, path in _inputs(args).items():
        same = os.path.samefile(out, path) if out.exists() and path.exists() else resolved == path.resolve()
        if same:
            raise CommandError(f"--out: expected a file other than the command's inputs, received {args.out!r}, "
                               f"which is {flag}'s file; choose another --out")
    refuse_existing({out: "--out"})          # the estimates are written whole, never over a file


def run(args: argparse.Namespace) -> int:
    """Estimate the log's states; write EST.csv; print the grid, the domain monitor and the scores.

    Exit status 0, or 3 where the sample guard flagged samples (the estimates are written all the same).
    """
    import numpy as np

    from ..evaluation.chunked import BITWISE, FAST
    from ..evaluation.logged import ekf_for_model, estimate_log
    from ..observer.guard import HELD, RESTARTED

    _check_out(args)
    obs = load(args.model, plant_of(args), "MODEL")
    plant = obs.system
    _check_count("--y-cols", args.y_cols, plant.ny, f"the outputs of {plant.name!r}")
    if args.u_cols and args.u_zero:
        raise CommandError("--u-zero: expected either --u-cols (the logged inputs) or --u-zero (a log at zero "
                           "input), received both")
    if plant.nu and not args.u_cols and not args.u_zero:
        raise CommandError(f"--u-cols: expected {plant.nu} column(s) (the inputs of {plant.name!r}, in order), "
                           "received none; name the logged inputs, or pass --u-zero if the input was zero "
                           "throughout the log")
    _check_count("--u-cols", args.u_cols, plant.nu, f"the inputs of {plant.name!r}", True)
    _check_count("--reference-cols", args.reference_cols, plant.nx, f"one per state of {plant.name!r}, '-' for "
                 "none", True)
    if args.state_names is not None:
        _check_count("--state-names", args.state_names, plant.nx, f"the states of {plant.name!r}")
    reference: tuple[Optional[str], ...] = tuple(None if name == "-" else name for name in args.reference_cols)
    ekf = False
    if args.ekf:
        ekf, levels = flagged("--ekf", ekf_for_model, obs, process_std=args.process_std,
                              measurement_std=args.measurement_std)
    compiler = None if args.vm else {"vector": FAST, "libm": BITWISE}[args.math]
    streamed = _streamed(args, obs, reference, ekf, compiler)
    if streamed is not None:                   # a block at a time: the memory of a block, whatever the length
        r, source, n, in_domain = streamed.resampling, streamed.source, streamed.n, streamed.in_domain
        status = np.zeros(n, dtype=np.int8)                     # it streams only where the guard does nothing
        scores, path = streamed.table(args.state_names) if reference else None, streamed.path
    else:                                      # the whole log: a faster log, or the guard holds or restarts
        log, recorded = _read(args, obs, reference)
        result = flagged("--settle", estimate_log, obs, log, u_zero=args.u_zero, ekf=ekf, settle=args.settle,
                         reference=recorded, compiler=compiler, progress=True)
        r, source, n, status = log.resampling, log.source, log.t.size, result.status
        in_domain = None if result.in_domain is None else int(result.in_domain.sum())
        scores = result.table(args.state_names) if recorded else None
        path = flagged("--out", result.write, args.out, state_names=args.state_names, stamp=stamp_of(args))
    print(f"model    {model_label(args.model)}  ({obs.method}, system {plant.name}, dt {obs.dt:g} s)")
    inputs = "none" if not plant.nu else "zero (--u-zero)" if args.u_zero else r.u_method
    print(f"log      {source}: {r.n_raw} rows over {r.t_last - r.t_first:.6g} s (spacing {r.dt_min:.4g} to "
          f"{r.dt_max:.4g} s, mean {r.dt_mean:.4g}) -> {n} samples every {obs.dt:g} s; y {r.y_method}, "
          f"u {inputs}" + (f"; angles unwrapped: {', '.join(r.angle_cols)}" if r.angle_cols else "")
          + ("; outputs not checked against the training domain (--no-range-check)" if args.no_range_check else ""))
    if in_domain is not None:
        print(f"domain   {in_domain} of {n} estimates in the domain the maps were trained on")
    flagged_samples = int(np.count_nonzero(status))
    if flagged_samples:
        print(f"guard    {flagged_samples} of {n} samples flagged in the status column: "
              f"{int(np.count_nonzero(status & HELD))} not fed (not finite or absurd), "
              f"{int(np.count_nonzero(status & RESTARTED))} restarts (exit status 3)")
    if args.ekf:
        q = levels_text(levels[0])
        print(f"EKF      Q = ({q} dt)^2 I, R = {levels[1]:g}^2 I" if "(" not in q else
              f"EKF      Q = diag({q[1:-1]})^2 dt^2, R = {levels[1]:g}^2 I")
    if scores is not None:
        print(scores)
    print(f"wrote    {path}")
    return 3 if flagged_samples else 0


def _streamed(args: argparse.Namespace, obs: Any, reference: tuple[Optional[str], ...], ekf: Any,
              compiler: Any) -> Any:
    """The log estimated and written a block at a time (:func:`kklcasadi.evaluation.streamed.estimate_streamed`), or
    None where it must be read whole; errors name their flags as :func:`_read`'s and the run's do."""
    from ..evaluation.streamed import estimate_streamed

    def run() -> Any:
        return estimate_streamed(obs, args.data, out=args.out, time_col=args.time_col, y_cols=args.y_cols,
                                 u_cols=args.u_cols, u_zero=args.u_zero, reference_cols=reference,
                                 angle_cols=args.angle_cols, range_check=not args.no_range_check, ekf=ekf,
                                 settle=args.settle, compiler=compiler, state_names=args.state_names,
                                 stamp=stamp_of(args), progress=True)

    try:
        return run()
    except ArgumentError as exc:
        if exc.argument in _WRITE_ARGUMENTS or exc.argument == "settle":
            raise CommandError(f"{'--settle' if exc.argument == 'settle' else '--out'}: {exc.detail}") from exc
        return _read_error(exc)
    except (ValueError, TypeError) as exc:
        return _read_error(exc)


#: The arguments of the estimates' writer (:class:`kklcasadi.plant.logs.EstimatesWriter`): errors of ``--out``.
_WRITE_ARGUMENTS = ("path", "state_names", "extra", "t", "xhat", "in_domain", "status", "columns", "blocks")
