"""Output-feedback NMPC on Duffing and Van der Pol: true state vs EKF vs learned KKL observer.

The NMPC (:class:`kklcasadi.estimators.nmpc.NMPC`: Opti, multiple shooting with RK4, ipopt, compiled with
``opti.to_function``, warm-started) regulates ``x1`` to a reference that switches between
``+r`` and ``-r`` every ``period / 2`` seconds, with ``|u| <= 2`` and the soft bound
``|x2| <= x2_max``. It measures only ``y = x1`` and the inputs it applied: the state comes from

(a) the true state (full-information reference),
(b) the shipped EKF (:class:`kklcasadi.estimators.nmpc.EKFEstimator`), or
(c) the learned KKL observer (``obs.estimator().make_step``),

with the plant simulated by CVODES under the docs/protocol.md noise (process std 0.1 on ``xdot`` held
per interval, measurement std 0.1), the same noise for every feed. The script writes one table
(markdown and JSON) and one PNG, as one step and never over a file (refused before any run where one exists)::

    python examples/nmpc_output_feedback.py --out results/nmpc/all

The reported cost is the mean stage cost ``||x - x_ref||_Q^2 + ||u - u_ref||_R^2`` of the true
trajectory over the whole run (the observer's transient included) and after ``--settle`` seconds;
``violation`` is by how much the true ``|x2|`` exceeded its bound. The initial states are a Latin
hypercube over 80 % of the X0 box with ``x2`` rescaled to 80 % of its bound, so they satisfy it.
"""

from __future__ import annotations

import argparse
import io
import json
from pathlib import Path
from typing import Callable

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import kklcasadi as kc  # noqa: E402
from kklcasadi import provenance  # noqa: E402
from kklcasadi.estimators.nmpc import NMPC, ClosedLoop, EKFEstimator, TrueState, closed_loop, steady_state  # noqa: E402
from kklcasadi.writes import refuse_existing, write_dir  # noqa: E402

#: Per system: set point magnitude r for x1 and the bound on |x2|.
SCENARIOS = {"duffing": {"r": 0.8, "x2_max": 1.0}, "vdp": {"r": 1.0, "x2_max": 1.5}}
FEEDS = ("true state", "EKF", "KKL")


def reference(system: kc.System, r: float, period: float) -> Callable[[float], tuple]:
    """``t -> (x_ref, u_ref)``: ``x1 = +r`` on the first half of each period, ``-r`` after."""
    plus, minus = steady_state(system, r), steady_state(system, -r)
    return lambda t: plus if (t % period) < period / 2 else minus


def run_system(name: str, model: Path, *, T: float, horizon: int, n_trials: int, period: float,
               seed: int, settle: float, tighten: float = 0.0) -> tuple[list[dict], dict[str, ClosedLoop]]:
    """Closed loops of the three feeds on ``n_trials`` initial states (and, with ``tighten`` k > 0, the KKL feed
    with the bound on x2 tightened by k sigma of its covariance head); rows and trial 0's runs."""
    plant = kc.systems.get(name)
    observer = kc.load_observer(model)
    if observer.system.name != name:
        raise SystemExit(f"error: {model} is a model of {observer.system.name!r}, not {name!r}")
    scenario = SCENARIOS[name]
    controller = NMPC(plant, observer.dt, horizon, u_bounds=(-2.0, 2.0),
                      state_bounds={1: (-scenario["x2_max"], scenario["x2_max"])})
    ref = reference(plant, scenario["r"], period)
    # initial states: a Latin hypercube over 80 % of the X0 box, x2 rescaled to 80 % of its bound
    x0s = plant.sample_box(n_trials, seed, scale=0.8)
    x0s[:, 1] *= scenario["x2_max"] / (0.5 * (plant.x0_box[1, 1] - plant.x0_box[1, 0]))
    rows, first = [], {}
    feeds = [(feed, 0.0) for feed in FEEDS]
    if tighten > 0:
        if observer.covariance is None:
            raise SystemExit(f"error: --tighten: expected a model with a covariance head, received {model}")
        feeds.append(("KKL", tighten))
    for feed, k in feeds:
        runs = []
        for i, x0 in enumerate(x0s):
            estimator = {"true state": TrueState, "EKF": lambda: EKFEstimator(plant, observer.dt),
                         "KKL": observer.estimator}[feed]()
            runs.append(closed_loop(controller, estimator, ref, x0, T, seed=seed + i, tighten=k))
        label = feed if feed != "KKL" else f"KKL ({observer.method})" + (f", x2 bound - {k:g} sigma" if k else "")
        first[label] = runs[0]
        rows.append({
            "system": name, "feed": label,
            "trials": n_trials,
            "cost": float(np.mean([r.cost for r in runs])),
            "cost_after_settle": (float(np.mean([r.stage_cost[r.t >= settle].mean() for r in runs]))
                                  if T > settle else None),
            "tracking_rmse_x1": float(np.mean([np.sqrt(np.mean((r.x[:, 0] - r.x_ref[:, 0]) ** 2))
                                               for r in runs])),
            "violation_max": float(max(r.violation.max() for r in runs)),
            "violation_fraction": float(np.mean([np.mean(r.violation > 0) for r in runs])),
            "violation_max_after_settle": (float(max(r.violation[r.t >= settle].max() for r in runs))
                                           if T > settle else None),
            "estimation_rmse": float(np.mean([r.estimation_rmse for r in runs])),
            "solve_ms_mean": float(1e3 * np.mean([r.solve_time.mean() for r in runs])),
            "solve_ms_max": float(1e3 * max(r.solve_time.max() for r in runs)),
            "iterations_mean": float(np.mean([r.iterations.mean() for r in runs])),
            "failed": int(sum(r.failed.sum() for r in runs)),
            "u_max": float(max(np.abs(r.u).max() for r in runs)),
        })
    return rows, first


