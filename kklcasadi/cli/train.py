"""``kklcasadi train``: train an observer variant and write its model directory.

Without ``--method`` it trains :data:`RECOMMENDED`, the observer the README recommends for a new
plant: ``kklcasadi train --plant FILE.py:NAME --dt DT --measurement-std S --out DIR``. With
``--like LOG.csv`` (and the log's columns) the training runs take the rig's envelope from its logs
(:func:`kklcasadi.estimators.noise.rig_envelope`): inputs like the logged ones, the outputs' range,
the noise levels (``--measurement-std``/``--process-std`` win over the estimates).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import fields, replace
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ..model import variants
from ..plant import signals as sig
from ..plant import systems
from ..plant.runs import ENVELOPE_ESCAPE, RolloutConfig, drifting_states, inside_box, resolved, rollouts
from .flags import (
    CommandError,
    add_dt,
    add_plant,
    add_system,
    columns,
    flagged,
    flagged_by,
    levels_text,
    load,
    needs_torch,
    nonnegative_float,
    out_path,
    plant_of,
    positive_float,
    positive_int,
    quiet_casadi,
    run_noise,
)

#: The method trained without ``--method``: the filter bank with a decoder fit on noisy runs of the plant.
RECOMMENDED = "bank"
#: The closing quality summary: runs per input kind of docs/protocol.md, and their seed (a validation seed: not
#: the protocol's scored 2026, and not a training seed's runs, which come from the training sampler).
SUMMARY_TRIALS, SUMMARY_SEED = 3, 7
#: Runs of the summary drawn by the card's training recipe (before the ones that leave the box are cut).
RECIPE_RUNS = 12
#: The summary's RMSE is over the samples after this time, s (docs/protocol.md's settling time).
SETTLE_S = 5.0

#: Flags that set a field of the method's training configuration: flag -> (field, value from args). A
#: field is found at the top of the configuration or in the one nested configuration that holds it
#: (:func:`kklcasadi.train.config.config_field`).
_CONFIG_FLAGS = {"--measurement-std": ("measurement_std", lambda a: a.measurement_std),
                 "--process-std": ("process_std", lambda a: a.process_std),
                 "--box-scale": ("box_scale", lambda a: a.box_scale),
                 "--kinds": ("kinds", lambda a: None if a.kinds is None else tuple(a.kinds)),
                 "--runs": ("n_traj", lambda a: a.runs),
                 "--noise-model": ("noise_models", lambda a: None if a.noise_model is None else tuple(a.noise_model)),
                 "--width": ("width", lambda a: a.width),
                 "--members": ("members", lambda a: a.members),
                 "--copies": ("copies", lambda a: None if a.copies is None else tuple(a.copies)),
                 "--corner-copies": ("corner_copies", lambda a: None if a.corner_copies is None
                                     else tuple(a.corner_copies)),
                 "--skip-path": ("skip", lambda a: True if a.skip_path else None),
                 "--ekf-block": ("ekf_block", lambda a: True if a.ekf_block else None),
                 "--teacher": ("teacher", lambda a: a.teacher),
                 "--input-scale": ("input_scale", lambda a: None if a.input_scale is None else
                                   a.input_scale[0] if len(a.input_scale) == 1 else tuple(a.input_scale)),
                 "--loss": ("loss", lambda a: a.loss),
                 "--smape-weight": ("smape_weight", lambda a: a.smape_weight),
                 "--on-inject": ("model_based_injection", lambda a: True if a.on_inject else None)}


def add_parser(sub: argparse._SubParsersAction) -> None:
    t = sub.add_parser("train", help="train an observer variant and write its model directory")
    add_system(t, with_models=False, what="a system kklcasadi ships (its plant; or --plant for yours)")
    add_plant(t)
    t.add_argument("--method", choices=variants.trainable(),
                   help=f"default {RECOMMENDED} (the observer for a new plant); "
                   + "; ".join(f"{v.name}: {v.summary}" for v in variants.VARIANTS.values()))
    t.add_argument("--out", required=True, help="model directory to write")
    add_dt(t, "the observer's sample time (default 0.05, the paper systems')")
    t.add_argument("--base", help="Phase-1 model (default OUT/../autonomous for Phase-2 methods)")
    t.add_argument("--measurement-std", type=nonnegative_float,
                   help="the measurement noise std on y the observer is fit for: bank's noisy training runs (default "
                   "0.1), autonomous's decoder (default 0); recorded in the card, where demo and estimate read the "
                   "EKF's from")
    t.add_argument("--process-std", type=nonnegative_float,
                   help="bank only: the process noise std of its noisy training runs, on xdot in the plant's units "
                   "per second (default 0.1): on every state of a shipped system; on a plant of yours only on the "
                   "rows that are not x_i' = x_j, so that it stands for unmodelled forces, not for a position "
                   "drifting from its velocity; recorded in the card")
    t.add_argument("--box-scale", type=positive_float, metavar="FACTOR",
                   help="draw the training runs' initial states from the X0 box scaled by FACTOR about its centre "
                   "(bank: its runs; autonomous: its Phase-1 data; default 1, the whole box). Below 1 where the "
                   "box bounds whole trajectories rather than their starts (the Qube: 0.5)")
    t.add_argument("--kinds", nargs="+", metavar="FAMILY",
                   help="the input families of the training data. bank: kklcasadi.plant.runs.FAMILIES "
                   "(default: the benchmark's four, multisine and a proportional feedback loop; add pd for a plant "
                   "that a controller with derivative action will drive); obs, dyn: the benchmark's kinds")
    t.add_argument("--runs", type=positive_int, metavar="N",
                   help="bank: the number of operational runs the decoders are fit on (the budget with --epochs; "
                   "default the recipe's: 8000 for Duffing and Van der Pol, 1000 for a new plant)")
    t.add_argument("--noise-model", nargs="+", metavar="MODEL",
                   help="bank: the measurement noise of the training runs, scaled by --measurement-std: gauss (the "
                   "default), student-t:NU, outliers:P,K (P of the samples at K times the noise), quantised:STEP, "
                   "or a combination with '+'; with several, each run draws one (kklcasadi.plant.noise)")
    t.add_argument("--param-spread", type=positive_float, metavar="S",
                   help="bank, with --system: train over the family of the plant, every coefficient in nominal "
                   f"(1 -+ S), each run's drawn from that box ({', '.join(systems.families())}); a --plant with "
                   "params= trains over its own box without this flag. The card records the box and the draw")
    t.add_argument("--width", type=positive_int, help="autonomous: hidden width of T and T* (default 150; the "
                   "paper uses 350 for rossler and fhn)")
    t.add_argument("--members", type=positive_int, metavar="K",
                   help="bank: fit K decoder networks from seeds SEED..SEED+K-1 and average them; their spread "
                   "joins the domain monitor (training time grows K-fold)")
    t.add_argument("--copies", nargs="+", type=positive_float, metavar="W",
                   help="bank: add one model copy of the plant per weight W to the latent, a constant-gain observer "
                   "xhat' = f(xhat, u) + L (y - h(xhat)) with the Kalman-Bucy gain of the plant linearised at its "
                   "box centre for process intensity W (1: the protocol EKF's noise ratio); the decoders read their "
                   "states beside the filters (docs/design.md, 'Model copies'); a state the plant's equations do not "
                   "read is left out of the copies")
    t.add_argument("--corner-copies", nargs="+", type=positive_float, metavar="W",
                   help="bank, over a family (--param-spread or a --plant with params=): add one model copy per "
                   "corner of the parameter box per weight W, each observing the plant at that corner with its "
                   "Kalman-Bucy gain for process intensity W; the card records their parameters (docs/design.md, "
                   "'Over a family')")
    t.add_argument("--ekf-block", action="store_true",
                   help="bank, over a family (--param-spread or a --plant with params=): end the latent with the "
                   "augmented EKF (the states and the parameters as random-walk states, at the runs' noise), stepped "
                   "once per sample by the augmented EKF's own step; the decoders read its estimates and covariance "
                   "and fit the state's residual over its estimate (docs/design.md, 'Over a family'); the card "
                   "records its settings")
    t.add_argument("--skip-path", action="store_true",
                   help="bank: give each decoder network a linear path beside its tanh layers, which keeps its "
                   "slope where they level off past the fitted states (Duffing's shipped bank has it)")
    t.add_argument("--teacher", metavar="DIR",
                   help="bank: fit the decoders to the estimates of this bank model (its ensemble's mean, through its "
                   "own latent) on the same runs instead of the true states: distillation into a smaller decoder "
                   "(docs/design.md, 'A compact observer')")
    t.add_argument("--input-scale", nargs="+", type=positive_float, metavar="F",
                   help="bank: scale each training run's input about the input range's centre by F, or by a factor "
                   "drawn log-uniformly from F_LO F_HI per run (the open-loop inputs, the feedback laws' limit; "
                   "default 1): with --teacher, a student fit on runs wider than its teacher's (docs/design.md, "
                   "'A compact observer')")
    t.add_argument("--loss", choices=("mse", "smape", "mse+smape"),
                   help="bank: the decoders' loss: mse (the default) of the normalised states, smape (the "
                   "protocol's metric) or mse+smape (their sum, --smape-weight on the SMAPE term). mse+smape with "
                   "weight 0.5 helped Roessler, whose third state sits near zero, and is its shipped recipe; it hurt "
                   "Duffing and Van der Pol (docs/design.md, 'The loss against the metric')")
    t.add_argument("--smape-weight", type=positive_float, metavar="W",
                   help="bank, with --loss mse+smape: the weight of the SMAPE term (default 0.01; Roessler's "
                   "shipped recipe: mse+smape, 0.5)")
    t.add_argument("--on-inject", action="store_true",
                   help="obs: learn the residual on top of the model-based injection of 'inject'")
    t.add_argument("--like", action="append", metavar="LOG.csv",
                   help="bank: a log of the rig (CSV with a header row; repeat for several): the training runs replay "
                   "resampled and rescaled segments of its inputs from the states it went through beside the input "
                   "families, are bounded by its outputs' range, and take its noise: the measurement std from the "
                   "outputs' high-frequency residual, the process std per state by the likelihood of the EKF's "
                   "innovations (recorded in the card; --measurement-std, --process-std win)")
    t.add_argument("--time-col", default="time", help="with --like: the logs' column of sample times in seconds "
                   "(default time)")
    t.add_argument("--y-cols", type=columns, metavar="NAMES",
                   help="with --like: the measured outputs' columns, comma-separated, in the plant's output order")
    t.add_argument("--u-cols", type=columns, metavar="NAMES",
                   help="with --like: the inputs' columns in the plant's input order (a log faster than --dt: "
                   "averaged over each interval)")
    t.add_argument("--u-zero", action="store_true",
                   help="with --like: the rig's input was zero throughout the logs (a plant with inputs needs "
                   "--u-cols or this)")
    t.add_argument("--angle-cols", type=columns, metavar="NAMES",
                   help="with --like: columns to unwrap as angles (default: those of the plant's angle outputs)")
    t.add_argument("--epochs", type=positive_int, help="override the number of epochs of every stage")
    t.add_argument("--seed", type=int, default=0, help="seed of the training data and the networks' weights "
                   "(default 0)")
    t.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where torch trains (default cpu)")
    t.add_argument("--resume", action="store_true", help="continue from the checkpoints in OUT/.train")
    t.add_argument("--overwrite", action="store_true", help="replace a model already in OUT")
    t.add_argument("--quiet", action="store_true", help="no progress bars")
    t.add_argument("--threads", type=positive_int, help="torch CPU threads (default 1: on shared cores more threads "
                   "wait on each other; a quiet machine with many cores may gain from more)")
    t.set_defaults(func=run)


def _takes(method: str, name: str, plant: str) -> bool:
    """Whether ``method``'s configuration has the field ``name``."""
    from ..train import default_config, has_field

    return variants.get(method).trains and has_field(default_config(plant, method), name)


