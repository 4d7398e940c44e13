"""Closed-loop output feedback on the Duffing oscillator with a learned KKL observer.

The plant ``x1' = x2, x2' = -x1 - x1^3 + u, y = x1`` is simulated with a CasADi integrator
(CVODES, one sample interval per call, input held). Only ``y`` is measured: a PD controller with
cubic feedforward,

    u_k = sat(r + r^3 + kp (r - xhat1) - kd xhat2),

tracks a square-wave reference ``r(t)`` for ``x1`` using the observer's estimate ``xhat`` (from
``obs.estimator().make_step(y_k, u_k)``); the control computed from ``xhat_k`` is applied from the
next sample on (one sample of computation delay). The script writes a PNG of the true and the
estimated states, the reference and the input (stamped with the command; refused before any work where
``--out`` exists, written whole or not at all).

    python examples/closed_loop.py --model models/duffing/inject --out closed_loop.png

Any Duffing model directory works (``autonomous``, ``obs``, ``dyn``, ``inject``); an ``inject``
model is written from an autonomous one with ``kklcasadi.observer.kkl.make_inject_model``.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import kklcasadi as kc  # noqa: E402
from kklcasadi import provenance  # noqa: E402
from kklcasadi.plant.simulate import step_function, time_grid  # noqa: E402
from kklcasadi.writes import refuse_existing, write_file  # noqa: E402


def run(observer: kc.KKLObserver, T: float, *, amplitude: float = 0.5, omega: float = 0.5,
        kp: float = 2.0, kd: float = 1.5, u_max: float = 3.0, x0=(0.6, -0.4),
        measurement_std: float = 0.0, seed: int = 0) -> dict[str, np.ndarray]:
    """Simulate the closed loop for ``T`` seconds.

    Returns
    -------
    dict
        ``t`` (N,), ``x`` and ``xhat`` (N, 2), ``r`` and ``u`` (N,).
    """
    plant, dt = observer.system, observer.dt
    t = time_grid(T, dt)
    reference = kc.signals.make("square", amplitude=amplitude, omega=omega, phase=0.0)
    r = np.asarray(reference(t), dtype=float).reshape(t.size)
    plant_step = step_function(plant, dt, "cvodes")            # (x, [u; process noise]) -> x_next
    rng = np.random.default_rng(seed)
    estimator = observer.estimator()
    x = np.empty((t.size, plant.nx))
    xhat = np.empty_like(x)
    u = np.zeros(t.size)
    x[0] = x0
    u_next = 0.0
    for k in range(t.size):
        y = np.asarray(plant.h(x[k])).ravel() + measurement_std * rng.normal(size=plant.ny)
        u[k] = u_next
        xhat[k] = estimator.make_step(y, [u[k]])
        feedback = r[k] + r[k] ** 3 + kp * (r[k] - xhat[k, 0]) - kd * xhat[k, 1]
        u_next = float(np.clip(feedback, -u_max, u_max))
        if k + 1 < t.size:
            x[k + 1] = np.asarray(plant_step(x[k], np.r_[u[k], np.zeros(plant.nx)])).ravel()
    return {"t": t, "x": x, "xhat": xhat, "r": r, "u": u}


def plot(result: dict[str, np.ndarray], title: str, stamp: provenance.Stamp) -> bytes:
    """The true vs estimated states, the reference and the input (a PNG with ``stamp`` in its metadata)."""
    t = result["t"]
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(8, 7))
    for i, ax in enumerate(axes[:2]):
        ax.plot(t, result["x"][:, i], label=f"x{i + 1} true")
        ax.plot(t, result["xhat"][:, i], "--", label=f"x{i + 1} estimated")
        ax.set_ylabel(f"x{i + 1}")
    axes[0].plot(t, result["r"], ":", color="k", label="reference")
    axes[2].step(t, result["u"], where="post", color="C2")
    axes[2].set_ylabel("u")
    axes[2].set_xlabel("t [s]")
    for ax in axes[:2]:
        ax.legend(loc="upper right", fontsize=8)
    axes[0].set_title(title)
    fig.tight_layout()
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=120, metadata=provenance.png_metadata(stamp))
    plt.close(fig)
    return png.getvalue()


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="models/duffing/inject",
                        help="a Duffing model directory (default: %(default)s)")
    parser.add_argument("--out", default="closed_loop.png", help="PNG to write (default: %(default)s)")
    parser.add_argument("--T", type=float, default=30.0, help="horizon in seconds (default: %(default)s)")
    parser.add_argument("--measurement-std", type=float, default=0.0,
                        help="measurement noise standard deviation (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default: %(default)s)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    refuse_existing({out: "--out"})
    try:
        observer = kc.load_observer(args.model)
    except ValueError as exc:
        parser.error(f"{exc}\nTrain a Duffing model first, or pass --model DIR.")
    if observer.system.name != "duffing":
        parser.error(f"--model: the controller is designed for the Duffing oscillator; "
                     f"{args.model} is a model of {observer.system.name!r}.")
    result = run(observer, args.T, measurement_std=args.measurement_std, seed=args.seed)
    error = np.sqrt(np.mean((result["x"] - result["xhat"]) ** 2, axis=0))
    tracking = np.sqrt(np.mean((result["x"][:, 0] - result["r"]) ** 2))
    title = (f"Duffing, {observer.method} observer in the loop\nestimation RMSE x1 {error[0]:.3g}, "
             f"x2 {error[1]:.3g}; tracking RMSE {tracking:.3g}")
    png = plot(result, title, provenance.stamp(seeds={"noise": args.seed}))
    write_file(out, png, argument="--out")                    # whole or not at all, never over another file
    print(f"{title}\nwrote {out}")
    return out


if __name__ == "__main__":
    main()
