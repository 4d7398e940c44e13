"""Fit the covariance head of a shipped ``bank`` model (issue 49): the decoder and every other array unchanged.

    OMP_NUM_THREADS=2 python benchmarks/covariance_heads.py MODEL --out DIR [--fit-seed 11] [--val-seed 12]
        [--fit-trials 50] [--val-trials 25] [--every 4] [--dense-until 0] [--epochs 20] [--hidden 16] [--seed 0]
        [--noisy-levels 0.2] [--time-constants 1 2.5 5] [--inflation-only]

The head (:mod:`kklcasadi.model.variants.covariance`) is fit by the Gaussian likelihood of the observer's own
errors (:func:`kklcasadi.train.covariance.fit_covariance`) on noisy runs of the protocol's four input regimes
(docs/protocol.md: its noise levels, horizon and ``id`` ranges) drawn from ``--fit-seed`` (``--fit-trials`` per
regime, every ``--every``-th sample, and every sample before ``--dense-until`` seconds: the start of a run, where
the errors are largest and change fastest, would otherwise be a few samples in a thousand), then calibrated per state
(:func:`kklcasadi.train.covariance.calibrate`) on other runs of the same recipe from ``--val-seed``. Neither seed
is the protocol's scored seed (2026). DIR gets the model with the head (``architecture.covariance``, the arrays
``covariance/*``, and ``training.covariance``: seeds, samples, the fit, the calibration factors and the validation
runs' consistency), its history copied; the script checks that the estimates of DIR equal the model's bit for bit
on the validation runs, and stops otherwise.

Then the head's inflation by the measurement residual (:mod:`kklcasadi.model.variants.inflation`,
``architecture.inflation``): ``R`` the protocol's measurement noise variance, ``c`` and the time constant chosen by
:func:`kklcasadi.train.covariance.calibrate_inflation` on the calibration runs and on runs of the same recipe and
seed at the process and measurement noise std ``--noisy-levels`` (validation runs only; the choice and every
candidate's scores go to ``training.covariance.inflation``). ``--inflation-only`` keeps MODEL's head as it is (no
fit, no calibration) and sets only its inflation.
"""

from __future__ import annotations

import argparse
import copy
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from kklcasadi import consistency as cs
from kklcasadi import provenance
from kklcasadi.evaluation.compiled import CompiledRecord
from kklcasadi.evaluation.protocol import Protocol
from kklcasadi.model.files import MODEL_FILES, load_model, save_model
from kklcasadi.model.shipped import resolve
from kklcasadi.model.variants.bankdecoder import ASINH_SCALE, decoder_features
from kklcasadi.model.variants.covariance import COVARIANCE, SCALE, covariance_numpy
from kklcasadi.model.variants.inflation import INFLATION
from kklcasadi.nets.specs import MLPSpec
from kklcasadi.observer.kkl import load_observer
from kklcasadi.plant import signals as sig
from kklcasadi.train.covariance import (
    CovarianceConfig,
    ValidationRuns,
    calibrate,
    calibrate_inflation,
    fit_covariance,
    output_errors,
)
from kklcasadi.writes import refuse_existing


def runs(obs, seed: int, trials: int, method: str = "rk", noise: float | None = None, measured: bool = False):
    """The observer (compiled, bitwise ``obs.simulate``) on ``trials`` noisy protocol runs per input regime from
    ``seed`` (at the protocol's noise, or at process and measurement noise std ``noise``): (t, x, xhat, features),
    trials of every regime stacked, and with ``measured`` the measurements last."""
    stds = {} if noise is None else {"process_std": noise, "measurement_std": noise}
    protocol = Protocol(n_trials=trials, seed=seed, method=method, **stds)
    record = CompiledRecord(obs)
    xs, ys, xhats, feats = [], [], [], []
    for kind in sig.BENCHMARK_KINDS:
        batch = protocol.trials(obs.system, kind)
        ok = batch.ok
        xhat, z, _ = record.record(batch.t, batch.y[ok], batch.u[ok])
        xs.append(batch.x[ok])
        ys.append(batch.y[ok])
        xhats.append(xhat)
        feats.append(decoder_features(z, batch.y[ok], batch.u[ok]))
        t = batch.t
        print(f"runs     seed {seed}, {kind}, noise {protocol.measurement_std}: {int(ok.sum())} trials", flush=True)
    out = (t, np.concatenate(xs), np.concatenate(xhats), np.concatenate(feats))
    return (*out, np.concatenate(ys)) if measured else out