def _takers(name: str, plant: str) -> list[str]:
    """The trainable methods whose configuration has the field ``name``."""
    return [v.name for v in variants.VARIANTS.values() if _takes(v.name, name, plant)]


#: The arguments of :func:`kklcasadi.estimators.noise.rig_envelope` that are flags of ``train --like``.
_LOG_FLAGS = {"time_col": "--time-col", "y_cols": "--y-cols", "u_cols": "--u-cols", "angle_cols": "--angle-cols",
              "paths": "--like", "measurement_std": "--measurement-std", "process_std": "--process-std"}


def rig_of(plant: systems.System, args: argparse.Namespace) -> Any:
    """The rig's envelope from ``--like`` and its column flags (None without ``--like``)."""
    from ..estimators.noise import rig_envelope

    if not args.like:
        given = [flag for flag, name in (("--y-cols", "y_cols"), ("--u-cols", "u_cols"), ("--angle-cols", "angle_cols"))
                 if getattr(args, name) is not None] + (["--u-zero"] if args.u_zero else [])
        if given:
            raise CommandError(f"{given[0]}: names the columns of the logs of --like, received no --like LOG.csv")
        return None
    if args.y_cols is None:
        raise CommandError(f"--y-cols: expected the logs' columns of the {plant.ny} output(s) of {plant.name!r} "
                           "(comma-separated), received none")
    if args.u_cols is not None and args.u_zero:
        raise CommandError("--u-zero: the rig's input was zero, so give no --u-cols; received both")
    if args.u_cols is None and not args.u_zero:
        raise CommandError(f"--u-cols: expected the logs' column(s) of the {plant.nu} input(s) of {plant.name!r}, "
                           "received none; pass --u-zero if the rig's input was zero throughout")
    dt = 0.05 if args.dt is None else args.dt
    try:
        return rig_envelope(plant, args.like, dt=dt, time_col=args.time_col, y_cols=args.y_cols,
                            u_cols=args.u_cols or (), angle_cols=args.angle_cols,
                            measurement_std=args.measurement_std, process_std=args.process_std)
    except (ValueError, TypeError) as exc:
        head, sep, rest = str(exc).partition(": ")
        if sep and head in _LOG_FLAGS:
            raise CommandError(f"{_LOG_FLAGS[head]}: {rest}") from exc
        raise CommandError(f"--like: {rest}" if sep and head.isidentifier() else f"--like: {exc}") from exc


