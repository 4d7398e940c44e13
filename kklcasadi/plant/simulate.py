"""Simulation of plants with CasADi integrators: zero-order-hold inputs, seeded noise, many trials.

One sample interval is a :func:`casadi.integrator` (CVODES by default, the docs/protocol.md reference;
fixed-step ``"rk"`` for speed). A trajectory is that step folded with ``mapaccum``, and many trials
are the folded trajectory mapped over ``"thread"`` workers: no Python loop per step or per trial.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any, Callable, Sequence, Union

import casadi as ca
import numpy as np

from ..validation import (
    Text,
    error,
    finite_array,
    finite_number,
    nonnegative_number,
    one_of,
    positive_int,
    positive_number,
)
from .rk4 import rk4_step
from .systems import System

__all__ = ["Trajectory", "TrajectoryBatch", "simulate", "simulate_batch", "time_grid", "input_samples",
           "step_function", "INTEGRATORS"]

log = logging.getLogger(__name__)

#: Plant integrators accepted by ``method``.
INTEGRATORS = ("cvodes", "rk")

InputLike = Union[Callable[[np.ndarray], np.ndarray], np.ndarray, Sequence[float]]


@dataclass(frozen=True, eq=False)
class Trajectory:
    """One simulated run, sampled at ``t_k = k dt``.

    Attributes
    ----------
    t : numpy.ndarray, shape (N,)
    x : numpy.ndarray, shape (N, nx)
        True states.
    u : numpy.ndarray, shape (N, nu)
        Inputs, held over ``[t_k, t_k+1)``.
    y : numpy.ndarray, shape (N, ny)
        Measurements ``h(x_k)`` plus measurement noise.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    y: np.ndarray


