"""``kklcasadi demo``: estimate one noisy run with a shipped observer (or yours) and the EKF, print the
errors, the domain monitor and the step time, and write a PNG. A run whose state escapes is one
line ``error: ...`` (exit status 2). The observer and the EKF run their compiled steps
(:mod:`kklcasadi.evaluation.chunked`: gcc, cached; the vectorised exp/tanh, within 1e-14 per step of
the VM), or the CasADi VM where there is no C compiler (the compiler's one-line warning)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from ..plant import signals as sig
from ..writes import refuse_existing
from .flags import (
    CommandError,
    add_dt,
    add_noise_levels,
    add_plant,
    add_system,
    levels_text,
    load,
    model_label,
    nonnegative_float,
    out_path,
    plant_of,
    positive_float,
    quiet_casadi,
    run_noise,
    shipped,
    stamp_of,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("demo", help="estimate a noisy run with a shipped observer and the EKF, write a PNG")
    add_system(d, with_models=True, what="the system of the shipped model (default duffing)")
    d.add_argument("--method", default="bank",
                   help="shipped model under models/SYSTEM/ (default: bank, the observer fit for noisy measurements)")
    d.add_argument("--model", help="a model directory instead of a shipped one")
    add_plant(d, "with --model")
    d.add_argument("--input", default="square", choices=sig.BENCHMARK_KINDS,
                   help="the input signal u(t) of the run (default square)")
    d.add_argument("--amplitude", type=nonnegative_float, default=0.8,
                   help="the input's amplitude, the constant's value (default 0.8)")
    d.add_argument("--omega", type=positive_float, default=1.0,
                   help="the sinusoid's and square wave's angular frequency, rad/s (default 1)")
    add_noise_levels(d, "the run's and the EKF's (default: the card's levels where it records both, else "
                        "docs/protocol.md's 0.1)")
    add_dt(d, "the sample time; the model's (a model runs only at its own)")
    d.add_argument("--T", type=positive_float, default=50.0, help="horizon, seconds")
    d.add_argument("--seed", type=int, default=0, help="seed of the initial state and the noise (default 0)")
    d.add_argument("--out", default="demo.png", help="the figure to write, PNG (default demo.png; refused where it "
                   "exists)")
    d.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Estimate one noisy trajectory with a shipped observer and the EKF; print SMAPE, write a PNG."""
    from .. import metrics
    from ..estimators.ekf import EKF
    from ..evaluation.chunked import FAST, ChunkedEKF, ChunkedObserver
    from ..evaluation.report import estimates_plot
    from ..plant.simulate import simulate_batch

    if args.model is None and args.plant is not None:
        raise CommandError("--plant: give the model trained for it with --model DIR")
    out = out_path(args.out, "--out", directory=False)
    if out is None:                          # the flag has a default: only a Namespace built by hand lacks it
        raise CommandError("--out: expected a file path for the figure, received none")
    refuse_existing({out: "--out"})          # the figure is written whole, never over a file
    model = Path(args.model) if args.model else shipped(args.system or "duffing", args.method)
    obs = load(model, plant_of(args))
    plant = obs.system
    if args.system is not None and args.system != plant.name:
        raise CommandError(f"--system {args.system}: the model {model} is for the system {plant.name!r}; "
                           f"drop --system or pass a model for {args.system!r}")
    if args.input == "zero":
        u = sig.Zero(plant.nu)
    elif args.input == "constant":
        u = sig.Constant(np.full(plant.nu, args.amplitude))
    else:
        u = sig.make(args.input, amplitude=np.full(plant.nu, args.amplitude), omega=args.omega)

    if args.dt is not None and abs(args.dt - obs.dt) > 1e-12 * obs.dt:
        raise CommandError(f"--dt {args.dt:g}: the model {model} runs at dt = {obs.dt:g} s; drop --dt or pass a model "
                           f"trained at {args.dt:g} s")
    process_std, measurement_std = run_noise(obs, args.process_std, args.measurement_std)
    x0 = plant.sample_box(1, args.seed)[0]
    with quiet_casadi():
        batch = simulate_batch(plant, x0[None], u, T=args.T, dt=obs.dt, process_std=process_std,
                               measurement_std=measurement_std, seed=[args.seed], n_threads=1)
    if not batch.ok[0]:
        k = int(np.argmax(np.isnan(batch.x[0]).any(axis=1)))
        raise CommandError(f"--input {args.input}: the plant {plant.name!r} escaped at t = {batch.t[k]:.3g} s of the "
                           f"run from x0 = {np.round(x0, 3).tolist()} (its state left |x| < 1e6 or the integrator "
                           "failed); lower --amplitude, change --omega or --seed, shorten --T, or pick another --input")
    tr = batch[0]
    compiled = FAST.available()
    chunked = ChunkedObserver(obs, compiler=FAST if compiled else None)
    chunked.function(chunked.size(len(tr.t)))                  # compiled (or found in the cache) before the clock
    t0 = time.perf_counter()
    xhat, _, in_domain = chunked.estimate(tr.y, tr.u)
    t_obs = time.perf_counter() - t0
    ekf = ChunkedEKF(EKF.for_noise(plant, obs.dt, process_std=process_std, measurement_std=measurement_std),
                     compiler=FAST if compiled else None).run(tr.y, tr.u)[0]
    print(f"model    {model_label(model)}  ({obs.method}, system {plant.name}, nz {obs.nz}, window {obs.window}, "
          f"dt {obs.dt:g} s)")
    print(f"input    {args.input} (amplitude {args.amplitude}, omega {args.omega} rad/s), noise std process "
          f"{levels_text(process_std)}, measurement {measurement_std:g} (the EKF's too), "
          f"x0 {np.round(x0, 3).tolist()}, T {args.T} s")
    print(f"SMAPE    KKL ({obs.method}) {metrics.smape(tr.x, xhat):6.2f} %   EKF {metrics.smape(tr.x, ekf):6.2f} %")
    settle = min(5.0, round(tr.t[-1] / 2, 2))
    print(f"RMSE t>{settle:g} KKL ({obs.method}) {metrics.rmse_after(tr.t, tr.x, xhat, settle):6.3f}     "
          f"EKF {metrics.rmse_after(tr.t, tr.x, ekf, settle):6.3f}")
    if in_domain is not None:
        print(f"domain   {int(in_domain.sum())} of {len(tr.t)} estimates in the domain the maps were trained on"
              + ("; most lie outside it: the KKL errors above are not to be trusted" if in_domain.mean() < 0.5
                 else ""))
    print(f"time     {t_obs * 1e3:.1f} ms for {len(tr.t)} samples ({t_obs / len(tr.t) * 1e6:.1f} us/step with the "
          f"domain monitor, {'compiled C' if compiled else 'CasADi VM: no C compiler'})")
    estimates_plot(tr.t, tr.x, tr.y, {f"KKL ({obs.method})": xhat, "EKF": ekf}, out, u=tr.u,
                   in_domain=in_domain, stamp=stamp_of(args, run=args.seed),
                   title=f"{plant.name}: {args.input} input, noise std {levels_text(process_std)} (process) / "
                         f"{measurement_std:g} (measurement), seed {args.seed}")
    print(f"plot     {out}")
    return 0