def training_config(plant: systems.System, method: str, args: argparse.Namespace, envelope: Any = None) -> Any:
    """The configuration ``kklcasadi train`` trains ``method`` of ``plant`` with: the method's default for
    the plant, with the rig's ``envelope`` (:func:`kklcasadi.train.bank.with_envelope`, from ``--like``) and
    the fields of :data:`_CONFIG_FLAGS` the flags in ``args`` set (None: a method without a configuration).
    A flag the method's configuration has no field for is a :class:`CommandError`."""
    from ..train import config_field, default_config, has_field, with_field

    config = default_config(plant.name, method) if variants.get(method).trains else None
    if envelope is not None:
        if config is None or not has_field(config, "envelope"):
            raise CommandError(f"--like: only --method {' or '.join(_takers('envelope', plant.name))} takes it, "
                               f"received --method {method}")
        from ..train.bank import with_envelope

        config = with_envelope(config, envelope)
    for flag, (name, value) in _CONFIG_FLAGS.items():
        if value(args) is None:
            continue
        if config is None or not has_field(config, name):
            raise CommandError(f"{flag}: only --method {' or '.join(_takers(name, plant.name))} takes it, "
                               f"received --method {method}")
        config = flagged(flag, with_field, config, name, value(args))
    if args.smape_weight is not None and (loss := config_field(config, "loss")) != "mse+smape":
        raise CommandError(f"--smape-weight: weighs the SMAPE term of --loss mse+smape, received --loss {loss}"
                           f"{'' if args.loss else ' (the default)'}; add --loss mse+smape")
    return config


