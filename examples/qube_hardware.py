"""A real rig, end to end: the six logged free swings of a Quanser Qube Servo 2 (``examples/qube/``).

1. **Settings from the fit runs only.** The runs are split before anything is looked at: runs 1
   and 3 fit the one setting the recipe needs from the rig, the encoders' noise (the std of the
   logged angles about a Savitzky-Golay smoothing of them); runs 5, 7, 9 and 11 are scored and
   fit nothing.
2. **Train** with the Python equivalent of the one command for a first observer::

       kklcasadi train --plant examples/qube/qube_plant.py:make_plant --dt 0.004 --measurement-std S --out DIR

   (``train_observer(plant, "bank", DIR, dt=0.004, config=...)`` with ``measurement_std = S``), for
   ``y = (theta, alpha)`` and for ``y = alpha`` (``make_plant_alpha``).
3. **Estimate every log** with :func:`kklcasadi.evaluation.logged.estimate_log` (the log put on the
   4 ms grid, angles unwrapped), beside the EKF of ``examples/qube/check_logs.py`` (``R = 1e-6 I``,
   process variance ``1e-3`` per step on the velocities) and a filtered finite difference of the
   angles (the backward difference low-passed at 50 rad/s, ``50 s / (s + 50)``), and score them
   for ``t >= 2 s``: the angles against the measured ones (wrapped), the velocities against the
   zero-phase reference :func:`kklcasadi.plant.logs.savgol_derivative` (window 15, cubic).
4. **Plot** the angles and velocities of a scored run against the reference (``OUT/qube_<y>.png``).

Run: ``python examples/qube_hardware.py [--out DIR] [--epochs N] [--runs N] [--horizon T]``
(``--runs``/``--horizon``: the number and length in seconds of the bank's training runs, default
the recipe's); ``tests/test_qube_hardware.py`` runs it on a tiny budget.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.signal import savgol_filter

import kklcasadi as kc
from kklcasadi.evaluation.logged import estimate_log
from kklcasadi.metrics import rmse
from kklcasadi.plant.logs import Log, read_log, savgol_derivative

HERE = Path(__file__).resolve().parent / "qube"
sys.path.insert(0, str(HERE))
from qube_plant import BOX, STATES, make_plant, make_plant_alpha  # noqa: E402

DT = 0.004
#: The split, fixed before anything was fitted: settings from these runs only ...
FIT_RUNS = (1, 3)
#: ... and scores on these.
SCORED_RUNS = (5, 7, 9, 11)
#: Scores leave out the first seconds (every estimator starts from its prior).
SETTLE = 2.0
#: The filtered finite difference: the backward difference low-passed at this rate (rad/s).
FFD_RATE = 50.0
#: The measured outputs per case: (label, plant factory, y columns).
CASES = {"theta_alpha": ("y = (theta, alpha)", make_plant, ("theta", "alpha")),
         "alpha": ("y = alpha", make_plant_alpha, ("alpha",))}


def run_path(k: int) -> Path:
    return HERE / "data" / f"free_swing_{k}.csv"


def read_angles(k: int) -> Log:
    """Run ``k``'s two angles on the 4 ms grid, unwrapped, alpha on the box's branch (hanging at pi)."""
    return read_log(run_path(k), time_col="time", y_cols=("theta", "alpha"), angle_cols=("theta", "alpha"), dt=DT,
                    box={"theta": BOX[0], "alpha": BOX[1]})


def encoder_noise(runs: tuple[int, ...]) -> float:
    """The std of the logged angles about their Savitzky-Golay smoothing (window 15, cubic) on ``runs``."""
    residuals = [log.y - savgol_filter(log.y, 15, 3, axis=0) for log in map(read_angles, runs)]
    return float(np.std(np.concatenate(residuals)))


def filtered_difference(t: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """``(theta_k - theta_k-1) / dt`` low-passed by ``v_k = a v_k-1 + (1 - a) d_k``, ``a = exp(-FFD_RATE dt)``."""
    h = float(t[1] - t[0])
    d = np.vstack([np.zeros((1, angles.shape[1])), np.diff(angles, axis=0) / h])
    a = np.exp(-FFD_RATE * h)
    v = np.zeros_like(d)
    for k in range(1, len(d)):
        v[k] = a * v[k - 1] + (1 - a) * d[k]
    return v


def train(case: str, out: Path, measurement_std: float, *, epochs: Optional[int], runs: Optional[int],
          horizon: Optional[float]) -> Path:
    """``kklcasadi train --plant ...:FACTORY --dt 0.004 --measurement-std S --out OUT/case`` in Python."""
    from kklcasadi.train import default_config, train_observer, with_field

    plant = CASES[case][1]()
    config = with_field(default_config(plant.name, "bank"), "measurement_std", measurement_std)
    for name, value in (("n_traj", runs), ("T", horizon)):      # a smaller budget than the recipe's, when asked
        if value is not None:
            config = with_field(config, name, value)
    if runs is not None and runs < 100:                          # batches a tiny budget's few samples can fill
        decoder = config.decoder
        config = replace(config, decoder=replace(decoder, loop=replace(decoder.loop, batch_size=64)))
    return train_observer(plant, "bank", out / case, config=config, dt=DT, epochs=epochs, overwrite=True,
                          threads=1)


def score(case: str, model: Path) -> tuple[dict, dict]:
    """Every run's errors for ``t >= SETTLE``: ``{run: {estimator: [theta, alpha, theta_dot, alpha_dot]}}``,
    and the traces of the first scored run for the plot."""
    label, factory, y_cols = CASES[case]
    plant = factory()
    obs = kc.load_observer(model, system=plant)
    ekf = kc.EKF(plant, DT, Q=np.diag([0.0, 0.0, 1e-3, 1e-3]), R=1e-6 * np.eye(plant.ny))
    table, traces = {}, {}
    for k in FIT_RUNS + SCORED_RUNS:
        # the reference: the measured angles (both, whatever y is) and their zero-phase derivative
        both = read_angles(k)
        result = estimate_log(obs, run_path(k), y_cols=y_cols, ekf=ekf)
        reference = np.column_stack([both.y, savgol_derivative(both.t, both.y)])
        keep = both.t - both.t[0] >= SETTLE
        # the filtered difference gives the angles it measures and their velocities, nothing else
        ffd = np.column_stack([both.y, filtered_difference(both.t, both.y)])
        for i in (0, 1):
            if STATES[i] not in y_cols:
                ffd[:, [i, i + 2]] = np.nan
        table[k] = {name: [rmse(reference[keep, i:i + 1], x[keep, i:i + 1], angles=(0,) if i < 2 else ())
                           for i in range(4)]
                    for name, x in (("KKL (bank)", result.xhat), ("EKF", result.ekf), ("filtered difference", ffd))}
        if k == SCORED_RUNS[0]:
            traces = {"t": both.t - both.t[0], "reference": reference, "KKL (bank)": result.xhat, "EKF": result.ekf,
                      "filtered difference": ffd, "in_domain": result.in_domain, "run": k, "label": label}
    return table, traces


def markdown(case: str, table: dict) -> str:
    """Per run and the mean over the scored runs; ``-`` where an estimator cannot give a state."""
    head = ("| " + CASES[case][0] + " | run | " + " | ".join(f"{s} RMSE" for s in STATES) + " |\n"
            + "|---|---|" + "---|" * len(STATES) + "\n")
    rows = []
    for name in ("KKL (bank)", "EKF", "filtered difference"):
        for k in FIT_RUNS + SCORED_RUNS:
            values = " | ".join("-" if np.isnan(v) else f"{v:.3f}" for v in table[k][name])
            rows.append(f"| {name} | {k}{' (fit)' if k in FIT_RUNS else ''} | {values} |")
        mean = np.mean([table[k][name] for k in SCORED_RUNS], axis=0)
        rows.append(f"| **{name}** | **mean 5-11** | " + " | ".join("-" if np.isnan(v) else f"**{v:.3f}**"
                                                                      for v in mean) + " |")
    return head + "\n".join(rows)


def plot(traces: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(10, 9), sharex=True)
    t = traces["t"]
    for i, ax in enumerate(axes):
        ax.plot(t, traces["reference"][:, i], "k", lw=1.4, label="measured" if i < 2 else "zero-phase reference")
        for j, name in enumerate(("KKL (bank)", "EKF", "filtered difference")):
            if not np.all(np.isnan(traces[name][:, i])):
                ax.plot(t, traces[name][:, i], color=f"C{j}", lw=0.9, ls="--" if j else "-", label=name)
        ax.axvline(SETTLE, color="0.7", lw=0.8)
        ax.set_ylabel(STATES[i] + (" [rad]" if i < 2 else " [rad/s]"))
        ax.legend(fontsize=7, ncol=4, loc="upper right")
    axes[0].set_title(f"Qube Servo 2, free swing {traces['run']} (scored), {traces['label']}")
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(out: Path, *, epochs: Optional[int] = None, runs: Optional[int] = None, horizon: Optional[float] = None,
         cases: tuple[str, ...] = tuple(CASES)) -> dict:
    """Fit, train, estimate, score and plot every case; returns ``{case: (table, markdown)}``."""
    out.mkdir(parents=True, exist_ok=True)
    std = encoder_noise(FIT_RUNS)
    print(f"encoder noise from runs {FIT_RUNS}: std {std:.3g} rad (the --measurement-std of the training)")
    results = {}
    for case in cases:
        t0 = time.perf_counter()
        model = train(case, out, std, epochs=epochs, runs=runs, horizon=horizon)
        print(f"{CASES[case][0]}: trained {model} in {time.perf_counter() - t0:.0f} s")
        table, traces = score(case, model)
        text = markdown(case, table)
        print(text)
        print(f"plot {plot(traces, out / f'qube_{case}.png')}")
        results[case] = (table, text)
    return results


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("models/qube"))
    parser.add_argument("--epochs", type=int, help="decoder epochs (default: the recipe's)")
    parser.add_argument("--runs", type=int, help="training runs of the bank (default: the recipe's)")
    parser.add_argument("--horizon", type=float, help="seconds per training run (default: the recipe's)")
    parser.add_argument("--cases", nargs="+", choices=tuple(CASES), default=list(CASES))
    args = parser.parse_args()
    main(args.out, epochs=args.epochs, runs=args.runs, horizon=args.horizon, cases=tuple(args.cases))
