"""Moving-horizon estimation on the exact CasADi model, plain and primed by a KKL observer.

:class:`MHE` solves, at every sample ``k``, the least-squares problem over the last ``N``
sample intervals (nodes ``x_{k-n}, ..., x_k`` with ``n = min(k, N)``)::

    min  ||x_{k-n} - xbar||^2_{P^-1}  +  sum_j ||w_j||^2 / qw^2  +  sum_j ||y_j - h(x_j)||^2 / rv^2
    s.t. x_{j+1} = Phi(x_j, u_j, w_j),   j = k-n, ..., k-1

where ``Phi`` is RK4 (``substeps`` steps) over one sample interval of ``xdot = f(x, u) + w`` with
``u`` and the process noise ``w`` held on the interval: the noise model of docs/protocol.md and
:func:`kklcasadi.plant.simulate` (``qw = process_std``, ``rv = measurement_std``). The estimate is
``x_k``. Before ``N`` intervals exist the horizon grows (``n = k``): one problem per length
``n = 0..N``, each built once with :class:`casadi.Opti` and compiled with
``Opti.to_function`` into one :class:`casadi.Function` call per step (ipopt, exact Hessian,
expanded to SX).

Arrival cost (plain MHE): ``(xbar, P)`` starts at the X0 box centre with the box's variance
(as the EKF) at node 0 and stays there while the horizon grows. Once the window slides past
node ``s - 1``, the prior of its new first node ``s`` is the filtering one: the MHE's own
estimate of ``x_{s-1}`` (made at time ``s - 1``) propagated through ``Phi``, with ``P``
propagated by one EKF step (covariance update with ``h``'s Jacobian, then the time update with
the exact Jacobians of ``Phi``) -- the EKF arrival cost of Rao, Rawlings and Lee (2001). (The
smoothed estimate of ``x_s`` from the previous window would count ``y_s..y_{k-1}`` twice;
measured on Duffing it cost 2-3 SMAPE points against the EKF.)

KKL-primed MHE (:class:`KKLPrimedMHE`): the learned observer runs alongside; its estimate at
``k - n`` is the arrival prior, with a covariance from the observer's typical error at that time
(calibrated on simulated runs, :func:`kkl_error_profile`), and its estimate at ``k`` initialises
the newest node. A short horizon then suffices.

Every solve is checked: ipopt's ``success`` and a finite solution. A failed solve is never
returned as an estimate: the plain MHE falls back to the previous estimate propagated through
the model, the primed one to the KKL estimate; both count it in :class:`MHEStats`.

Both are protocol estimators (``kklcasadi.evaluation.protocol``): ``mhe(t, y, u) -> xhat`` with
``y`` (M, N, ny), ``u`` (M, N, nu), ``xhat`` (M, N, nx).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Optional, Sequence

import casadi as ca
import numpy as np

from ..plant.rk4 import rk4_step
from ..plant.systems import System
from ..validation import covariance, nonnegative_number, positive_int

__all__ = ["MHE", "KKLPrimedMHE", "MHEEstimate", "MHEStats", "SolveRecord", "kkl_error_profile",
           "solve_compiled", "ipopt_options"]

#: ipopt return statuses that count as a solved problem.
_SOLVED = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


# ---------------------------------------------------------------------- solver helpers
def ipopt_options(max_iter: int = 50, **extra: Any) -> dict:
    """Options of ``Opti.solver("ipopt", ...)``: silent, exact Hessian, expanded to SX.

    Parameters
    ----------
    max_iter : int
        Iteration limit per solve.
    **extra
        More ipopt options (e.g. ``tol``, ``mu_init``), passed under ``"ipopt"``.

    Returns
    -------
    dict
        ``{"plugin": {...}, "ipopt": {...}}``: the two option dictionaries of ``Opti.solver``.
    """
    positive_int(max_iter, "max_iter")
    ipopt = {"print_level": 0, "sb": "yes", "max_iter": int(max_iter),
             "hessian_approximation": "exact", **extra}
    plugin = {"expand": True, "print_time": False, "error_on_fail": False}
    return {"plugin": plugin, "ipopt": ipopt}


@dataclass(frozen=True)
class SolveRecord:
    """The outcome of one compiled ``Opti`` solve.

    Attributes
    ----------
    success : bool
        ipopt's ``success`` and a finite solution.
    status : str
        ipopt's ``return_status`` (``"NonFinite_Solution"`` when ipopt succeeded but the solution
        holds a NaN/inf).
    iterations : int
    seconds : float
        Wall time of the call.
    """

    success: bool
    status: str
    iterations: int
    seconds: float


def solve_compiled(function: ca.Function, args: Sequence[Any]) -> tuple[list[np.ndarray], SolveRecord]:
    """Call a Function made by ``Opti.to_function`` and read ipopt's statistics of the call.

    Parameters
    ----------
    function : casadi.Function
        From ``opti.to_function(...)`` (its ``stats()`` are those of the embedded ipopt call).
    args : sequence
        Its inputs, in order.

    Returns
    -------
    outputs : list of numpy.ndarray
        The Function's outputs (dense).
    record : SolveRecord
    """
    start = time.perf_counter()
    outputs = function.call(list(args))
    seconds = time.perf_counter() - start
    stats = function.stats()
    arrays = [np.asarray(ca.DM(out)) for out in outputs]
    status = str(stats.get("return_status", "unknown"))
    success = bool(stats.get("success", False)) and status in _SOLVED
    if success and not all(np.all(np.isfinite(a)) for a in arrays):
        success, status = False, "NonFinite_Solution"
    return arrays, SolveRecord(success, status, int(stats.get("iter_count", -1)), seconds)


# ---------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class MHEStats:
    """Solver statistics of an MHE run.

    Attributes
    ----------
    iterations : numpy.ndarray, shape (M, N)
        ipopt iterations per solve.
    solve_time : numpy.ndarray, shape (M, N)
        Wall time per solve in seconds (the compiled Function call).
    failed : numpy.ndarray of bool, shape (M, N)
        Solves that failed; their estimate is the fallback (see :class:`MHE`).
    statuses : dict
        ``{return_status: count}`` over all solves.
    """

    iterations: np.ndarray
    solve_time: np.ndarray
    failed: np.ndarray
    statuses: dict

    @property
    def n_solves(self) -> int:
        return int(self.failed.size)

    @property
    def n_failed(self) -> int:
        """Solves whose estimate is the fallback."""
        return int(self.failed.sum())

    @property
    def mean_solve_time(self) -> float:
        """Mean wall time per solve in seconds."""
        return float(np.mean(self.solve_time))

    def __str__(self) -> str:
        return (f"{self.n_solves} solves, {self.n_failed} failed (fallback used), "
                f"mean {self.mean_solve_time * 1e3:.2f} ms, iterations mean "
                f"{np.mean(self.iterations):.1f} max {int(np.max(self.iterations))}, "
                f"statuses {dict(self.statuses)}")


@dataclass(frozen=True, eq=False)
class MHEEstimate:
    """An MHE run: ``t`` (N,), ``xhat`` (N, nx) or (M, N, nx), and its :class:`MHEStats`."""

    t: np.ndarray
    xhat: np.ndarray
    stats: MHEStats


# ---------------------------------------------------------------------- the estimator
class MHE:
    """Moving-horizon estimator for ``xdot = f(x, u) + w``, ``y = h(x) + v`` sampled every ``dt``.

    Parameters
    ----------
    system : System
    dt : float
        Sample period.
    horizon : int
        ``N``, the number of sample intervals in the window (``N + 1`` measurements).
    process_std : float
        Standard deviation of the process noise on ``xdot`` (held per interval); the weight of
        ``||w||^2`` is ``1 / max(process_std, noise_floor)^2``.
    measurement_std : float
        Standard deviation of the measurement noise; weight ``1 / max(measurement_std,
        noise_floor)^2``.
    x0 : array_like, shape (nx,), optional
        Prior mean at node 0; default the X0 box centre.
    P0 : array_like, shape (nx, nx), optional
        Prior covariance at node 0; default the variance of the uniform distribution on the box.
    substeps : int
        RK4 steps per sample interval in ``Phi``.
    noise_floor : float
        Lower bound of the noise levels used in the weights (noise-free data gets small but
        finite, regularising weights).
    max_iter : int
        ipopt iteration limit per solve.
    ipopt : dict, optional
        More ipopt options.
    params : array_like, shape (n_params,), optional
        The parameter values of the estimator's model, for a plant with parameters; default the
        nominal ones (:meth:`kklcasadi.System.at`).

    Attributes
    ----------
    system : System
    dt : float
    horizon : int
    nx, nu, ny : int
    phi : casadi.Function
        ``phi(x, u, w) -> x_next``, the model over one interval.
    arrival : casadi.Function
        ``arrival(x, P, u) -> P_next``: EKF propagation of the prior covariance from a node to the
        next (update with ``h``'s Jacobian, then the time update with ``phi``'s Jacobians).
    last_stats : MHEStats or None
        Statistics of the last :meth:`__call__`.
    """

    def __init__(self, system: System, dt: float, horizon: int = 10, *, process_std: float = 0.1,
                 measurement_std: float = 0.1, x0: Any = None, P0: Any = None, substeps: int = 1,
                 noise_floor: float = 1e-3, max_iter: int = 50,
                 ipopt: Optional[dict] = None, params: Any = None) -> None:
        if not isinstance(system, System):
            raise TypeError(f"system: expected a kklcasadi.System, received "
                            f"{type(system).__name__}.")
        if params is not None:
            system = system.at(params)
        dt = nonnegative_number(dt, "dt")
        if dt == 0:
            raise ValueError("dt: expected a sample period > 0, received 0.")
        self.system, self.dt = system, dt
        self.horizon = positive_int(horizon, "horizon")
        self.substeps = positive_int(substeps, "substeps")
        self.max_iter = positive_int(max_iter, "max_iter")
        self.nx, self.nu, self.ny = system.nx, system.nu, system.ny
        floor = nonnegative_number(noise_floor, "noise_floor")
        if floor == 0:
            raise ValueError("noise_floor: expected a number > 0 (it keeps the weights finite), "
                             "received 0.")
        self.process_std = nonnegative_number(process_std, "process_std")
        self.measurement_std = nonnegative_number(measurement_std, "measurement_std")
        self._qw = max(self.process_std, floor)
        self._rv = max(self.measurement_std, floor)
        box = system.x0_box
        self.x0 = box.mean(axis=1) if x0 is None else system.check_state(x0, "x0")
        if P0 is not None:
            P0 = covariance(P0, self.nx, "P0", definite=True)
        self.P0 = np.diag((box[:, 1] - box[:, 0]) ** 2 / 12.0) if P0 is None else 0.5 * (P0 + P0.T)
        self._ipopt = dict(ipopt or {})

        x, w = ca.SX.sym("x", self.nx), ca.SX.sym("w", self.nx)
        u = ca.SX.sym("u", self.nu)
        x_next = rk4_step(lambda _s, xx: system.f(xx, u) + w, x, self.dt, self.substeps)
        self.phi = ca.Function("phi", [x, u, w], [x_next], ["x", "u", "w"], ["x_next"])
        P = ca.SX.sym("P", self.nx, self.nx)
        H = system.h_jac(x)
        S = ca.mtimes([H, P, H.T]) + self._rv ** 2 * ca.DM.eye(self.ny)
        P_upd = P - ca.mtimes([P, H.T, ca.solve(S, ca.mtimes(H, P))])
        F, G = ca.jacobian(x_next, x), ca.jacobian(x_next, w)
        w0 = ca.DM.zeros(self.nx)
        F, G = ca.substitute(F, w, w0), ca.substitute(G, w, w0)
        P_next = ca.mtimes([F, P_upd, F.T]) + self._qw ** 2 * ca.mtimes(G, G.T)
        self.arrival = ca.Function("arrival", [x, P, u], [0.5 * (P_next + P_next.T)],
                                   ["x", "P", "u"], ["P_next"])
        self._solvers: dict[int, ca.Function] = {}
        self.last_stats: Optional[MHEStats] = None

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(system={self.system.name!r}, horizon={self.horizon}, "
                f"dt={self.dt}, process_std={self.process_std}, "
                f"measurement_std={self.measurement_std})")

    # ------------------------------------------------------------------ problems
    def problem(self, n: int) -> ca.Function:
        """The compiled problem over ``n`` intervals (built on first use, then cached).

        Parameters
        ----------
        n : int
            Window length in intervals, ``0 <= n <= horizon``.

        Returns
        -------
        casadi.Function
            ``mhe_n(xbar (nx,1), Lp (nx,nx), Y (ny,n+1), U (nu,n), X0 (nx,n+1), W0 (nx,n))
            -> (X, W)``: ``Lp`` is the scaled square root of the prior's inverse covariance
            (``rv^2 P^-1 = Lp^T Lp``), ``X0`` and ``W0`` the initial guess. For ``n = 0`` the
            ``U``, ``W0`` and ``W`` slots are absent.
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 0 <= n <= self.horizon:
            raise ValueError(f"n: expected an int in [0, {self.horizon}], received {n!r}.")
        n = int(n)
        if n not in self._solvers:
            self._solvers[n] = self._build(n)
        return self._solvers[n]

    def _build(self, n: int) -> ca.Function:
        nx, nu, ny = self.nx, self.nu, self.ny
        opti = ca.Opti()
        X = opti.variable(nx, n + 1)
        xbar, Lp = opti.parameter(nx), opti.parameter(nx, nx)
        Y = opti.parameter(ny, n + 1)
        residual = Y - self.system.h.map(n + 1)(X)
        cost = ca.sumsqr(ca.mtimes(Lp, X[:, 0] - xbar)) + ca.sumsqr(residual)
        inputs, names = [xbar, Lp, Y], ["xbar", "Lp", "Y"]
        outputs, out_names = [X], ["X"]
        if n > 0:
            W, U = opti.variable(nx, n), opti.parameter(nu, n)
            cost = cost + (self._rv / self._qw) ** 2 * ca.sumsqr(W)
            opti.subject_to(X[:, 1:] == self.phi.map(n)(X[:, :-1], U, W))
            inputs.insert(3, U)
            names.insert(3, "U")
            outputs.append(W)
            out_names.append("W")
        opti.minimize(cost)
        options = ipopt_options(self.max_iter, **self._ipopt)
        opti.solver("ipopt", options["plugin"], options["ipopt"])
        guesses = [X] + ([outputs[1]] if n > 0 else [])
        return opti.to_function(f"mhe_{n}", inputs + guesses, outputs,
                                names + [f"{name}0" for name in out_names], out_names)

    # ------------------------------------------------------------------ running
    def _prior_root(self, P: np.ndarray) -> np.ndarray:
        """``Lp`` with ``Lp^T Lp = rv^2 P^-1``."""
        info = np.linalg.inv(P)
        info = 0.5 * (info + info.T)
        return self._rv * np.linalg.cholesky(info).T

    def simulate(self, t: Any, y: Any, u: Any, *, guide: Any = None,
                 guide_std: Any = None) -> MHEEstimate:
        """Estimate one or many measured trajectories, one solve per sample.

        Parameters
        ----------
        t : array_like, shape (N,)
            Sample times, spaced by ``dt``.
        y : array_like, shape (N, ny) or (M, N, ny)
        u : array_like, shape (N, nu) or (M, N, nu)
            ``u_k`` is held on ``[t_k, t_k+1)``.
        guide : array_like, shape like ``xhat``, optional
            An external estimate (the KKL observer's): the arrival prior mean at the window's
            first node, the initial guess of the newest node, and the fallback of a failed solve.
            Without it the arrival cost is the EKF one and the fallback is the propagated
            previous estimate.
        guide_std : array_like, shape (N, nx), optional
            Standard deviation of the guide's error at each sample (the prior covariance is
            ``diag(guide_std[k - n]^2)``); required with ``guide``.

        Returns
        -------
        MHEEstimate
            ``xhat`` (N, nx) or (M, N, nx), ``xhat_k`` from ``y_0..y_k`` and ``u_0..u_k-1``.
        """
        t, ys, us, single = _check_run(t, y, u, self)
        m, n_samples = ys.shape[:2]
        guides, guide_var = _check_guide(guide, guide_std, m, n_samples, self.nx, single)
        xhat = np.empty((m, n_samples, self.nx))
        iterations = np.zeros((m, n_samples), dtype=int)
        seconds = np.zeros((m, n_samples))
        failed = np.zeros((m, n_samples), dtype=bool)
        statuses: Counter = Counter()
        for i in range(m):
            g = None if guides is None else guides[i]
            records = self._run_trial(ys[i], us[i], g, guide_var, xhat[i])
            for k, record in enumerate(records):
                iterations[i, k], seconds[i, k] = record.iterations, record.seconds
                failed[i, k] = not record.success
                statuses[record.status] += 1
        stats = MHEStats(iterations, seconds, failed, dict(statuses))
        for array in (xhat, iterations, seconds, failed):
            array.setflags(write=False)
        return MHEEstimate(t, xhat[0] if single else xhat, stats)

    def __call__(self, t: Any, y: Any, u: Any) -> np.ndarray:
        """The protocol estimator ``(t, y (M,N,ny), u (M,N,nu)) -> xhat (M,N,nx)``.

        The statistics of the call are kept in :attr:`last_stats`.
        """
        run = self.simulate(t, y, u)
        self.last_stats = run.stats
        return run.xhat

    def _run_trial(self, y: np.ndarray, u: np.ndarray, guide: Optional[np.ndarray],
                   guide_var: Optional[np.ndarray], out: np.ndarray) -> list[SolveRecord]:
        """Fill ``out`` (N, nx) with the estimates of one trial; return one record per sample."""
        N, nx = self.horizon, self.nx
        records: list[SolveRecord] = []
        xbar, P = self.x0.copy(), self.P0.copy()
        X = np.zeros((nx, 1))
        W = np.zeros((nx, 0))
        for k in range(y.shape[0]):
            n = min(k, N)
            start = k - n
            if guide is not None:
                xbar, P = guide[start], np.diag(guide_var[start])
            elif n == N and k > N:
                # the window slid: the prior of the new first node is the filtered estimate of the
                # dropped node propagated one interval, with the EKF covariance propagation
                P = np.asarray(self.arrival(out[start - 1], P, u[start - 1]))
                xbar = np.asarray(self.phi(out[start - 1], u[start - 1], np.zeros(nx))).ravel()
            # warm start: the previous solution shifted by one node, the newest node predicted
            newest = (guide[k] if guide is not None and k > 0 else
                      np.asarray(self.phi(X[:, -1], u[k - 1], np.zeros(nx))).ravel() if k > 0
                      else xbar)
            if n == 0:
                X_guess = xbar[:, None]
            else:
                keep = X[:, 1:] if X.shape[1] == n + 1 else X
                X_guess = np.hstack([keep, newest[:, None]])
                keep_w = W[:, 1:] if W.shape[1] == n else W
                W_guess = np.hstack([keep_w, np.zeros((nx, 1))])
            args: list[Any] = [xbar, self._prior_root(P), y[start:k + 1].T]
            if n > 0:
                args += [u[start:k].T, X_guess, W_guess]
            else:
                args += [X_guess]
            outputs, record = solve_compiled(self.problem(n), args)
            records.append(record)
            if record.success:
                X = outputs[0]
                W = outputs[1] if n > 0 else np.zeros((nx, 0))
            else:
                X, W = X_guess, (W_guess if n > 0 else np.zeros((nx, 0)))
            out[k] = X[:, -1]
        return records