def envelope_text(envelope: Any, plant: systems.System) -> str:
    """A few lines on what the logs gave: files, ranges, noise levels and where each came from."""
    noise = envelope.noise
    process = ", ".join(f"{v:.3g}" for v in envelope.process_std)
    lines = [f"like     {len(envelope.sources)} log(s): " + ", ".join(f"{s['path']} ({s['rows']} rows)"
                                                            for s in envelope.sources),
             f"         outputs {envelope.y_range.round(6).tolist()}"
             + ("" if envelope.u_range is None else f", inputs {envelope.u_range.round(6).tolist()}"),
             f"         measurement std {envelope.measurement_std:.3g} ({noise.get('measurement_std_from')}), "
             f"process std ({process}) ({noise.get('process_std_from')})"]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if (args.plant is None) == (args.system is None):
        raise CommandError("--system/--plant: give exactly one: a shipped system name or your plant FILE.py:NAME")
    if args.param_spread is not None and args.system is None:
        raise CommandError("--param-spread: makes the family of a shipped --system; your --plant declares its own "
                           "parameters (kc.System(..., params=P, param_box=...))")
    plant = plant_of(args) or flagged("--param-spread", systems.get, args.system, param_spread=args.param_spread)
    needs_torch("kklcasadi train")
    from ..train import train_observer

    out = out_path(args.out, "--out", directory=True)
    if (out / "card.json").exists() and not args.overwrite:
        raise CommandError(f"--out {out}: a model already exists there; pass --overwrite to replace it"
                           + (" (--resume continues an unfinished training, never a finished model)"
                              if args.resume else ""))
    method = args.method or RECOMMENDED
    if args.method is None and not args.quiet:
        print(f"method: {RECOMMENDED} (the observer for a new plant; --method chooses another)", flush=True)
    if args.like and not _takes(method, "envelope", plant.name):
        raise CommandError(f"--like: only --method {' or '.join(_takers('envelope', plant.name))} takes it, "
                           f"received --method {method}")
    envelope = rig_of(plant, args)
    if envelope is not None and not args.quiet:
        print(envelope_text(envelope, plant), flush=True)
    config = training_config(plant, method, args, envelope)
    dt = 0.05 if args.dt is None else args.dt
    if args.copies is not None or args.corner_copies is not None:   # the plant must take them (see design_copies)
        from ..train.bank import design_copies

        flagged("--copies" if args.corner_copies is None else "--corner-copies", design_copies, plant, config, dt)
    if args.ekf_block:                                              # the plant must be a family (see design_ekf_block)
        from ..train.bank import design_ekf_block

        flagged("--ekf-block", design_ekf_block, plant, config, dt)
    t0 = time.perf_counter()
    path = flagged_by({"resume": "--resume", "out_dir": "--out", "base": "--base"}, "--" + method, train_observer,
                      plant, method, out, config=config, base=args.base, dt=dt, seed=args.seed, device=args.device,
                      resume=args.resume, overwrite=args.overwrite, progress=not args.quiet, threads=args.threads,
                      epochs=args.epochs)
    print(f"wrote    {path}/weights.npz and card.json ({time.perf_counter() - t0:.0f} s)")
    print(summary(path, plant, args.plant))
    return 0


