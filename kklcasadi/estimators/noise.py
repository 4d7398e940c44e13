"""The rig's noise from its logs: the measurement std from the outputs' high-frequency residual, and the
process noise per state by maximising the likelihood of the log's innovations under the plant's EKF.

A model is never exact, and a rig's logs say by how much: a filter that trusts the model too much
(too little process noise) lags the rig, one that trusts it too little passes the measurement noise
on. Both levels are read from the logs:

- :func:`residual_std`: each output's noise std from the residual of a local polynomial fit (degree
  ``order`` over ``window`` neighbouring samples, at the logged times) at the log's own rate. For
  white noise of std ``s`` the residual at a sample has variance ``s^2 (1 - h)``, ``h`` the fit's
  leverage there, and the estimate divides it out; a smooth signal leaves a residual of the order of
  its ``order + 1``-th derivative times the window's span to that power, negligible where the log
  samples the motion finely (a 1 kHz encoder, a 250 Hz pendulum).
- :func:`process_noise`: with ``R`` fixed to that measurement std, the process-noise std ``q_i`` of
  each chosen state (``Q = diag(q dt)^2`` per sample, the convention of :meth:`kklcasadi.EKF.for_noise`)
  that maximise the Gaussian likelihood of the EKF's innovations ``e_k = y_k - h(x_k|k-1)``,
  ``S_k = H P_k|k-1 H^T + R``: minimise ``sum_k (log det S_k + e_k^T S_k^-1 e_k) / 2`` over the
  samples after ``settle`` seconds of every log. One CasADi ``mapaccum`` per log gives the sum and its
  exact gradient in ``log q``; L-BFGS-B, started from the best common factor on a grid, finds the
  minimum. The unmodelled effects (friction the model lacks, an energy loss, a flexible mode) show
  as process noise on the states they act on.

Both take logs already on the model's grid (:class:`kklcasadi.plant.logs.Log`, or any object with
``t``, ``y``, ``u``; a simulated :class:`kklcasadi.Trajectory` is one); :func:`measurement_std` the raw
samples.
"""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import casadi as ca
import numpy as np
import scipy.optimize

from ..plant.envelope import Envelope, output_ranges
from ..plant.logs import read_log
from ..plant.systems import System
from ..validation import Text, error, index_tuple, nonnegative_number, positive_int, positive_number
from .ekf import EKF, NOISE_FLOOR

__all__ = ["residual_std", "process_noise", "forced_states", "rig_envelope", "ProcessNoise", "GRID"]

#: Common factors of the state scales (half-width of the X0 box times the plant's time scale) tried
#: before the per-state search starts from the best.
GRID = tuple(10.0 ** k for k in range(-6, 3))