class KKLPrimedMHE:
    """The MHE with its arrival prior and warm start from a KKL observer.

    At sample ``k`` the prior of the window's first node ``k - n`` is the KKL estimate there,
    with covariance ``diag(error_std[k - n]^2)``; the newest node starts at the KKL estimate at
    ``k``, and a failed solve returns the KKL estimate (counted in the stats).

    Parameters
    ----------
    observer : KKLObserver
        The learned observer (its ``simulate`` runs alongside; its system and ``dt`` are used).
    error_std : array_like, shape (N, nx) or (nx,)
        Typical error of the observer at each sample time (:func:`kkl_error_profile`), or one
        level for all times.
    horizon : int
        Short window length (default 5).
    **mhe_options
        Keyword options of :class:`MHE` (``process_std``, ``measurement_std``, ``substeps``,
        ``noise_floor``, ``max_iter``, ``ipopt``).

    Attributes
    ----------
    observer : KKLObserver
    mhe : MHE
    error_std : numpy.ndarray
    last_stats : MHEStats or None
        Statistics of the last :meth:`__call__`.
    """

    def __init__(self, observer: Any, error_std: Any, horizon: int = 5, **mhe_options: Any) -> None:
        from ..observer.kkl import KKLObserver

        if not isinstance(observer, KKLObserver):
            raise TypeError(f"observer: expected a KKLObserver (kc.load_observer), received "
                            f"{type(observer).__name__}.")
        self.observer = observer
        self.mhe = MHE(observer.system, observer.dt, horizon, **mhe_options)
        std = np.asarray(error_std, dtype=float)
        if std.ndim not in (1, 2) or std.shape[-1] != observer.nx or not np.all(std > 0):
            raise ValueError(f"error_std: expected positive values of shape (N, {observer.nx}) or "
                             f"({observer.nx},), received shape {std.shape}"
                             f"{'' if std.size == 0 or np.all(std > 0) else ' with values <= 0'}.")
        self.error_std = std
        self.last_stats: Optional[MHEStats] = None

    def __repr__(self) -> str:
        return (f"KKLPrimedMHE(method={self.observer.method!r}, system="
                f"{self.observer.system.name!r}, horizon={self.mhe.horizon})")

    def _std(self, n_samples: int) -> np.ndarray:
        if self.error_std.ndim == 1:
            return np.repeat(self.error_std[None], n_samples, axis=0)
        if self.error_std.shape[0] < n_samples:
            tail = np.repeat(self.error_std[-1:], n_samples - self.error_std.shape[0], axis=0)
            return np.vstack([self.error_std, tail])
        return self.error_std[:n_samples]

    def simulate(self, t: Any, y: Any, u: Any) -> MHEEstimate:
        """Run the observer, then the MHE primed by it (shapes as :meth:`MHE.simulate`)."""
        guide = self.observer.simulate(t, y, u).xhat
        return self.mhe.simulate(t, y, u, guide=guide, guide_std=self._std(np.size(t)))

    def __call__(self, t: Any, y: Any, u: Any) -> np.ndarray:
        """The protocol estimator; statistics in :attr:`last_stats`."""
        run = self.simulate(t, y, u)
        self.last_stats = run.stats
        return run.xhat