def summary(path: Path, plant: systems.System, plant_flag: Optional[str]) -> str:
    """How good the trained observer is, in a few lines, and the commands to run next.

    The observer and the EKF (``Q``, ``R`` of the card's noise levels, else docs/protocol.md's 0.1) on
    :data:`SUMMARY_TRIALS` noisy runs per input kind of docs/protocol.md, drawn with :data:`SUMMARY_SEED` (runs
    nothing was fit or chosen on). Scored per kind on the runs whose state stays in the box the observer was trained
    in (:func:`~kklcasadi.observer.guard.training_box`, widened by a quarter of its half-width, where training cuts
    the runs of a plant that declares where it lives: :data:`~kklcasadi.plant.runs.ENVELOPE_ESCAPE`): the RMSE after
    docs/protocol.md's settling time in % of the box's width (a scale the states' values near zero do not distort,
    as they do SMAPE) of each and their ratio, and their SMAPE. The runs that leave the box (open-loop inputs on an
    integrating state, where training ran under a stabilising loop) are counted apart with their RMSE: there the
    observer extrapolates. Where the card records the recipe of its training runs, the same scores on runs drawn by
    it (:func:`recipe_lines`). Also the share of the estimates inside the domain the maps were trained on (on the
    runs that stay in the box, and over every run where some leave it: :func:`domain_line`), and the trials whose
    state escaped. Runs on which the EKF diverges (non-finite estimates) are counted and left out of the ratio.
    """
    from ..estimators.ekf import EKF
    from ..evaluation.protocol import Protocol
    from ..observer.guard import training_box

    obs = load(path, plant, "--out")
    process_std, measurement_std = run_noise(obs)
    draw = Protocol(n_trials=SUMMARY_TRIALS, dt=obs.dt, seed=SUMMARY_SEED, process_std=process_std,
                    measurement_std=measurement_std, t_settle=SETTLE_S)
    ekf = EKF.for_noise(plant, obs.dt, process_std=process_std, measurement_std=measurement_std)
    box = training_box(obs)
    rows: list[str] = []
    inside: list[tuple[np.ndarray, np.ndarray]] = []
    left: dict[str, int] = {}
    outside: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    escaped = 0
    for kind in sig.BENCHMARK_KINDS:
        with quiet_casadi():
            batch = draw.trials(plant, kind)
        ok = batch.ok
        escaped += int((~ok).sum())
        if not ok.any():
            continue
        x = batch.x[ok]
        est = obs.simulate(batch.t, batch.y[ok], batch.u[ok])
        theirs = ekf.simulate(batch.t, batch.y[ok], batch.u[ok]).xhat
        kept = np.isfinite(theirs).all(axis=(1, 2))            # an EKF can diverge (a stiff plant, a large P0)
        stays = np.asarray(inside_box(x, box, plant.angle_states, scale=ENVELOPE_ESCAPE).all(axis=1))
        if est.in_domain is not None:                           # the share of each run's samples inside
            share = np.asarray(est.in_domain, dtype=float).reshape(len(x), -1).mean(axis=1)
            inside.append((share, stays))
        late = batch.t >= SETTLE_S                              # the RMSE after the observers' transients
        ours = box_rmse(x[:, late], est.xhat[:, late], box, plant.angle_states)
        ekf_rmse = box_rmse(x[:, late], theirs[:, late], box, plant.angle_states)
        if (~stays).any():
            left[kind] = int((~stays).sum())
            outside[0].append(ours[~stays])
            outside[1].append(ekf_rmse[~stays & kept])
        rows.append(_quality_row(kind, x[stays], est.xhat[stays], theirs[stays], ours[stays], ekf_rmse[stays],
                                 kept[stays], plant.angle_states, len(x)))
    noise = f"noise std {levels_text(process_std)} / {measurement_std:g}"
    lines = [f"quality  the observer / the EKF on {draw.n_trials} held-out runs per input ({noise}, seed "
             f"{SUMMARY_SEED}; not the benchmark's trials), scored on the runs that stay in the box it was trained "
             f"in: RMSE after {SETTLE_S:g} s in % of the box's width (ratio), SMAPE:",
             "         " + ("; ".join(rows) if rows else "every run escaped")
             + (f"; {escaped} run(s) escaped, not scored" if escaped else "")]
    if left:
        drifting = drifting_states(plant)
        why = (f"; {', '.join(f'x[{i}]' for i in drifting)} integrates: open-loop inputs drive it out"
               if drifting else "")
        theirs_out = np.concatenate(outside[1])
        lines.append(f"outside  {sum(left.values())} run(s) left that box ("
                     + ", ".join(f"{kind} {n}" for kind, n in left.items()) + f"{why}): not the observer's domain, "
                     f"it extrapolates there (RMSE {np.mean(np.concatenate(outside[0])):.3g} %"
                     + (f", the EKF's {np.mean(theirs_out):.3g} %" if theirs_out.size else "") + ")")
    lines += recipe_lines(obs, box, ekf, process_std, measurement_std)
    if inside:
        lines.append(domain_line(*(np.concatenate(parts) for parts in zip(*inside))))
    own = f" --plant {plant_flag}" if plant_flag else ""
    lines += ["next     kklcasadi evaluate " + f"{path}{own} --ekf" + "      # the benchmark, 100 trials per cell",
              f"         kklcasadi demo --model {path}{own}          # one run, printed and plotted",
              f"         kklcasadi export {path}{own} --c build/obs   # the observer step as C"]
    return "\n".join(lines)


