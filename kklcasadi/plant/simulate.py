"""Simulation of plants with CasADi integrators: zero-order-hold inputs, seeded noise, many trials.

One sample interval is a :func:`casadi.integrator` (CVODES by default, the docs/protocol.md reference;
fixed-step ``"rk"`` for speed). A trajectory is that step folded with ``mapaccum``, and many trials
are the folded trajectory mapped over ``"thread"`` workers: no Python loop per step or per trial.

An output-feedback input (:class:`kklcasadi.plant.signals.OutputFeedback`) closes the loop inside
the folded step: ``y_k = h(x_k) + v_k``, ``u_k = law(c_k, y_k, r_k)``, then the plant interval with
``u_k`` held (:func:`closed_loop_step`).
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
    state_stds,
)
from .noise import NoiseModel
from .noise import noise_model as as_noise_model
from .rk4 import rk4_step
from .signals import OutputFeedback
from .systems import System

__all__ = ["Trajectory", "TrajectoryBatch", "simulate", "simulate_batch", "time_grid", "input_samples",
           "step_function", "closed_loop_step", "INTEGRATORS"]

log = logging.getLogger(__name__)

#: Plant integrators accepted by ``method``.
INTEGRATORS = ("cvodes", "rk")

InputLike = Union[Callable[[np.ndarray], np.ndarray], np.ndarray, Sequence[float], OutputFeedback]


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
                  substeps: int = 4, parametric: bool = False) -> ca.Function:
    """One sample interval of the plant: ``step(x, p) -> x_next`` with ``p = [u; w]``.

    ``u`` (nu,) is held over the interval and ``w`` (nx,) is process noise added to ``xdot``. With
    ``parametric`` (a plant with parameters), ``p = [u; w; theta]``: the plant's parameter values
    ``theta`` (n_params,) (:attr:`kklcasadi.System.f_param`); without, the nominal plant.

    Parameters
    ----------
    method : {"cvodes", "rk"}
        ``"cvodes"``: adaptive BDF with tolerances ``rtol``/``atol`` (docs/protocol.md: 1e-8 / 1e-10).
        ``"rk"``: RK4 (:func:`kklcasadi.plant.rk4.rk4_step`, SX) with ``substeps`` fixed steps per interval.
    """
    one_of(method, "method", INTEGRATORS)
    substeps = positive_int(substeps, "substeps")
    nx, nu = system.nx, system.nu
    n_theta = system.n_params if parametric else 0
    if parametric and not system.n_params:
        raise error("parametric", f"False for plant {system.name!r}, which declares no parameters", parametric)
    x = ca.SX.sym("x", nx)
    p = ca.SX.sym("p", nu + nx + n_theta)

    def field(xx: ca.SX) -> ca.SX:
        f = system.f_param(xx, p[:nu], p[nu + nx:]) if parametric else system.f(xx, p[:nu])
        return f + p[nu:nu + nx]

    ode = field(x)
    if method == "rk":
        x_next = rk4_step(lambda _s, xx: field(xx), x, float(dt), substeps)
        return ca.Function("step", [x, p], [x_next], ["x", "p"], ["x_next"])
    opts = {"abstol": float(atol), "reltol": float(rtol), "max_num_steps": 100000, "disable_internal_warnings": True,
            "show_eval_warnings": False}
    integ = ca.integrator(f"{system.name}_plant", "cvodes", {"x": x, "p": p, "ode": ode}, 0.0, float(dt), opts)
    xs = ca.MX.sym("x", nx)
    ps = ca.MX.sym("p", nu + nx + n_theta)
    return ca.Function("step", [xs, ps], [integ(x0=xs, p=ps)["xf"]], ["x", "p"], ["x_next"])


def closed_loop_step(system: System, law: OutputFeedback, dt: float, method: str = "cvodes", *, rtol: float = 1e-8,
                     atol: float = 1e-10, substeps: int = 4, parametric: bool = False,
                     noise: NoiseModel | str | None = None) -> ca.Function:
    """One sample interval of the plant under an output-feedback law.

    ``cl(s, p) -> (s_next, u)`` with ``s = [x; c]`` (plant state, law state) and
    ``p = [w; v; r; theta]``: process noise ``w`` (nx,) added to ``xdot`` over the interval,
    measurement noise ``v`` (ny,) of ``y_k = h(x_k) + v``, the reference ``r_k`` and the law's numbers
    ``theta``; ``u = law(c, y_k, r_k, theta)`` (nu,) is held over the interval. With ``parametric``,
    ``p`` ends with the plant's parameter values (see :func:`step_function`); a quantising ``noise``
    model (:mod:`kklcasadi.plant.noise`) rounds the measurement the law reads.

    Parameters
    ----------
    system : System
    law : OutputFeedback
        Its :meth:`~kklcasadi.plant.signals.OutputFeedback.function` (shared by every law of its class).
    dt, method, rtol, atol, substeps
        See :func:`step_function`.
    """
    _check_law(system, law, "u")
    plant = step_function(system, dt, method, rtol=rtol, atol=atol, substeps=substeps, parametric=parametric)
    f = law.function(dt)
    nx, nc, ny = system.nx, law.n_state, system.ny
    nr, nth, npl = f.size1_in(2), f.size1_in(3), system.n_params if parametric else 0
    s, p = ca.MX.sym("s", nx + nc), ca.MX.sym("p", nx + ny + nr + nth + npl)
    x, c = s[:nx], s[nx:]
    w, v, r, theta, plant_theta = ca.vertsplit(p, np.cumsum([0, nx, ny, nr, nth, npl]).tolist())
    y = system.h_param(x, plant_theta) if parametric else system.h(x)
    u, c_next = f(c, as_noise_model(noise).measure(y + v), r, theta)
    x_next = plant(x, ca.vertcat(u, w, plant_theta) if parametric else ca.vertcat(u, w))
    return ca.Function("closed_loop_step", [s, p], [ca.vertcat(x_next, c_next), u], ["s", "p"], ["s_next", "u"])


def _check_law(system: System, law: OutputFeedback, arg: str) -> None:
    if law.channels != system.nu or system.ny != system.nu:
        raise error(arg, f"an output-feedback law of one input per output for system {system.name!r} "
                    f"(nu = {system.nu}, ny = {system.ny})", Text(f"a law of {law.channels} channels"))


def _seeds(seed: int | Sequence[int] | None, m: int) -> list[Any]:
    if seed is None or isinstance(seed, (int, np.integer)):
        return list(np.random.SeedSequence(seed).spawn(m)) if m > 1 else [seed]
    seeds = list(seed)
    if len(seeds) != m:
        raise error("seed", f"an int or one seed per trial ({m})", Text(f"{len(seeds)} seeds"))
    return seeds


def simulate_batch(system: System, x0: Any, u: InputLike | Sequence[InputLike], T: float = 50.0, dt: float = 0.05,
                   *, process_std: float | Sequence[float] = 0.0, measurement_std: float = 0.0,
                   seed: int | Sequence[int] | None = None, method: str = "cvodes", rtol: float = 1e-8,
                   atol: float = 1e-10, substeps: int = 4, blowup: float = 1e6, n_threads: int | None = None,
                   params: object = None, noise_model: NoiseModel | str | None = None) -> TrajectoryBatch:
    """Simulate M trials at once (one CasADi call, mapped over threads).

    Parameters
    ----------
    system : System
    x0 : array_like, shape (M, nx)
        Initial states.
    u : signal, array (N, nu), output-feedback law, or a sequence of M of them
        Input of each trial (one shared input if a single one is given). An
        :class:`~kklcasadi.plant.signals.OutputFeedback` law (all trials' laws of one class) computes
        ``u_k`` from the measured ``y_k = h(x_k) + v_k`` (the noisy one the run records) and holds it
        over the interval; the batch's ``u`` holds the inputs it applied.
    T, dt : float
        Horizon and sample period; ``N = round(T / dt)`` samples at ``t_k = k dt``.
    process_std : float or array_like, shape (nx,)
        Standard deviation of the process noise added to ``xdot`` (drawn per interval and held on
        it): one for every state, or one per state (e.g. zero on the kinematic rows of a
        mechanical plant, so that noise acts as a force).
    measurement_std : float
        Standard deviation (the scale) of the measurement noise (added to ``y_k``).
    seed : int or sequence of M ints, optional
        Trial ``i`` draws its noise from ``default_rng(seed[i])``; an int is spawned into M streams
        (``SeedSequence``). With one trial an int seed is used directly, as in :func:`simulate`.
    method, rtol, atol, substeps
        See :func:`step_function`.
    blowup : float
        A trial whose state exceeds this magnitude is marked failed (``ok`` False).
    n_threads : int, optional
        Worker threads for the trial map (default: the CPU count).
    params : array_like, shape (n_params,) or (M, n_params), optional
        The plant's parameter values (a plant with parameters, :class:`kklcasadi.System`): one set
        for every trial or one per trial; values outside the plant's ``param_box`` are allowed.
        Default: the nominal plant (:attr:`kklcasadi.System.f`).
    noise_model : NoiseModel or str, optional
        The measurement noise's distribution, outliers and quantisation (:mod:`kklcasadi.plant.noise`:
        ``"gauss"``, ``"student-t:NU"``, ``"outliers:P,K"``, ``"quantised:STEP"``, combined with ``+``),
        scaled by ``measurement_std``; default Gaussian.
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
    single = callable(u) or isinstance(u, OutputFeedback) or (not isinstance(u, (list, tuple)))
    inputs = [u] * m if single else list(u)
    if len(inputs) != m:
        raise error("u", f"one input or a sequence of M = {m} inputs", Text(f"{len(inputs)} inputs"))
    feedback = [isinstance(ui, OutputFeedback) for ui in inputs]
    if any(feedback) and not (all(feedback) and len({type(ui) for ui in inputs}) == 1):
        raise error("u", "signals or arrays for every trial, or output-feedback laws of one class for every trial",
                    Text(f"{sum(feedback)} laws among {m} inputs"), kind=TypeError)
    process_std = state_stds(process_std, system.nx)
    measurement_std = nonnegative_number(measurement_std, "measurement_std")
    noise = as_noise_model(noise_model)
    theta = None if params is None else system.param_rows(params, m)
    rngs = [np.random.default_rng(s) for s in _seeds(seed, m)]
    w = np.stack([rng.normal(0.0, 1.0, (n - 1, system.nx)) for rng in rngs]) * process_std
    v = np.stack([noise.sample(rng, (n, system.ny), 1.0) for rng in rngs]) * measurement_std
    x = np.full((m, n, system.nx), np.nan)
    x[:, 0] = x0
    options = {"rtol": rtol, "atol": atol, "substeps": substeps, "parametric": theta is not None}
    held = [] if theta is None else [np.repeat(theta[:, None], n - 1, axis=1)]      # (M, N-1, n_params)
    if all(feedback):
        us, ok = _closed_loop(system, x0, inputs, t, dt, w, v, x, method, options, n_threads, theta, noise)
    else:
        us = np.stack([input_samples(ui, t, system.nu, f"u[{i}]") for i, ui in enumerate(inputs)])
        traj = step_function(system, dt, method, **options).mapaccum("trajectory", n - 1)
        rows = np.concatenate([us[:, :-1, :], w, *held], axis=2)    # (M, N-1, nu+nx[+n_params])
        states, ok = _fold(traj, x0.T, rows, n_threads)
        x[:, 1:] = states.reshape(m, n - 1, system.nx)
    with np.errstate(invalid="ignore"):
        x[~(np.abs(x) < blowup)] = np.nan                       # inf, NaN and blow-ups become NaN
    ok &= ~np.isnan(x).any(axis=(1, 2))
    y = noise.measure(_outputs(system, x, theta) + v)
    for arr in (x, us, y):
        arr.setflags(write=False)
    return TrajectoryBatch(t, x, us, y, ok)