def inflation(obs, head: MLPSpec, arrays, args) -> tuple[dict, dict]:
    """The head's inflation (``architecture.inflation``) and its record, chosen on validation runs (``--val-seed``)
    at the protocol's noise and at ``--noisy-levels``."""
    out_std, asinh = arrays["decoder/out_std"], arrays[ASINH_SCALE]

    def validation(noise):
        t, x, xhat, f, y = runs(obs, args.val_seed, args.val_trials, noise=noise, measured=True)
        return ValidationRuns(t, x, y, xhat, covariance_numpy(head, arrays, f, xhat, out_std, asinh))

    R = [Protocol.measurement_std ** 2] * obs.ny
    chosen, table = calibrate_inflation(obs.system, obs.dt, R, validation(None),
                                        [validation(level) for level in args.noisy_levels], args.time_constants)
    for row in table:
        print(f"inflation time constant {row['time_constant']:g} s: worst 2-sigma coverage off by "
              f"{100 * row['worst']:.2f} points; " + "; ".join(
                  f"mean {s['mean_inflation']:.3f}, coverage {[round(100 * v, 1) for v in s['coverage_2sigma']]}"
                  for s in row["sets"]), flush=True)
    print(f"inflation {chosen.to_card()}", flush=True)
    record = {"how": "c: the residual statistic's mean on the validation runs at the protocol's noise; the time "
                     "constant: the candidate whose worst 2-sigma coverage (states, noise levels) is nearest 95.45 %",
              "validation_seed": args.val_seed, "validation_trials_per_regime": args.val_trials,
              "noise_levels": [Protocol.measurement_std, *args.noisy_levels], "candidates": table}
    return chosen.to_card(), record


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", help="a bank model directory or a shipped name (duffing/bank)")
    p.add_argument("--out", required=True, type=Path, help="new directory for the model with the head")
    p.add_argument("--fit-seed", type=int, default=11)
    p.add_argument("--val-seed", type=int, default=12)
    p.add_argument("--fit-trials", type=int, default=50, help="fit runs per input regime")
    p.add_argument("--val-trials", type=int, default=25, help="calibration runs per input regime")
    p.add_argument("--every", type=int, default=4, help="keep every n-th sample of the fit runs")
    p.add_argument("--dense-until", type=float, default=0.0, metavar="T",
                   help="and every sample before T seconds (default 0: none)")
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--hidden", type=int, nargs="+", default=[16])
    p.add_argument("--seed", type=int, default=0, help="the head's initialisation and batches")
    p.add_argument("--noisy-levels", type=float, nargs="+", default=[0.2], metavar="STD",
                   help="noise std of the validation runs the inflation's time constant is chosen on, besides the "
                        "protocol's (default 0.2)")
    p.add_argument("--time-constants", type=float, nargs="+", default=[1.0, 2.5, 5.0], metavar="S",
                   help="the inflation's candidate time constants in seconds (default 1 2.5 5)")
    p.add_argument("--inflation-only", action="store_true",
                   help="keep MODEL's covariance head; set only its inflation")
    args = p.parse_args()
    if args.fit_seed in (Protocol.seed, args.val_seed) or args.val_seed == Protocol.seed:
        p.error(f"--fit-seed, --val-seed: expected two seeds other than each other and the scored seed "
                f"{Protocol.seed}, received {args.fit_seed} and {args.val_seed}")
    refuse_existing({args.out / name: "--out" for name in MODEL_FILES})         # before any fit, never over a model
    source = resolve(args.model)
    model = load_model(source)
    if model.method != "bank":
        p.error(f"model: expected a 'bank' model, received method {model.method!r}")
    obs = load_observer(source)
    out_std, asinh = model.arrays["decoder/out_std"], model.arrays[ASINH_SCALE]
    start = time.perf_counter()
    if args.inflation_only:
        if COVARIANCE not in model.card["architecture"]:
            p.error("--inflation-only: expected a model with a covariance head (architecture.covariance)")
        head = MLPSpec.from_card(model.card["architecture"][COVARIANCE], "architecture", COVARIANCE)
        entry, record = inflation(obs, head, model.arrays, args)
        card = copy.deepcopy(model.card)
        card["architecture"][INFLATION] = entry
        stamp = provenance.stamp(seeds={"validation": args.val_seed})
        card["training"]["covariance"]["inflation"] = {"command": stamp.command, "commit": stamp.commit, **record,
                                                       "wall_time_s": round(time.perf_counter() - start, 1)}
        write(args.out, source, obs, model.arrays, card, args.val_seed, start)
        return

    t, x, xhat, f = runs(obs, args.fit_seed, args.fit_trials)
    k = (np.arange(t.size) % args.every == 0) | (t < args.dense_until)
    fit_f = f[:, k].reshape(-1, f.shape[-1])
    fit_e = output_errors(x[:, k], xhat[:, k], out_std, asinh).reshape(-1, obs.nx)
    config = CovarianceConfig(hidden=tuple(args.hidden), loop=replace(CovarianceConfig().loop, epochs=args.epochs))
    fitted = fit_covariance(fit_f, fit_e, config, seed=args.seed, progress=True)
    print(f"fit      {len(fit_f)} samples, {fitted.fit.summary()}", flush=True)

    tv, xv, xhv, fv = runs(obs, args.val_seed, args.val_trials)
    scale = calibrate(fitted.arrays, fitted.arch, fv.reshape(-1, fv.shape[-1]), xhv.reshape(-1, obs.nx),
                      (xv - xhv).reshape(-1, obs.nx), out_std, asinh)
    print(f"calibration factors {scale.tolist()}", flush=True)
    head = MLPSpec.from_card(fitted.arch, "architecture", COVARIANCE)
    cov = covariance_numpy(head, {**fitted.arrays, SCALE: scale}, fv, xhv, out_std, asinh)
    score = cs.consistency(xv, xhv, cov, t=tv).to_json()
    print(f"validation runs (seed {args.val_seed}, calibrated there): {score}", flush=True)

    arrays = {**model.arrays, **fitted.arrays, SCALE: scale}
    entry, record = inflation(obs, head, arrays, args)
    card = copy.deepcopy(model.card)
    card["architecture"][COVARIANCE] = fitted.arch
    card["architecture"][INFLATION] = entry
    stamp = provenance.stamp(seeds={"fit": args.fit_seed, "validation": args.val_seed, "head": args.seed})
    card["training"]["covariance"] = {
        "how": "Gaussian negative log-likelihood of the observer's errors on noisy protocol runs (docs/protocol.md "
               "noise, id ranges, RK4 plant), then one calibration factor per state on other runs",
        "command": stamp.command, "commit": stamp.commit, "fit_seed": args.fit_seed, "fit_trials_per_regime":
        args.fit_trials, "fit_every": args.every, "fit_dense_until": args.dense_until, "samples": int(len(fit_f)),
        "head_seed": args.seed,
        "config": {"hidden": list(config.hidden), "activation": config.activation, "epochs": args.epochs},
        "fit": fitted.fit.summary(), "validation_seed": args.val_seed, "validation_trials_per_regime":
        args.val_trials, "scale": scale.tolist(), "validation": score, "inflation": record,
        "wall_time_s": round(time.perf_counter() - start, 1)}
    write(args.out, source, obs, arrays, card, args.val_seed, start)


def write(out: Path, source, obs, arrays, card, seed: int, start: float) -> None:
    """Save the model with the head at ``out`` (MODEL's history with it, in the same step), and check that its
    estimates are MODEL's bit for bit on validation runs (stop otherwise)."""
    history = Path(source) / "history.json"
    out = save_model(out, arrays, card, extra={history.name: history.read_bytes()} if history.exists() else None)

    headed = load_observer(out)
    check = Protocol(n_trials=4, seed=seed, method="rk").trials(obs.system, "square")
    a = obs.simulate(check.t, check.y[check.ok], check.u[check.ok])
    b = headed.simulate(check.t, check.y[check.ok], check.u[check.ok])
    if not (np.array_equal(a.xhat, b.xhat) and np.array_equal(a.z, b.z)):
        raise SystemExit(f"{out}: the estimates differ from {source}'s (max {np.max(np.abs(a.xhat - b.xhat))})")
    print(f"wrote {out} ({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