def residual_std(t: Any, y: Any, *, window: int = 11, order: int = 3) -> np.ndarray:
    """Each column's noise std from its residual about a local polynomial fit at the logged times.

    Parameters
    ----------
    t : array_like, shape (N,)
        Sample times, strictly increasing (any spacing: the raw log, jitter included).
    y : array_like, shape (N,) or (N, ny)
        The logged outputs (angles unwrapped).
    window : int
        Odd number of samples of each fit, ``order + 2 <= window <= N``.
    order : int
        Degree of the local polynomial (>= 0).

    Returns
    -------
    numpy.ndarray, shape (ny,)
        ``sqrt(mean(r_k^2 / (1 - h_k)))`` per column: ``r_k`` the residual of the fit centred on sample
        ``k`` (the first and last ``window // 2`` samples use the first and last full window), ``h_k``
        its leverage.
    """
    t = np.asarray(t, dtype=float)
    values = np.asarray(y, dtype=float)
    values = values[:, None] if values.ndim == 1 else values
    if t.ndim != 1 or values.ndim != 2 or values.shape[0] != t.size:
        raise error("y", f"shape (N,) or (N, ny) with N = {t.size} (one row per time)", Text(f"shape {values.shape}"))
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(values))):
        raise error("t, y", "finite values", Text("NaN or inf"))
    if np.any(np.diff(t) <= 0):
        raise error("t", "strictly increasing times", Text(f"a step of {np.diff(t).min():.6g}"))
    window, order = positive_int(window, "window"), int(order)
    if order < 0 or window % 2 == 0 or window < order + 2 or window > t.size:
        raise error("window", f"an odd number of samples >= order + 2 = {order + 2} and <= N = {t.size}", window)
    half = window // 2
    centre = np.clip(np.arange(t.size), half, t.size - 1 - half)
    rows = centre[:, None] + np.arange(-half, half + 1)                    # (N, window)
    local = t[rows] - t[centre][:, None]
    scale = np.maximum(np.abs(local).max(axis=1, keepdims=True), 1e-300)
    basis = (local / scale)[..., None] ** np.arange(order + 1)            # (N, window, p)
    pinv = np.linalg.pinv(basis)                                          # (N, p, window)
    at = np.arange(t.size) - (centre - half)                               # each sample's place in its window
    lever = np.einsum("np,npw->nw", basis[np.arange(t.size), at], pinv)    # the fit's weights at the sample
    fitted = np.einsum("nw,nwc->nc", lever, values[rows])
    h = lever[np.arange(t.size), at]
    residual = values - fitted
    return np.sqrt(np.mean(residual ** 2 / (1.0 - h)[:, None], axis=0))


def forced_states(system: System) -> tuple[int, ...]:
    """The states whose derivative is not simply another state (not a row ``x_i' = x_j``): where a force,
    and so the process noise of a mechanical plant, acts."""
    return tuple(i for i in range(system.nx) if not system.xdot_expr[i].is_symbolic())


@dataclass(frozen=True)
class ProcessNoise:
    """The result of :func:`process_noise`.

    Attributes
    ----------
    process_std : numpy.ndarray, shape (nx,)
        The std on each ``xdot_i`` (0 on the states not estimated).
    measurement_std : numpy.ndarray, shape (ny,)
        The ``R`` the likelihood was maximised under (given).
    states : tuple of int
        The states whose process std was estimated.
    nll : float
        The minimised negative log-likelihood per scored sample (constants left out).
    samples : int
        Innovations scored (after ``settle`` in every log).
    at_bound : tuple of int
        Estimated states whose std ended at a bound of the search (the likelihood does not pin them).
    """

    process_std: np.ndarray
    measurement_std: np.ndarray
    states: tuple
    nll: float
    samples: int
    at_bound: tuple

    def record(self) -> dict:
        """A JSON-able record for a model card."""
        return {"process_std": self.process_std.tolist(), "measurement_std": self.measurement_std.tolist(),
                "states": list(self.states), "nll_per_sample": self.nll, "samples": self.samples,
                "at_bound": list(self.at_bound),
                "method": "maximum likelihood of the EKF's innovations, R fixed, Q = diag(q dt)^2 (L-BFGS-B in log q)"}


def _likelihood(system: System, dt: float, r: np.ndarray, states: tuple,
                substeps: int | str) -> tuple[ca.Function, EKF]:
    """``(s, uyw, log_q) -> s_next``: one EKF step whose state ``s = [x; vec(P); nll]`` carries the weighted
    sum of the innovations' negative log-likelihood (``uyw = [u_k; y_k+1; weight]``), and the EKF (no
    process noise) it is built on."""
    nx, ny, nu = system.nx, system.ny, system.nu
    ekf = EKF(system, dt, Q=np.zeros((nx, nx)), R=np.diag(r ** 2), substeps=substeps)
    s, uyw, log_q = ca.SX.sym("s", nx + nx * nx + 1), ca.SX.sym("uyw", nu + ny + 1), ca.SX.sym("log_q", len(states))
    x, P = s[:nx], ca.reshape(s[nx:nx + nx * nx], nx, nx)
    u, y, w = uyw[:nu], uyw[nu:nu + ny], uyw[nu + ny]
    xp, Pp = ekf.predict(x, P, u)
    q = ca.SX.zeros(nx)
    for k, i in enumerate(states):
        q[i] = ca.exp(2.0 * log_q[k]) * dt ** 2
    Pp = Pp + ca.diag(q)
    H = system.h_jac(xp)
    S = ca.mtimes([H, Pp, H.T]) + ca.DM(np.diag(r ** 2))
    e = y - system.h(xp)
    nll = 0.5 * (ca.log(ca.det(S)) + ca.dot(e, ca.solve(S, e)))
    xu, Pu = ekf.update(xp, Pp, y)
    step = ca.Function("nll_step", [s, uyw, log_q], [ca.vertcat(xu, ca.vec(Pu), s[-1] + w * nll)])
    return step, ekf