def kkl_error_profile(observer: Any, protocol: Any, kinds: Sequence[str] = ("zero", "constant",
                      "sinusoid", "square"), *, floor: float = 0.05) -> np.ndarray:
    """The observer's RMS error at each sample time over simulated protocol runs (calibration).

    Use a protocol with another seed than the benchmark's, so that the calibration runs are not
    the scored ones.

    Parameters
    ----------
    observer : KKLObserver
    protocol : kklcasadi.evaluation.protocol.Protocol
        Trials to calibrate on (its noise levels, horizon and seed).
    kinds : sequence of str
        Input regimes pooled.
    floor : float
        Lower bound of the returned standard deviations, as a fraction of the X0 box half-width
        (keeps the prior from being overconfident where the sample error is small by chance).

    Returns
    -------
    numpy.ndarray, shape (N, nx)
        RMS over trials of ``x - xhat`` per state and sample.
    """
    system = observer.system
    errors = []
    for kind in kinds:
        batch = protocol.trials(system, kind)
        ok = batch.ok
        xhat = observer.simulate(batch.t, batch.y[ok], batch.u[ok]).xhat
        errors.append(batch.x[ok] - xhat)
    err = np.concatenate(errors, axis=0)
    half = 0.5 * (system.x0_box[:, 1] - system.x0_box[:, 0])
    return np.maximum(np.sqrt(np.mean(err ** 2, axis=0)), nonnegative_number(floor, "floor") * half)