def table(rows: list[dict], *, settle: float) -> str:
    """The markdown table of :func:`run_system` rows."""
    head = ["system", "feed", "trials", "cost", f"cost t>={settle:g}s", "x1 RMSE",
            "max violation", f"max violation t>={settle:g}s", "violating samples", "estimation RMSE",
            "solve ms mean / max",
            "ipopt iter", "failed", "max abs(u)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append("| " + " | ".join([
            r["system"], r["feed"], str(r["trials"]), f"{r['cost']:.3f}",
            "-" if r["cost_after_settle"] is None else f"{r['cost_after_settle']:.3f}",
            f"{r['tracking_rmse_x1']:.3f}",
            f"{r['violation_max']:.3f}",
            "-" if r["violation_max_after_settle"] is None else f"{r['violation_max_after_settle']:.3f}",
            f"{100 * r['violation_fraction']:.1f} %",
            f"{r['estimation_rmse']:.3f}", f"{r['solve_ms_mean']:.1f} / {r['solve_ms_max']:.1f}",
            f"{r['iterations_mean']:.1f}", str(r["failed"]), f"{r['u_max']:.2f}"]) + " |")
    return "\n".join(lines)


def plot(runs: dict[str, dict[str, ClosedLoop]], stamp: provenance.Stamp) -> bytes:
    """One row per system: x1 and its reference, x2 and its bound, u; one line per feed (a stamped PNG)."""
    fig, axes = plt.subplots(len(runs), 3, figsize=(14, 3.2 * len(runs)), squeeze=False)
    for row, (name, by_feed) in enumerate(runs.items()):
        bound = SCENARIOS[name]["x2_max"]
        for j, (feed, res) in enumerate(by_feed.items()):
            axes[row, 0].plot(res.t, res.x[:, 0], color=f"C{j}", lw=1, label=feed)
            axes[row, 1].plot(res.t, res.x[:, 1], color=f"C{j}", lw=1, label=feed)
            axes[row, 2].step(res.t, res.u[:, 0], where="post", color=f"C{j}", lw=1, label=feed)
        first = next(iter(by_feed.values()))
        axes[row, 0].plot(first.t, first.x_ref[:, 0], "k:", lw=1, label="reference")
        for sign in (-1, 1):
            axes[row, 1].axhline(sign * bound, color="k", ls="--", lw=0.8)
            axes[row, 2].axhline(sign * 2.0, color="k", ls="--", lw=0.8)
        for col, label in enumerate(("x1 (true)", "x2 (true)", "u")):
            axes[row, col].set_ylabel(f"{name}: {label}")
        axes[row, 0].legend(fontsize=7, loc="lower left")
    for ax in axes[-1]:
        ax.set_xlabel("t (s)")
    fig.suptitle("Output-feedback NMPC, noise on (docs/protocol.md): true state vs EKF vs KKL observer")
    fig.tight_layout()
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=110, metadata=provenance.png_metadata(stamp))
    plt.close(fig)
    return png.getvalue()


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--systems", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS))
    parser.add_argument("--method", default="inject",
                        help="learned observer under models/SYSTEM/ (default: %(default)s)")
    parser.add_argument("--models-root", default="models")
    parser.add_argument("--T", type=float, default=20.0, help="seconds per run (default: %(default)s)")
    parser.add_argument("--horizon", type=int, default=20, help="NMPC intervals (default: %(default)s)")
    parser.add_argument("--trials", type=int, default=5, help="initial states (default: %(default)s)")
    parser.add_argument("--period", type=float, default=10.0, help="reference period in s")
    parser.add_argument("--settle", type=float, default=5.0, help="s; cost also reported after it")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tighten", type=float, default=0.0, metavar="K",
                        help="also run the KKL feed with the bound on x2 tightened by K sigma of the observer's "
                        "covariance head (a model with one, e.g. --method bank)")
    parser.add_argument("--out", default="results/nmpc/all", help="output directory")
    args = parser.parse_args(argv)
    out = Path(args.out)
    names = ("nmpc_table.md", "nmpc.json", "nmpc.png")
    refuse_existing({out / name: "--out" for name in names})   # before any run: never written over
    rows, runs = [], {}
    for name in args.systems:
        model = Path(args.models_root) / name / args.method
        system_rows, runs[name] = run_system(name, model, T=args.T, horizon=args.horizon,
                                             n_trials=args.trials, period=args.period,
                                             seed=args.seed, settle=args.settle, tighten=args.tighten)
        rows += system_rows
    text = table(rows, settle=args.settle)
    stamp = provenance.stamp(seeds={"initial_states_and_noise": args.seed})    # names this command in every file
    contents = (provenance.markdown(text + "\n", stamp),
                json.dumps(provenance.json_record({"settings": vars(args), "rows": rows}, stamp), indent=1) + "\n",
                plot(runs, stamp))
    write_dir(out, dict(zip(names, contents)), argument="--out")  # the three files as one step, or none of them
    png = out / "nmpc.png"
    print(text)
    print(f"wrote {out / 'nmpc_table.md'}, {out / 'nmpc.json'}, {png}")
    return {"rows": rows, "runs": runs, "png": png}


if __name__ == "__main__":
    main()