def process_noise(system: System, logs: Sequence[Any], *, dt: float, measurement_std: Any,
                  states: Optional[Sequence[int]] = None, settle: float = 1.0, substeps: int | str = "auto",
                  bounds: tuple[float, float] = (1e-8, 1e4), shared: bool = False) -> ProcessNoise:
    """The process-noise std per state that maximises the likelihood of the logs' EKF innovations.

    Parameters
    ----------
    system : System
    logs : sequence of Log (or objects with ``t`` (N,), ``y`` (N, ny), ``u`` (N, nu) or (N, 0))
        Logs on the grid of spacing ``dt``; a log without inputs (``u`` (N, 0)) ran at ``u = 0``.
    dt : float
        The model's sample time (the EKF's).
    measurement_std : float or array_like (ny,)
        The measurement noise std (:func:`residual_std`), fixed.
    states : sequence of int, optional
        The states whose std is estimated; default :func:`forced_states` (the others get 0).
    settle : float
        Seconds at the start of each log whose innovations are left out (the prior's transient).
    substeps : int or "auto"
        RK4 steps per sample of the EKF's prediction (as :class:`kklcasadi.EKF`'s).
    bounds : (float, float)
        The search's bounds on ``q_i`` in units of state ``i``'s scale (the half-width of its X0 box row
        times the plant's time scale, :func:`kklcasadi.plant.design.time_scales`).
    shared : bool
        One std for all the estimated states (a log that measures few states cannot tell the ones it does
        not measure apart) instead of one each.

    Returns
    -------
    ProcessNoise
    """
    from ..plant.design import time_scales

    if not isinstance(system, System):
        raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
    dt = positive_number(dt, "dt")
    settle = nonnegative_number(settle, "settle")
    r = np.broadcast_to(np.asarray(measurement_std, dtype=float), (system.ny,)).copy()
    if not (np.all(np.isfinite(r)) and np.all(r >= 0)):
        raise error("measurement_std", f"a std >= 0 or ny = {system.ny} of them", r.tolist())
    r = np.maximum(r, NOISE_FLOOR)
    states = forced_states(system) if states is None else index_tuple(states, "states", system.nx)
    if not states:
        raise error("states", "at least one state to estimate the process noise of", Text("none"))
    lo, hi = bounds
    if not (0 < lo < hi and math.isfinite(hi)):
        raise error("bounds", "factors 0 < lo < hi", bounds)
    if isinstance(logs, (str, bytes)) or not isinstance(logs, Sequence) or not logs:
        raise error("logs", "a non-empty sequence of logs on the model's grid", Text(type(logs).__name__),
                    kind=TypeError)
    step, ekf = _likelihood(system, dt, r, states, substeps)
    runs, scored = [], 0
    for n, log in enumerate(logs):
        t, y = np.asarray(log.t, dtype=float), np.asarray(log.y, dtype=float)
        u = np.asarray(log.u, dtype=float)
        u = np.zeros((t.size, system.nu)) if u.ndim != 2 or u.shape[1] == 0 else u
        if y.shape != (t.size, system.ny) or u.shape != (t.size, system.nu) or t.size < 3:
            raise error(f"logs[{n}]", f"t (N >= 3,), y (N, {system.ny}), u (N, {system.nu}) or (N, 0)",
                        Text(f"t {t.shape}, y {y.shape}, u {u.shape}"))
        if not np.allclose(np.diff(t), dt, rtol=1e-6, atol=0.0):
            raise error(f"logs[{n}]", f"samples spaced by dt = {dt:g} s (a log on the model's grid)",
                        Text(f"spacings {np.diff(t).min():.6g} to {np.diff(t).max():.6g} s"))
        w = (t[1:] - t[0] >= settle).astype(float)
        scored += int(w.sum())
        x0, P0 = ekf.update(ekf.x0, ekf.P0, y[0])
        s0 = ca.vertcat(x0, ca.vec(P0), 0.0)
        run = step.mapaccum(f"nll_run_{n}", t.size - 1)
        uyw = np.column_stack([u[:-1], y[1:], w]).T
        runs.append((run, s0, uyw))
    if scored == 0:
        raise error("settle", "less than the logs' length (no innovation is left to score)", settle)
    log_q = ca.MX.sym("log_q", 1 if shared else len(states))
    each = ca.repmat(log_q, len(states), 1) if shared else log_q
    total = sum(run(s0, uyw, ca.repmat(each, 1, uyw.shape[1]))[-1, -1] for run, s0, uyw in runs) / scored
    fun = ca.Function("nll", [log_q], [total, ca.gradient(total, log_q)])
    scale = np.array([0.5 * (system.x0_box[i, 1] - system.x0_box[i, 0]) for i in states]) * time_scales(system)[0]
    if shared:
        scale = np.array([np.exp(np.mean(np.log(scale)))])

    def objective(v: np.ndarray) -> tuple[float, np.ndarray]:
        value, grad = fun(v)
        value = float(value)
        return (value, np.asarray(grad, dtype=float).ravel()) if math.isfinite(value) else (1e300, np.zeros(v.size))

    grid = [(objective(np.log(scale * c))[0], c) for c in GRID]
    start = np.log(scale * min(grid)[1])
    limits = [(math.log(s * lo), math.log(s * hi)) for s in scale]
    best = scipy.optimize.minimize(objective, start, jac=True, method="L-BFGS-B", bounds=limits)
    std = np.zeros(system.nx)
    std[list(states)] = np.exp(best.x)
    edge = tuple(i for i, v, (a, b) in zip(states, np.broadcast_to(best.x, len(states)),
                                            limits * len(states) if shared else limits) if min(v - a, b - v) < 1e-6)
    return ProcessNoise(std, r, tuple(states), float(best.fun), scored, edge)


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def rig_envelope(system: System, paths: Sequence[str | os.PathLike], *, dt: float, time_col: str,
                 y_cols: Sequence[str], u_cols: Sequence[str] = (), angle_cols: Optional[Sequence[str]] = None,
                 settle: float = 1.0, measurement_std: Optional[float] = None,
                 process_std: Optional[float | Sequence[float]] = None, shared: bool = False) -> Envelope:
    """The envelope of ``system``'s training runs read from the rig's logs (``kklcasadi train --like``).

    Each log is put on the model's grid (:func:`kklcasadi.plant.logs.read_log`: outputs sampled, inputs
    averaged over each interval of a faster log, angle columns unwrapped and moved onto the branch of
    the outputs' range over the X0 box). The measurement std is each output's high-frequency residual
    (:func:`residual_std`) on the log at its own rate, the root mean square over the logs, the
    largest over the outputs (floored at :data:`kklcasadi.estimators.ekf.NOISE_FLOOR`); the process
    std per forced state maximises the likelihood of the EKF's innovations over all logs
    (:func:`process_noise`); the states along the logs are that EKF's estimates.

    Parameters
    ----------
    system : System
    paths : sequence of path
        CSV logs of the rig (one or more).
    dt : float
        The model's sample time.
    time_col, y_cols, u_cols, angle_cols
        As :func:`kklcasadi.plant.logs.read_log` (``angle_cols`` default: the ``y_cols`` of the plant's
        angle outputs); without ``u_cols`` the rig ran at ``u = 0``.
    settle : float
        Seconds at the start of each log left out of the likelihood, and where no training run starts (the
        EKF's transient).
    measurement_std, process_std : optional
        Given levels win over the estimates (a process std: one for the forced states, or one per state).
    shared : bool
        Estimate one process std for all the forced states (:func:`process_noise`).

    Returns
    -------
    Envelope
    """
    if isinstance(paths, (str, bytes, os.PathLike)) or not isinstance(paths, Sequence) or not paths:
        raise error("paths", "a non-empty sequence of CSV logs", Text(type(paths).__name__), kind=TypeError)
    y_cols, u_cols = tuple(y_cols), tuple(u_cols)
    if len(y_cols) != system.ny:
        raise error("y_cols", f"{system.ny} columns (the outputs of {system.name!r}, in order)", list(y_cols))
    if u_cols and len(u_cols) != system.nu:
        raise error("u_cols", f"{system.nu} columns (the inputs of {system.name!r}, in order) or none (u = 0)",
                    list(u_cols))
    angles = tuple([y_cols[j] for j in system.angle_outputs] if angle_cols is None else angle_cols)
    ranges = output_ranges(system)
    box = {name: tuple(ranges[j]) for j, name in enumerate(y_cols) if ranges[j, 1] > ranges[j, 0]}
    logs, residual, sources = [], [], []
    for path in map(Path, paths):
        log = read_log(path, time_col=time_col, y_cols=y_cols, u_cols=u_cols, dt=dt, angle_cols=angles, box=box)
        raw = read_log(path, time_col=time_col, y_cols=y_cols, dt=log.resampling.dt_mean, angle_cols=angles, box=box)
        logs.append(log)
        residual.append(residual_std(raw.t, raw.y))
        sources.append({"path": str(path), "sha256": _sha256(path), "rows": log.resampling.n_raw,
                        "columns": {"time": time_col, "y": list(y_cols), "u": list(u_cols)},
                        "t": [float(log.t[0]), float(log.t[-1])], "logged_dt_mean": log.resampling.dt_mean})
    per_output = np.sqrt(np.mean(np.square(residual), axis=0))
    noise: dict = {"measurement_std_per_output": per_output.tolist(),
                   "measurement_method": "residual of a local cubic over 11 samples at the log's own rate, "
                                         "leverage divided out; RMS over the logs, largest output"}
    if measurement_std is None:
        r = max(float(per_output.max()), NOISE_FLOOR)
        noise["measurement_std_from"] = "logs"
    else:
        r = nonnegative_number(measurement_std, "measurement_std")
        noise["measurement_std_from"] = "given"
    if process_std is None:
        fit = process_noise(system, logs, dt=dt, measurement_std=r, settle=settle, shared=shared)
        q = fit.process_std
        noise.update(process=fit.record(), process_std_from="logs")
    else:
        q = np.asarray(process_std, dtype=float)
        if q.ndim == 0:
            q = np.where(np.isin(np.arange(system.nx), forced_states(system)), float(q), 0.0)
        noise["process_std_from"] = "given"
    ekf = EKF.for_noise(system, dt, process_std=q, measurement_std=r)
    states = tuple(ekf.simulate(log.t, log.y, log.u if log.u.shape[1] else np.zeros((log.t.size, system.nu))).xhat
                   for log in logs)
    y_all = np.vstack([log.y for log in logs])
    u_range = None
    if u_cols:
        u_all = np.vstack([log.u for log in logs])
        u_range = np.column_stack([u_all.min(axis=0), u_all.max(axis=0)])
    return Envelope(dt, tuple(log.u for log in logs) if u_cols else (), states,
                    np.column_stack([y_all.min(axis=0), y_all.max(axis=0)]), u_range, r, q, tuple(sources), noise,
                    settle)