# ---------------------------------------------------------------------- checks
def _check_run(t: Any, y: Any, u: Any, mhe: MHE) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size < 1:
        raise ValueError(f"t: expected sample times of shape (N,), received shape {t.shape}.")
    if t.size > 1 and not np.allclose(np.diff(t), mhe.dt, rtol=1e-9, atol=1e-12):
        raise ValueError(f"t: expected samples spaced by dt = {mhe.dt}, received steps in "
                         f"[{np.min(np.diff(t))}, {np.max(np.diff(t))}].")
    ys, us = np.asarray(y, dtype=float), np.asarray(u, dtype=float)
    single = ys.ndim == 2
    if single:
        ys, us = ys[None], us[None]
    if ys.ndim != 3 or ys.shape[1:] != (t.size, mhe.ny):
        raise ValueError(f"y: expected shape (N, {mhe.ny}) or (M, N, {mhe.ny}) with N = {t.size}, "
                         f"received {np.shape(y)}.")
    if us.shape != ys.shape[:2] + (mhe.nu,):
        raise ValueError(f"u: expected shape {ys.shape[:2] + (mhe.nu,)} (as y), received "
                         f"{np.shape(u)}.")
    for name, values in (("y", ys), ("u", us)):
        bad = np.argwhere(~np.isfinite(values))
        if bad.size:
            raise ValueError(f"{name}: expected finite values, received a NaN/inf at trial "
                             f"{bad[0, 0]}, sample {bad[0, 1]}.")
    return t, ys, us, single


def _check_guide(guide: Any, guide_std: Any, m: int, n: int, nx: int,
                 single: bool) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
    if guide is None:
        if guide_std is not None:
            raise ValueError("guide_std: given without guide; pass both or neither.")
        return None, None
    g = np.asarray(guide, dtype=float)
    if single and g.ndim == 2:
        g = g[None]
    if g.shape != (m, n, nx):
        expected = f"({n}, {nx})" if single else f"({m}, {n}, {nx})"
        raise ValueError(f"guide: expected shape {expected} (as the estimate), received "
                         f"{np.shape(guide)}.")
    if not np.all(np.isfinite(g)):
        raise ValueError("guide: expected finite values, received a NaN/inf.")
    if guide_std is None:
        raise ValueError("guide_std: required with guide (the prior's standard deviation per "
                         "sample, shape (N, nx)).")
    s = np.asarray(guide_std, dtype=float)
    if s.shape != (n, nx) or not np.all(s > 0):
        raise ValueError(f"guide_std: expected positive values of shape ({n}, {nx}), received "
                         f"shape {s.shape}.")
    return g, s ** 2
