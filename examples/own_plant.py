"""Your own plant, end to end: a damped pendulum the package does not ship.

The plant is written in CasADi (``make_plant``), a Phase-1 observer and its model-based ``inject``
variant are trained for it, and the observer is checked noise-free under zero, constant,
sinusoidal and square inputs that keep the state in its box (RMSE after 5 s), and under a resonant
square wave that drives it out of its box. The same from the command line::

    kklcasadi train --plant examples/own_plant.py:make_plant --method inject --out models/pendulum/inject
    kklcasadi demo --plant examples/own_plant.py:make_plant --model models/pendulum/inject --input square

Run: ``python examples/own_plant.py [--out DIR] [--epochs N]`` (writes the models ``DIR/autonomous`` and
``DIR/inject`` and the plot ``DIR/own_plant.png``, refused before any work where one of them exists; the plot is
rendered in memory and written whole or not at all).
"""

from __future__ import annotations

import argparse
import io
import time
from pathlib import Path

import casadi as ca
import numpy as np

import kklcasadi as kc

#: The test inputs; the last one drives the pendulum out of its box.
CASES = (
    ("zero", kc.signals.Zero(1)),
    ("constant 0.3", kc.signals.Constant([0.3])),
    ("sinusoid 0.3, 0.7 rad/s", kc.signals.make("sinusoid", amplitude=0.3, omega=0.7)),
    ("square 0.3, 0.5 rad/s", kc.signals.make("square", amplitude=0.3, omega=0.5)),
    ("resonant square 0.6, 1 rad/s", kc.signals.make("square", amplitude=0.6, omega=1.0)),
)


def make_plant() -> kc.System:
    """Damped pendulum ``x1' = x2, x2' = -sin x1 - 0.3 x2 + u``, ``y = x1``, box [-1.5, 1.5]^2."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    return kc.System("pendulum", x, u, [x[1], -ca.sin(x[0]) - 0.3 * x[1] + u], x[0], [[-1.5, 1.5], [-1.5, 1.5]],
                     description="damped pendulum, y = angle")


def main(out: Path, epochs: int | None = None, n_traj: int | None = None, T: float = 30.0) -> dict:
    """Train (Phase 1 + inject) into ``out`` and report the noise-free RMSE after 5 s per input."""
    from kklcasadi.train import default_config, train_observer
    from kklcasadi.writes import refuse_existing, write_file

    png = out / "own_plant.png"
    refuse_existing({out / "autonomous": "--out", out / "inject": "--out", png: "--out"})
    plant = make_plant()
    overrides = {} if n_traj is None else {"n_traj": n_traj, "n_pde": 25 * n_traj}
    t0 = time.perf_counter()
    train_observer(plant, "autonomous", out / "autonomous", threads=1,
                   config=default_config(plant.name, "autonomous", epochs=epochs, **overrides))
    obs_dir = train_observer(plant, "inject", out / "inject")      # no training: the exact term
    print(f"trained Phase 1 + inject in {time.perf_counter() - t0:.0f} s")

    obs = kc.load_observer(obs_dir, system=plant)
    results, traces = {}, {}
    for k, (label, u) in enumerate(CASES):
        x0 = plant.sample_box(len(CASES), seed=3)[k] * 0.6
        tr = kc.simulate(plant, x0, u, T=T, dt=obs.dt)
        est = obs.simulate(tr.t, tr.y, tr.u)
        rmse = float(kc.metrics.rmse_after(tr.t, tr.x, est.xhat, 5.0))
        in_box = bool(np.all(np.abs(tr.x) <= 1.5))
        results[label] = {"rmse_after_5s": rmse, "state_in_box": in_box,
                          "estimates_in_domain": float(np.mean(est.in_domain)) if est.in_domain is not None else None}
        traces[label] = (tr, est)
        flag = "" if est.in_domain is None else f", {100 * np.mean(est.in_domain):.0f} % of estimates in the domain"
        print(f"{label:<30s} RMSE after 5 s {rmse:.4f}  (state {'in' if in_box else 'leaves'} the box{flag})")
    write_file(png, _plot(traces), argument="--out")
    print(f"plot {png}")
    return results


def _plot(traces: dict) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from kklcasadi import provenance

    fig, axes = plt.subplots(len(traces), 1, figsize=(9, 2.2 * len(traces)), sharex=True)
    for ax, (label, (tr, est)) in zip(axes, traces.items()):
        ax.plot(tr.t, tr.x[:, 0], "k", lw=1.2, label="angle x1")
        ax.plot(tr.t, est.xhat[:, 0], "C1--", lw=1.2, label="estimate")
        ax.plot(tr.t, tr.x[:, 1], "0.5", lw=1.0, label="velocity x2")
        ax.plot(tr.t, est.xhat[:, 1], "C0--", lw=1.0, label="estimate")
        if est.in_domain is not None and not est.in_domain.all():
            ax.fill_between(tr.t, *ax.get_ylim(), where=~est.in_domain, color="C3", alpha=0.15,
                            label="outside the trained domain")
        ax.set_title(label, fontsize=9)
    axes[0].legend(fontsize=7, ncol=5, loc="upper right")
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=110, metadata=provenance.png_metadata(provenance.stamp(seeds={"train": 0})))
    plt.close(fig)
    return png.getvalue()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("models/pendulum"))
    parser.add_argument("--epochs", type=int, help="epochs of each Phase-1 stage (default: the package's "
                        "budget for a new plant, kklcasadi.train.config.NEW_PLANT_PHASE1)")
    args = parser.parse_args()
    main(args.out, args.epochs)