def _outputs(system: System, x: np.ndarray, theta: np.ndarray | None) -> np.ndarray:
    """``h(x)`` of (M, N, nx) states, at the nominal parameters or at ``theta`` (M, n_params) per trial."""
    m, n = x.shape[:2]
    params = None if theta is None else np.repeat(theta, n, axis=0)
    return system.h_batch(x.reshape(m * n, system.nx), params=params).reshape(m, n, system.ny)


def _fold(traj: ca.Function, s0: np.ndarray, params: np.ndarray,
          n_threads: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Run a folded trajectory (one input state, one parameter row and one output per interval) for
    every trial: ``s0`` (ns, M) columns, ``params`` (M, N-1, np).

    Returns the output per trial and interval, (M, N-1, rows), NaN for the trials that
    failed in the integrator, and ``ok`` (M,). A failing batch is retried trial by trial to
    isolate the failures.
    """
    m, steps = params.shape[:2]
    rows = traj.size1_out(0)
    out = np.full((m, steps, rows), np.nan)
    ok = np.ones(m, dtype=bool)
    threads = n_threads or os.cpu_count() or 1
    try:
        batch = traj.map(m, "thread", min(threads, m))
        out[:] = np.asarray(batch(s0, params.reshape(m * steps, -1).T)).T.reshape(m, steps, rows)
    except RuntimeError as err:
        log.info("batched simulation failed (%s); retrying trial by trial to isolate the failures", err)
        for i in range(m):
            try:
                out[i] = np.asarray(traj(s0[:, i], params[i].T)).T
            except RuntimeError as trial_err:
                log.info("trial %d failed in the integrator: %s", i, trial_err)
                ok[i] = False
    return out, ok


def _closed_loop(system: System, x0: np.ndarray, laws: list, t: np.ndarray, dt: float, w: np.ndarray,
                 v: np.ndarray, x: np.ndarray, method: str, options: dict, n_threads: int | None,
                 plant_theta: np.ndarray | None, noise: NoiseModel) -> tuple[np.ndarray, np.ndarray]:
    """Simulate M closed loops in place in ``x`` (M, N, nx); return the applied inputs (M, N, nu) and ``ok``."""
    for i, law in enumerate(laws):
        _check_law(system, law, f"u[{i}]")
    m, n = x.shape[:2]
    nx, nu = system.nx, system.nu
    refs = np.stack([input_samples(law.reference, t, law.channels, f"u[{i}].reference") for i, law in enumerate(laws)])
    theta = np.stack([np.asarray(law.theta(), dtype=float) for law in laws])           # (M, nth)
    y0 = noise.measure(system.h_batch(x0, params=plant_theta) + v[:, 0])
    s0 = np.stack([np.concatenate([x0[i], laws[i].state0(y0[i])]) for i in range(m)])   # (M, nx + nc)
    step = closed_loop_step(system, laws[0], dt, method, **options, noise=noise)
    traj = ca.Function("closed_loop", *_with_inputs(step.mapaccum("closed_loop", n - 1)))
    held = [] if plant_theta is None else [np.repeat(plant_theta[:, None], n - 1, axis=1)]
    params = np.concatenate([w, v[:, :-1], refs[:, :-1], np.repeat(theta[:, None], n - 1, axis=1), *held], axis=2)
    out, ok = _fold(traj, s0.T, params, n_threads)
    x[:, 1:] = out[..., :nx]
    us = np.full((m, n, nu), np.nan)
    us[:, :-1] = out[..., nx + laws[0].n_state:]
    # the last input, from the last measurement and the law's last state
    law = laws[0].function(dt)
    y_last = noise.measure(system.h_batch(np.nan_to_num(x[:, -1]), params=plant_theta) + v[:, -1])
    c_last = out[:, -1, nx:nx + laws[0].n_state]
    us[:, -1] = np.asarray(law.map(m)(np.nan_to_num(c_last).T, y_last.T, refs[:, -1].T, theta.T)[0]).T
    us[~ok] = np.nan
    return us, ok


def _with_inputs(traj: ca.Function) -> tuple[list, list, list, list]:
    """``traj`` (s0, P) -> (S, U) as a Function whose one output stacks ``[S; U]`` per interval."""
    s0, params = ca.MX.sym("s0", traj.sparsity_in(0)), ca.MX.sym("P", traj.sparsity_in(1))
    states, inputs = traj(s0, params)
    return [s0, params], [ca.vertcat(states, inputs)], ["s0", "P"], ["SU"]


def simulate(system: System, x0: Any, u: InputLike, T: float = 50.0, dt: float = 0.05, *, process_std: float = 0.0,
             measurement_std: float = 0.0, seed: int | None = None, method: str = "cvodes", rtol: float = 1e-8,
             atol: float = 1e-10, substeps: int = 4, params: object = None,
             noise_model: NoiseModel | str | None = None) -> Trajectory:
    """Simulate one trial with a CasADi integrator (see :func:`simulate_batch` for the parameters).

    Parameters
    ----------
    x0 : array_like, shape (nx,)
    u : signal ``u(t) -> (nu,)`` or array, shape (N, nu)
    params : array_like, shape (n_params,), optional
        The plant's parameter values; default the nominal ones.
    noise_model : NoiseModel or str, optional
        The measurement noise (:mod:`kklcasadi.plant.noise`); default Gaussian.

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
                           seed=[seed], method=method, rtol=rtol, atol=atol, substeps=substeps, n_threads=1,
                           params=None if params is None else np.asarray(params, dtype=float)[None],
                           noise_model=noise_model)
    if not batch.ok[0]:
        raise RuntimeError(f"simulation of {system.name!r} from x0 = {x0.tolist()} failed or blew up; "
                           "shorten T, reduce the input, or use method='cvodes'")
    return batch[0]