@dataclass(frozen=True, eq=False)
class TrajectoryBatch:
    """Many runs on one time grid: ``x`` (M, N, nx), ``u`` (M, N, nu), ``y`` (M, N, ny).

    ``ok[i]`` is False for a run that failed in the integrator or left the finite range
    (``|x| > blowup``); its arrays hold NaN from the failure on. Index it to get a :class:`Trajectory`.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    y: np.ndarray
    ok: np.ndarray

    def __len__(self) -> int:
        return self.x.shape[0]

    def __getitem__(self, i: int) -> Trajectory:
        return Trajectory(self.t, self.x[i], self.u[i], self.y[i])


def time_grid(T: float, dt: float) -> np.ndarray:
    """Sample times ``t_k = k dt``, ``k = 0..N-1`` with ``N = round(T / dt)`` (docs/protocol.md)."""
    dt = positive_number(dt, "dt")
    T = finite_number(T, "T")
    if T < 2 * dt:
        raise error("T", f"at least 2 dt = {2 * dt}", T)
    n = int(round(T / dt))
    if abs(n * dt - T) > 1e-9 * max(1.0, T):
        raise error("T", f"a whole number of sample periods dt = {dt}", T)
    return np.arange(n) * dt


def input_samples(u: InputLike, t: np.ndarray, nu: int, arg: str = "u") -> np.ndarray:
    """Evaluate an input (a signal ``u(t)`` or an array of samples) on the grid ``t``.

    Returns
    -------
    numpy.ndarray, shape (N, nu)
        ``u_k = u(t_k)``; a clear ValueError names the first non-finite sample.
    """
    if callable(u):
        values = np.asarray(u(t), dtype=float)
    else:
        values = np.asarray(u, dtype=float)
    if values.ndim == 1 and nu == 1:
        values = values[:, None]
    if values.shape != (t.size, nu):
        raise error(arg, f"samples of shape (N, nu) = ({t.size}, {nu})", Text(f"shape {values.shape}"))
    bad = ~np.isfinite(values)
    if bad.any():
        k = int(np.argwhere(bad)[0, 0])
        raise error(arg, "finite samples", Text(f"{values[k].tolist()} at sample {k} (t = {t[k]:.6g})"))
    return values


def step_function(system: System, dt: float, method: str = "cvodes", *, rtol: float = 1e-8, atol: float = 1e-10,
                  substeps: int = 4) -> ca.Function:
    """One sample interval of the plant: ``step(x, p) -> x_next`` with ``p = [u; w]``.

    ``u`` (nu,) is held over the interval and ``w`` (nx,) is process noise added to ``xdot``.

    Parameters
    ----------
    method : {"cvodes", "rk"}
        ``"cvodes"``: adaptive BDF with tolerances ``rtol``/``atol`` (docs/protocol.md: 1e-8 / 1e-10).
        ``"rk"``: RK4 (:func:`kklcasadi.plant.rk4.rk4_step`, SX) with ``substeps`` fixed steps per interval.
    """
    one_of(method, "method", INTEGRATORS)
    substeps = positive_int(substeps, "substeps")
    x = ca.SX.sym("x", system.nx)
    p = ca.SX.sym("p", system.nu + system.nx)
    ode = system.f(x, p[:system.nu]) + p[system.nu:]
    if method == "rk":
        x_next = rk4_step(lambda _s, xx: system.f(xx, p[:system.nu]) + p[system.nu:], x, float(dt), substeps)
        return ca.Function("step", [x, p], [x_next], ["x", "p"], ["x_next"])
    opts = {"abstol": float(atol), "reltol": float(rtol), "max_num_steps": 100000, "disable_internal_warnings": True,
            "show_eval_warnings": False}
    integ = ca.integrator(f"{system.name}_plant", "cvodes", {"x": x, "p": p, "ode": ode}, 0.0, float(dt), opts)
    xs = ca.MX.sym("x", system.nx)
    ps = ca.MX.sym("p", system.nu + system.nx)
    return ca.Function("step", [xs, ps], [integ(x0=xs, p=ps)["xf"]], ["x", "p"], ["x_next"])


def _seeds(seed: int | Sequence[int] | None, m: int) -> list[Any]:
    if seed is None or isinstance(seed, (int, np.integer)):
        return list(np.random.SeedSequence(seed).spawn(m)) if m > 1 else [seed]
    seeds = list(seed)
    if len(seeds) != m:
        raise error("seed", f"an int or one seed per trial ({m})", Text(f"{len(seeds)} seeds"))
    return seeds


def _process_std(value: Any, nx: int) -> float | np.ndarray:
    """A scalar process-noise std, or one per state (nx,), validated (all finite and >= 0)."""
    if np.ndim(value) == 0:
        return nonnegative_number(value, "process_std")
    std = finite_array(value, "process_std")
    if std.shape != (nx,) or np.any(std < 0):
        raise error("process_std", f"a number >= 0 or nx = {nx} of them (one per state)", std.tolist())
    return std


def simulate_batch(system: System, x0: Any, u: InputLike | Sequence[InputLike], T: float = 50.0, dt: float = 0.05,
                   *, process_std: float | Sequence[float] = 0.0, measurement_std: float = 0.0,
                   seed: int | Sequence[int] | None = None, method: str = "cvodes", rtol: float = 1e-8,
                   atol: float = 1e-10, substeps: int = 4, blowup: float = 1e6,
                   n_threads: int | None = None) -> TrajectoryBatch:
    """Simulate M trials at once (one CasADi call, mapped over threads).

    Parameters
    ----------
    system : System
    x0 : array_like, shape (M, nx)
        Initial states.
    u : signal, array (N, nu), or a sequence of M of them
        Input of each trial (one shared input if a single signal/array is given).
    T, dt : float
        Horizon and sample period; ``N = round(T / dt)`` samples at ``t_k = k dt``.
    process_std : float or array_like, shape (nx,)
        Standard deviation of the process noise added to ``xdot`` (drawn per interval and held on
        it): one for every state, or one per state (e.g. zero on the kinematic rows of a
        mechanical plant, so that noise acts as a force).
    measurement_std : float
        Standard deviation of the measurement noise (added to ``y_k``).
    seed : int or sequence of M ints, optional
        Trial ``i`` draws its noise from ``default_rng(seed[i])``; an int is spawned into M streams
        (``SeedSequence``). With one trial an int seed is used directly, as in :func:`simulate`.
    method, rtol, atol, substeps
        See :func:`step_function`.
    blowup : float
        A trial whose state exceeds this magnitude is marked failed (``ok`` False).
    n_threads : int, optional
        Worker threads for the trial map (default: the CPU count).
    """
    if not isinstance(system, System):
        raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
    t = time_grid(T, dt)
    n = t.size
    x0 = np.asarray(x0, dtype=float)
    if x0.ndim != 2 or x0.shape[1] != system.nx or x0.shape[0] == 0:
        raise error("x0", f"shape (M, nx) = (M, {system.nx}) for system {system.name!r}", Text(f"shape {x0.shape}"))
    finite_array(x0, "x0")
    m = x0.shape[0]
    single = callable(u) or (not isinstance(u, (list, tuple)))
    inputs = [u] * m if single else list(u)
    if len(inputs) != m:
        raise error("u", f"one input or a sequence of M = {m} inputs", Text(f"{len(inputs)} inputs"))
    us = np.stack([input_samples(ui, t, system.nu, f"u[{i}]") for i, ui in enumerate(inputs)])
    process_std = _process_std(process_std, system.nx)
    measurement_std = nonnegative_number(measurement_std, "measurement_std")
    rngs = [np.random.default_rng(s) for s in _seeds(seed, m)]
    w = np.stack([rng.normal(0.0, 1.0, (n - 1, system.nx)) for rng in rngs]) * process_std
    v = np.stack([rng.normal(0.0, 1.0, (n, system.ny)) for rng in rngs]) * measurement_std

    step = step_function(system, dt, method, rtol=rtol, atol=atol, substeps=substeps)
    traj = step.mapaccum("trajectory", n - 1)
    params = np.concatenate([us[:, :-1, :], w], axis=2)          # (M, N-1, nu+nx)
    x = np.full((m, n, system.nx), np.nan)
    x[:, 0] = x0
    ok = np.ones(m, dtype=bool)
    threads = n_threads or os.cpu_count() or 1
    try:
        batch = traj.map(m, "thread", min(threads, m))
        xs = np.asarray(batch(x0.T, params.reshape(m * (n - 1), -1).T))
        x[:, 1:] = xs.T.reshape(m, n - 1, system.nx)
    except RuntimeError as err:
        log.info("batched simulation failed (%s); retrying trial by trial to isolate the failures", err)
        for i in range(m):
            try:
                x[i, 1:] = np.asarray(traj(x0[i], params[i].T)).T
            except RuntimeError as trial_err:
                log.info("trial %d failed in the integrator: %s", i, trial_err)
                ok[i] = False
    with np.errstate(invalid="ignore"):
        x[~(np.abs(x) < blowup)] = np.nan                       # inf, NaN and blow-ups become NaN
    ok &= ~np.isnan(x).any(axis=(1, 2))
    y = system.h_batch(x.reshape(m * n, system.nx)).reshape(m, n, system.ny) + v
    for arr in (x, us, y):
        arr.setflags(write=False)
    return TrajectoryBatch(t, x, us, y, ok)


def simulate(system: System, x0: Any, u: InputLike, T: float = 50.0, dt: float = 0.05, *, process_std: float = 0.0,
             measurement_std: float = 0.0, seed: int | None = None, method: str = "cvodes", rtol: float = 1e-8,
             atol: float = 1e-10, substeps: int = 4) -> Trajectory:
    """Simulate one trial with a CasADi integrator (see :func:`simulate_batch` for the parameters).

    Parameters
    ----------
    x0 : array_like, shape (nx,)
    u : signal ``u(t) -> (nu,)`` or array, shape (N, nu)

    Returns
    -------
    Trajectory
        ``t`` (N,), ``x`` (N, nx), ``u`` (N, nu), ``y`` (N, ny).

    Raises
    ------
    RuntimeError
        If the integrator fails or the state blows up.
    """
    x0 = system.check_state(x0, "x0")
    batch = simulate_batch(system, x0[None, :], u, T, dt, process_std=process_std, measurement_std=measurement_std,
                           seed=[seed], method=method, rtol=rtol, atol=atol, substeps=substeps, n_threads=1)
    if not batch.ok[0]:
        raise RuntimeError(f"simulation of {system.name!r} from x0 = {x0.tolist()} failed or blew up; "
                           "shorten T, reduce the input, or use method='cvodes'")
    return batch[0]
