"""Moving-horizon estimation with and without a learned KKL observer, on one noisy run.

Estimates one docs/protocol.md run (noise std 0.1 on ``xdot`` and ``y``) of a plant with

* the learned KKL observer (``obs.simulate``),
* the EKF (``kklcasadi.estimators.ekf.EKF``),
* the MHE on the exact model with its EKF arrival cost (:class:`kklcasadi.estimators.mhe.MHE`, ``N = 10``),
* the KKL-primed MHE (:class:`kklcasadi.estimators.kkl_mhe.KKLPrimedMHE`, ``N = 5``): the observer's estimate is
  the arrival prior (its error profile calibrated on other runs) and the warm start,

prints SMAPE, time per sample and the solver statistics, and writes a PNG (refused before any work where
``--out`` exists; written whole or not at all)::

    python examples/mhe_estimation.py --model models/duffing/inject --out mhe_estimation.png
"""

from __future__ import annotations

import argparse
import io
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import kklcasadi as kc  # noqa: E402
from kklcasadi import provenance  # noqa: E402
from kklcasadi.estimators.ekf import EKF  # noqa: E402
from kklcasadi.estimators.kkl_mhe import KKLPrimedMHE, kkl_error_profile  # noqa: E402
from kklcasadi.estimators.mhe import MHE  # noqa: E402
from kklcasadi.evaluation.protocol import Protocol  # noqa: E402
from kklcasadi.writes import refuse_existing, write_file  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="models/duffing/inject")
    parser.add_argument("--kind", default="square", choices=("zero", "constant", "sinusoid", "square"))
    parser.add_argument("--T", type=float, default=20.0)
    parser.add_argument("--horizon", type=int, default=10, help="MHE horizon")
    parser.add_argument("--primed-horizon", type=int, default=5)
    parser.add_argument("--calibration-trials", type=int, default=3)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--out", default="mhe_estimation.png")
    args = parser.parse_args(argv)
    out = Path(args.out)
    refuse_existing({out: "--out"})
    obs = kc.load_observer(args.model)
    plant = obs.system
    run = Protocol(n_trials=1, T=args.T, seed=args.seed).trials(plant, args.kind)
    t, x, y, u = run.t, run.x[0], run.y[0], run.u[0]
    calibration = Protocol(n_trials=args.calibration_trials, T=args.T, seed=args.seed + 1)
    primed = KKLPrimedMHE(obs, kkl_error_profile(obs, calibration), args.primed_horizon)
    estimators = {
        f"KKL ({obs.method})": lambda: obs.simulate(t, y, u).xhat,
        "EKF": lambda: EKF(plant, obs.dt).simulate(t, y, u).xhat,
        f"MHE N={args.horizon}": lambda: MHE(plant, obs.dt, args.horizon).simulate(t, y, u),
        f"KKL-primed MHE N={args.primed_horizon}": lambda: primed.simulate(t, y, u),
    }
    results = {}
    for label, estimate in estimators.items():
        start = time.perf_counter()
        estimated = estimate()
        seconds = time.perf_counter() - start
        xhat, stats = ((estimated, None) if isinstance(estimated, np.ndarray)
                       else (estimated.xhat, estimated.stats))
        results[label] = xhat
        print(f"{label:24s} SMAPE {kc.metrics.smape(x, xhat):6.2f} %   "
              f"{1e3 * seconds / t.size:7.3f} ms/sample" + (f"   {stats}" if stats else ""))
    fig, axes = plt.subplots(plant.nx, 1, sharex=True, figsize=(9, 2.4 * plant.nx))
    for i, ax in enumerate(np.atleast_1d(axes)):
        ax.plot(t, x[:, i], "k", lw=1.5, label="true")
        for j, (label, xhat) in enumerate(results.items()):
            ax.plot(t, xhat[:, i], color=f"C{j}", lw=1, label=label)
        ax.set_ylabel(f"x{i + 1}")
    np.atleast_1d(axes)[0].legend(fontsize=7, ncol=3)
    np.atleast_1d(axes)[-1].set_xlabel("t (s)")
    fig.suptitle(f"{plant.name}, {args.kind} input, noise std 0.1")
    fig.tight_layout()
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=110,
                metadata=provenance.png_metadata(provenance.stamp(seeds={"trials": args.seed})))
    plt.close(fig)
    write_file(out, png.getvalue(), argument="--out")          # whole or not at all, never over another file
    print(f"wrote {out}")
    return results


if __name__ == "__main__":
    main()