def domain_line(share: np.ndarray, stays: np.ndarray) -> str:
    """The summary's ``domain`` line: the mean share of the estimates inside the trained domain on the runs that stay
    in the box (``share`` (n_runs,), each run's share in [0, 1]; ``stays`` (n_runs,) bool), with the mean over every
    run beside it where some runs leave the box (there the observer extrapolates and is rightly flagged)."""
    what = "of the estimates inside the domain the maps were trained on"
    if not stays.any():
        return f"domain   {100 * float(np.mean(share)):.1f} % {what} (every run left the box)"
    every = "" if stays.all() else f" ({100 * float(np.mean(share)):.1f} % over every run)"
    return f"domain   {100 * float(np.mean(share[stays])):.1f} % {what}, on the runs that stay in the box{every}"


def box_rmse(x: np.ndarray, xhat: np.ndarray, box: np.ndarray, angles: Sequence[int] = ()) -> np.ndarray:
    """Each run's RMSE over its samples and states of the error in units of the box's width per state, in %,
    (M,); ``x``, ``xhat`` (M, N, nx), ``box`` (nx, 2); angle states' error wrapped. NaN where ``xhat`` is not
    finite."""
    from ..metrics import wrap_angle

    error = np.asarray(xhat, dtype=float) - np.asarray(x, dtype=float)
    if angles:
        error[..., list(angles)] = wrap_angle(error[..., list(angles)])
    width = box[:, 1] - box[:, 0]
    return 100 * np.sqrt(np.mean((error / np.where(width > 0, width, 1.0)) ** 2, axis=(1, 2)))


