"""The Qube model and an EKF against the six logged free swings of ``data/``.

1. Model check: each run is read onto the 4 ms grid (``kklcasadi.plant.logs.read_log``, angles
   unwrapped), the velocities of its first sample are the Savitzky-Golay derivative of the angles
   (window 15, cubic), and the model is simulated from that state with ``u = 0`` (CVODES). Printed:
   how long the simulated angles stay within 0.05, 0.1 and 0.5 rad of the logged ones, the RMSE
   of the angles over the first 1 s and 2 s, and the ratio of the model's to the log's mean swing
   period over the first 4 s (upward crossings of ``alpha = pi``).
2. EKF: ``kklcasadi.ekf.EKF`` with ``R = 1e-6 I`` and process noise variance ``1e-3`` per step on
   the two velocities (``Q = diag(0, 0, 1e-3, 1e-3)``; ``Q`` is the covariance added at every
   prediction), started at the box centre with the box's variance, for ``y = (theta, alpha)`` and
   ``y = alpha``. Printed: the RMSE of the velocity estimates for ``t >= 2 s`` against the
   Savitzky-Golay reference (both velocities together, then each).

Nothing is fitted: the model's parameters are the data authors' and the filter's settings are fixed
beforehand, so every run is out of sample. Run: ``python examples/qube/check_logs.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import kklcasadi as kc
from kklcasadi.metrics import rmse, wrap_angle
from kklcasadi.plant import logs

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from qube_plant import make_plant, make_plant_alpha  # noqa: E402

DT = 0.004
RUNS = sorted((HERE / "data").glob("free_swing_*.csv"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
THRESHOLDS = (0.05, 0.1, 0.5)


def swing_periods(alpha: np.ndarray, n: int) -> np.ndarray:
    """Times between upward crossings of ``alpha = pi`` (hanging) in the first ``n`` samples."""
    a = alpha[:n] - np.pi
    return np.diff(np.nonzero((a[:-1] < 0) & (a[1:] >= 0))[0]) * DT


def load(path: Path, plant: kc.System) -> tuple[logs.Log, np.ndarray]:
    """A run on the grid, and its Savitzky-Golay velocity reference (N, 2)."""
    box = {"theta": tuple(plant.x0_box[0]), "alpha": tuple(plant.x0_box[1])}
    log = logs.read_log(path, time_col="time", y_cols=("theta", "alpha"), angle_cols=("theta", "alpha"), dt=DT,
                          box=box)
    return log, logs.savgol_derivative(log.t, log.y)


def tracking(plant: kc.System) -> None:
    print("model vs log, free swing from the first logged state (u = 0)")
    print(f"{'run':<17} {'T [s]':>5} " + " ".join(f"{'t(' + str(e) + ')':>8}" for e in THRESHOLDS)
          + f" {'rmse 1s':>8} {'rmse 2s':>8} {'period':>7}")
    for path in RUNS:
        log, velocity = load(path, plant)
        x0 = np.concatenate([log.y[0], velocity[0]])
        n = log.t.size
        sim = kc.simulate(plant, x0, np.zeros((n, 1)), T=n * DT, dt=DT)
        error = np.abs(wrap_angle(sim.x[:, :2] - log.y)).max(axis=1)
        elapsed = log.t - log.t[0]
        times = []
        for threshold in THRESHOLDS:
            over = np.nonzero(error > threshold)[0]
            times.append(elapsed[over[0]] if over.size else elapsed[-1])
        rms = [rmse(log.y[elapsed < s], sim.x[elapsed < s, :2], angles=(0, 1)) for s in (1.0, 2.0)]
        periods = [swing_periods(a, int(round(4.0 / DT))) for a in (sim.x[:, 1], log.y[:, 1])]
        k = min(p.size for p in periods)
        ratio = periods[0][:k].mean() / periods[1][:k].mean()
        print(f"{path.name:<17} {elapsed[-1]:5.2f} " + " ".join(f"{v:8.3f}" for v in times)
              + f" {rms[0]:8.4f} {rms[1]:8.4f} {ratio:7.3f}")


def ekf(plant: kc.System, outputs: list[int], label: str) -> None:
    print(f"EKF, y = {label}: velocity RMSE [rad/s] for t >= 2 s against the Savitzky-Golay reference")
    filt = kc.EKF(plant, DT, Q=np.diag([0.0, 0.0, 1e-3, 1e-3]), R=1e-6 * np.eye(plant.ny))
    scores = []
    for path in RUNS:
        log, velocity = load(path, plant)
        est = filt.simulate(log.t, log.y[:, outputs], np.zeros((log.t.size, 1)))
        keep = log.t - log.t[0] >= 2.0
        both = rmse(velocity[keep], est.xhat[keep, 2:])
        each = [rmse(velocity[keep, i:i + 1], est.xhat[keep, 2 + i:3 + i]) for i in range(2)]
        scores.append(both)
        print(f"  {path.name:<17} both {both:.4f}   theta_dot {each[0]:.4f}   alpha_dot {each[1]:.4f}")
    print(f"  mean over the runs: {np.mean(scores):.4f}")


def main() -> None:
    plant = make_plant()
    tracking(plant)
    ekf(plant, [0, 1], "(theta, alpha)")
    ekf(make_plant_alpha(), [1], "alpha")


if __name__ == "__main__":
    main()