def _quality_row(kind: str, x: np.ndarray, ours: np.ndarray, theirs: np.ndarray, ours_rmse: np.ndarray,
                 ekf_rmse: np.ndarray, kept: np.ndarray, angles: Sequence[int], total: int) -> str:
    """One input kind's entry of the summary, on its runs that stayed in the box (``x`` (M, N, nx)) of the
    ``total`` it scored."""
    from .. import metrics

    if not len(x):
        return f"{kind}: every run left the box"
    count = "" if len(x) == total else f" on {len(x)} of {total} runs"
    ours_smape = np.asarray(metrics.smape(x, ours, angles=angles))
    if not kept.any():
        return f"{kind} {np.mean(ours_rmse):.3g} % / the EKF diverged on every run{count}"
    ekf_smape = float(np.mean(metrics.smape(x[kept], theirs[kept], angles=angles)))
    lost = "" if kept.all() else f", the EKF diverged on {int((~kept).sum())} of {kept.size}: ratio on the rest"
    return (f"{kind} {np.mean(ours_rmse):.3g} % / {np.mean(ekf_rmse[kept]):.3g} % "
            f"({np.mean(ours_rmse[kept]) / np.mean(ekf_rmse[kept]):.2f}x{lost}), SMAPE {np.mean(ours_smape):.2f} % "
            f"/ {ekf_smape:.2f} %{count}")


def recipe_lines(obs: Any, box: np.ndarray, ekf: Any, process_std: Any, measurement_std: float) -> list[str]:
    """The observer and ``ekf`` on :data:`RECIPE_RUNS` held-out runs drawn as the card's training runs were (its
    ``training.config.rollouts`` recipe as :func:`~kklcasadi.plant.runs.resolved` for the plant: families,
    stabilising loop, input range, runs cut where they leave the box), seed :data:`SUMMARY_SEED`: RMSE after
    :data:`SETTLE_S` in % of the box's width and SMAPE, one line; none where the card records no recipe or one
    replaying logs (``--like``: the card keeps no log segments to replay)."""
    training = obs.model.card.get("training")
    record = training.get("config") if isinstance(training, dict) else None
    record = record.get("rollouts") if isinstance(record, dict) else None
    if not isinstance(record, dict) or record.get("envelope") is not None:
        return []
    plant = obs.system
    names = {f.name for f in fields(RolloutConfig)} - {"envelope"}
    given: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in record.items() if k in names}
    recipe = RolloutConfig(**given)
    recipe = resolved(plant, replace(recipe, n_traj=RECIPE_RUNS, chunk=RECIPE_RUNS))
    with quiet_casadi():
        runs = rollouts(plant, recipe, SUMMARY_SEED, dt=obs.dt, measurement_std=measurement_std,
                        process_std=process_std, time_scale=float(training.get("time_scale", 1.0)))
    cut = RECIPE_RUNS - len(runs.x)
    cut_text = f", {cut} of {RECIPE_RUNS} left the box: not scored, training cuts them there" if cut else ""
    if not len(runs.x):
        return [f"training every one of {RECIPE_RUNS} runs drawn as its training runs left the box"]
    ours = obs.simulate(runs.t, runs.y, runs.u).xhat
    theirs = ekf.simulate(runs.t, runs.y, runs.u).xhat
    kept = np.isfinite(theirs).all(axis=(1, 2))
    loop = "under the stabilising loop, " if recipe.stabilise else ""
    settle = min(SETTLE_S, 0.5 * float(runs.t[-1]))       # runs shorter than 10 s (a fast plant's): their second half
    after = "" if settle == SETTLE_S else f"; runs of {runs.t[-1]:.3g} s, RMSE after {settle:.3g} s"
    head = (f"training the same on {len(runs.x)} held-out runs drawn as its training runs were ({loop}families "
            f"{', '.join(recipe.kinds)}; seed {SUMMARY_SEED}{cut_text}{after}): RMSE ")
    late = runs.t >= settle
    row = _quality_row("", runs.x, ours, theirs, box_rmse(runs.x[:, late], ours[:, late], box, plant.angle_states),
                       box_rmse(runs.x[:, late], theirs[:, late], box, plant.angle_states), kept,
                       plant.angle_states, len(runs.x))
    return [head + row.strip()]
