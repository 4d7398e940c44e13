"""Output-feedback nonlinear MPC on the CasADi plant, fed by a state estimator.

:class:`NMPC` is a multiple-shooting problem built once with :class:`casadi.Opti` and compiled
with ``Opti.to_function`` (ipopt, exact Hessian, expanded to SX), so that a solve is one
Function call::

    min   sum_{j<N} ||x_j - x_ref||_Q^2 + ||u_j - u_ref||_R^2 + ||x_N - x_ref||_Qf^2
          + rho1 sum s + rho2 sum s^2
    s.t.  x_0 = x_init,  x_{j+1} = Phi(x_j, u_j)          (RK4 over one sample, input held)
          u_lo <= u_j <= u_hi
          lo_i - s_ij <= x_{i,j} <= hi_i + s_ij,  s >= 0     (soft state bounds, optional)

The previous solution, shifted by one sample, warm-starts the next solve (primal and dual).

:func:`closed_loop` runs the loop the way a deployed controller does: the plant is a CVODES
integrator with the docs/protocol.md process noise held on each interval and measurement noise on
``y``; at sample ``k`` the estimator receives ``y_k`` and the input ``u_k`` already applied
from ``t_k`` (``make_step(y_k, u_k)``, the :class:`kklcasadi.observer.kkl.Estimator` convention)
and returns ``xhat_k``; the controller then predicts ``x_{k+1}`` from ``xhat_k`` and ``u_k``
and computes ``u_{k+1}``, applied from ``t_{k+1}``: one sample of computation delay, as in
``examples/closed_loop.py``, compensated by the prediction. The same loop with the true state
in place of ``xhat_k`` is the full-information reference.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Optional

import casadi as ca
import numpy as np

from ..plant.rk4 import rk4_step
from ..plant.systems import System
from ..validation import nonnegative_number, positive_int
from .ekf import EKF
from .mhe import SolveRecord, ipopt_options, solve_compiled

__all__ = ["NMPC", "NMPCStep", "ClosedLoop", "EKFEstimator", "TrueState", "closed_loop",
           "steady_state", "plant_step"]


def steady_state(system: System, r: float, index: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The equilibrium ``(x_ref, u_ref)`` with ``x_ref[index] = r`` of a single-input plant.

    Solves ``f(x, u) = 0`` for the other states and the input with CasADi's Newton rootfinder,
    started at zero.

    Parameters
    ----------
    system : System
        A plant with ``nu = 1`` (the unknowns are ``nx - 1`` states and the input).
    r : float
        Set point of state ``index``.
    index : int

    Returns
    -------
    x_ref : numpy.ndarray, shape (nx,)
    u_ref : numpy.ndarray, shape (1,)
    """
    if not isinstance(system, System):
        raise TypeError(f"system: expected a kklcasadi.System, received {type(system).__name__}.")
    if system.nu != 1:
        raise ValueError(f"system: expected a single-input plant (nu = 1) so that f(x, u) = 0 "
                         f"with x[{index}] fixed is square, received nu = {system.nu}.")
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < system.nx:
        raise ValueError(f"index: expected an int in [0, {system.nx}), received {index!r}.")
    v = ca.SX.sym("v", system.nx)                      # other states, then u
    others = [i for i in range(system.nx) if i != index]
    x = ca.SX.zeros(system.nx)
    x[index] = float(r)
    for j, i in enumerate(others):
        x[i] = v[j]
    residual = system.f(x, v[-1])
    finder = ca.rootfinder("steady_state", "newton", ca.Function("g", [v], [residual]))
    sol = np.asarray(finder(np.zeros(system.nx))).ravel()
    x_ref = np.empty(system.nx)
    x_ref[index] = float(r)
    x_ref[others] = sol[:-1]
    if not np.allclose(np.asarray(system.f(x_ref, sol[-1:])).ravel(), 0.0, atol=1e-9):
        raise ValueError(f"r: no equilibrium of {system.name!r} with x[{index}] = {r} was found "
                         "from the zero guess.")
    return x_ref, sol[-1:]


def plant_step(system: System, dt: float, *, rtol: float = 1e-8, atol: float = 1e-10) -> ca.Function:
    """The plant over one sample interval: CVODES, ``(x, u, w) -> x_next``, ``xdot = f(x, u) + w``.

    ``u`` and the process noise ``w`` are held on the interval (docs/protocol.md tolerances).
    """
    x, u, w = ca.SX.sym("x", system.nx), ca.SX.sym("u", system.nu), ca.SX.sym("w", system.nx)
    p = ca.vertcat(u, w)
    integrator = ca.integrator(f"{system.name}_plant", "cvodes",
                               {"x": x, "p": p, "ode": system.f(x, u) + w}, 0.0, float(dt),
                               {"abstol": atol, "reltol": rtol, "max_num_steps": 100000})
    xs, us, ws = ca.MX.sym("x", system.nx), ca.MX.sym("u", system.nu), ca.MX.sym("w", system.nx)
    return ca.Function("plant_step", [xs, us, ws], [integrator(x0=xs, p=ca.vertcat(us, ws))["xf"]],
                       ["x", "u", "w"], ["x_next"])


@dataclass(frozen=True)
class NMPCStep:
    """One controller call: the input to apply and the solver's record.

    Attributes
    ----------
    u : numpy.ndarray, shape (nu,)
        The input to apply; on a failed solve the previous plan's next input (``fallback``).
    record : SolveRecord
    fallback : bool
    """

    u: np.ndarray
    record: SolveRecord
    fallback: bool


class NMPC:
    """Multiple-shooting NMPC for ``xdot = f(x, u)`` sampled every ``dt``.

    Parameters
    ----------
    system : System
    dt : float
        Sample period (the shooting interval).
    horizon : int
        Number of shooting intervals ``N``.
    Q : array_like, shape (nx,) or (nx, nx), optional
        State weight; default ``diag(10, 1, ..., 1)``.
    R : array_like, shape (nu,) or (nu, nu), optional
        Input weight; default ``0.1 I``.
    Qf : array_like, optional
        Terminal weight; default ``10 Q``.
    u_bounds : (array_like, array_like)
        ``(u_lo, u_hi)``, each scalar or (nu,); default ``(-2, 2)``.
    state_bounds : mapping, optional
        ``{i: (lo, hi)}`` soft bounds on state ``i`` (either side may be ``None``).
    slack_weights : (float, float)
        ``(rho1, rho2)``: exact L1 and quadratic penalties of the slacks.
    substeps : int
        RK4 steps per interval.
    max_iter : int
        ipopt iteration limit.
    ipopt : dict, optional
        More ipopt options.

    Attributes
    ----------
    solver : casadi.Function
        ``solver(x_init, x_ref, u_ref, margin, X0, U0, S0, lam_g0) -> (u0, X, U, S, lam_g)`` from
        ``Opti.to_function`` (``S`` is (n_soft, N + 1); with no soft bounds it has zero rows; ``margin``
        (n_soft,) tightens each soft bound, ``lo + margin <= x_i <= hi - margin``).
    phi : casadi.Function
        ``phi(x, u) -> x_next``, the prediction model.
    """

    def __init__(self, system: System, dt: float, horizon: int = 20, *, Q: Any = None, R: Any = None,
                 Qf: Any = None, u_bounds: tuple = (-2.0, 2.0),
                 state_bounds: Optional[Mapping[int, tuple]] = None,
                 slack_weights: tuple = (1e3, 1e4), substeps: int = 1, max_iter: int = 100,
                 ipopt: Optional[dict] = None) -> None:
        if not isinstance(system, System):
            raise TypeError(f"system: expected a kklcasadi.System, received "
                            f"{type(system).__name__}.")
        self.system = system
        self.dt = nonnegative_number(dt, "dt")
        if self.dt == 0:
            raise ValueError("dt: expected a sample period > 0, received 0.")
        self.horizon = positive_int(horizon, "horizon")
        nx, nu = system.nx, system.nu
        self.nx, self.nu = nx, nu
        self.Q = _weight(np.r_[10.0, np.ones(nx - 1)] if Q is None else Q, nx, "Q")
        self.R = _weight(0.1 * np.ones(nu) if R is None else R, nu, "R")
        self.Qf = 10.0 * self.Q if Qf is None else _weight(Qf, nx, "Qf")
        self.u_lo, self.u_hi = _bounds(u_bounds, nu)
        self.state_bounds = _state_bounds(state_bounds, nx)
        rho1, rho2 = (nonnegative_number(v, "slack_weights") for v in slack_weights)
        x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
        self.phi = ca.Function("phi", [x, u], [rk4_step(lambda _s, xx: system.f(xx, u), x, self.dt,
                                                        positive_int(substeps, "substeps"))],
                               ["x", "u"], ["x_next"])
        self.solver = self._build(rho1, rho2, positive_int(max_iter, "max_iter"), dict(ipopt or {}))
        self.reset()

    def _build(self, rho1: float, rho2: float, max_iter: int, extra: dict) -> ca.Function:
        nx, nu, N = self.nx, self.nu, self.horizon
        opti = ca.Opti()
        X, U = opti.variable(nx, N + 1), opti.variable(nu, N)
        n_soft = len(self.state_bounds)
        S = opti.variable(n_soft, N + 1)
        x_init, x_ref, u_ref = opti.parameter(nx), opti.parameter(nx), opti.parameter(nu)
        margin = opti.parameter(n_soft)
        dx, du = X - ca.repmat(x_ref, 1, N + 1), U - ca.repmat(u_ref, 1, N)
        cost = (ca.sum2(ca.sum1(dx[:, :N] * ca.mtimes(ca.DM(self.Q), dx[:, :N])))
                + ca.sum2(ca.sum1(du * ca.mtimes(ca.DM(self.R), du)))
                + ca.bilin(ca.DM(self.Qf), dx[:, N], dx[:, N]))
        opti.subject_to(X[:, 0] == x_init)
        opti.subject_to(X[:, 1:] == self.phi.map(N)(X[:, :N], U))
        opti.subject_to(opti.bounded(ca.repmat(ca.DM(self.u_lo), 1, N), U,
                                     ca.repmat(ca.DM(self.u_hi), 1, N)))
        if n_soft:
            cost = cost + rho1 * ca.sum2(ca.sum1(S)) + rho2 * ca.sumsqr(S)
            opti.subject_to(ca.vec(S) >= 0)
            for row, (i, (lo, hi)) in enumerate(self.state_bounds.items()):
                if hi is not None:
                    opti.subject_to(X[i, :] - S[row, :] <= hi - margin[row])
                if lo is not None:
                    opti.subject_to(X[i, :] + S[row, :] >= lo + margin[row])
        opti.minimize(cost)
        options = ipopt_options(max_iter, **{"warm_start_init_point": "yes",
                                             "mu_init": 1e-3, **extra})
        opti.solver("ipopt", options["plugin"], options["ipopt"])
        self._n_g = int(opti.ng)
        return opti.to_function("nmpc", [x_init, x_ref, u_ref, margin, X, U, S, opti.lam_g],
                                [U[:, 0], X, U, S, opti.lam_g],
                                ["x_init", "x_ref", "u_ref", "margin", "X0", "U0", "S0", "lam_g0"],
                                ["u0", "X", "U", "S", "lam_g"])

    def __repr__(self) -> str:
        return (f"NMPC(system={self.system.name!r}, horizon={self.horizon}, dt={self.dt}, "
                f"u_bounds=({self.u_lo.tolist()}, {self.u_hi.tolist()}), "
                f"state_bounds={self.state_bounds})")

    def reset(self) -> None:
        """Forget the warm start."""
        self._plan: Optional[tuple[np.ndarray, ...]] = None
        self._shifts = 0

    def solve(self, x_init: Any, x_ref: Any, u_ref: Any, *, margin: Any = None) -> NMPCStep:
        """Solve from ``x_init`` towards ``(x_ref, u_ref)``; warm-started from the last plan.

        Parameters
        ----------
        x_init : array_like, shape (nx,)
        x_ref : array_like, shape (nx,)
        u_ref : array_like, shape (nu,)
        margin : array_like, shape (n_soft,), optional
            By how much to tighten each soft state bound, in the order of :attr:`state_bounds`
            (``k sigma`` of the estimate: :func:`closed_loop`'s ``tighten``); default 0.

        Returns
        -------
        NMPCStep
            The first input of the plan, clipped to the bounds (ipopt may exceed them by its
            ``bound_relax_factor``). On a failed solve the previous plan's next input
            (``fallback`` True), or ``u_ref`` clipped to the bounds when there is no plan left.
        """
        x_init = self.system.check_state(x_init, "x_init")
        x_ref = self.system.check_state(x_ref, "x_ref")
        u_ref = _vector(u_ref, self.nu, "u_ref")
        n_soft = len(self.state_bounds)
        margin = np.zeros(n_soft) if margin is None else _vector(margin, n_soft, "margin")
        if np.any(margin < 0):
            raise ValueError(f"margin: expected tightenings >= 0, received {margin.tolist()}.")
        N = self.horizon
        if self._plan is None:
            X0 = np.repeat(x_init[:, None], N + 1, axis=1)
            U0 = np.repeat(np.clip(u_ref, self.u_lo, self.u_hi)[:, None], N, axis=1)
            S0 = np.zeros((len(self.state_bounds), N + 1))
            lam0 = np.zeros((self._n_g, 1))
        else:
            X, U, S, lam = self._plan
            X0 = np.hstack([X[:, 1:], X[:, -1:]])
            X0[:, 0] = x_init
            U0 = np.hstack([U[:, 1:], U[:, -1:]])
            S0 = np.hstack([S[:, 1:], S[:, -1:]])
            lam0 = lam
        outputs, record = solve_compiled(self.solver, [x_init, x_ref, u_ref, margin, X0, U0, S0, lam0])
        if record.success:
            self._plan = tuple(outputs[1:])
            self._shifts = 0
            # ipopt relaxes bounds by its bound_relax_factor (1e-8): apply the input clipped
            return NMPCStep(np.clip(outputs[0].ravel(), self.u_lo, self.u_hi), record, False)
        if self._plan is not None and self._shifts + 1 < N:
            self._shifts += 1
            X, U, S, lam = self._plan
            self._plan = (np.hstack([X[:, 1:], X[:, -1:]]), np.hstack([U[:, 1:], U[:, -1:]]),
                          np.hstack([S[:, 1:], S[:, -1:]]), lam)
            return NMPCStep(self._plan[1][:, 0].copy(), record, True)
        self.reset()
        return NMPCStep(np.clip(u_ref, self.u_lo, self.u_hi), record, True)


# ---------------------------------------------------------------------- estimators in the loop
class TrueState:
    """The full-information "estimator": returns the true state the loop passes in."""

    def __init__(self) -> None:
        self.x: Optional[np.ndarray] = None

    def make_step(self, y: Any, u: Any) -> np.ndarray:
        """Return the true state set by :func:`closed_loop` (``y`` and ``u`` unused)."""
        if self.x is None:
            raise ValueError("TrueState: no state was set; closed_loop sets it before each step.")
        return self.x.copy()


class EKFEstimator:
    """The shipped EKF (:class:`kklcasadi.estimators.ekf.EKF`) one sample at a time.

    ``make_step(y_k, u_k)``: the first call updates the prior (box centre, box variance) with
    ``y_0``; later calls predict over the last interval with the input stored by the previous
    call, then update with ``y_k``. Same convention as :class:`kklcasadi.observer.kkl.Estimator`.
    """

    def __init__(self, system: System, dt: float) -> None:
        self.ekf = EKF(system, dt)
        self.reset()

    def reset(self) -> None:
        self._x: Optional[np.ndarray] = None
        self._P: Optional[np.ndarray] = None
        self._u: Optional[np.ndarray] = None

    def make_step(self, y: Any, u: Any) -> np.ndarray:
        if self._x is None:
            x, P = self.ekf.x0, self.ekf.P0
        else:
            x, P = self.ekf.predict(self._x, self._P, self._u)
        x, P = self.ekf.update(x, P, np.atleast_1d(np.asarray(y, dtype=float)))
        self._x, self._P = np.asarray(x).ravel(), np.asarray(P)
        self._u = np.atleast_1d(np.asarray(u, dtype=float))
        return self._x.copy()

    @property
    def cov(self) -> Optional[np.ndarray]:
        """The filter's covariance (nx, nx) of the last estimate, or None before the first step."""
        return None if self._P is None else self._P.copy()


@dataclass(frozen=True, eq=False)
class ClosedLoop:
    """A closed-loop run.

    Attributes
    ----------
    t : numpy.ndarray, shape (N,)
    x, xhat : numpy.ndarray, shape (N, nx)
        True and estimated states.
    u : numpy.ndarray, shape (N, nu)
        Applied inputs (``u_k`` on ``[t_k, t_k+1)``).
    x_ref : numpy.ndarray, shape (N, nx)
    u_ref : numpy.ndarray, shape (N, nu)
    solve_time : numpy.ndarray, shape (N - 1,)
        Wall time of each controller solve (s).
    iterations : numpy.ndarray, shape (N - 1,)
    failed : numpy.ndarray of bool, shape (N - 1,)
        Solves that failed (the fallback input was applied).
    statuses : dict
        ``{return_status: count}``.
    Q, R : numpy.ndarray
        The controller's weights (for :attr:`cost`).
    state_bounds : dict
    """

    t: np.ndarray
    x: np.ndarray
    xhat: np.ndarray
    u: np.ndarray
    x_ref: np.ndarray
    u_ref: np.ndarray
    solve_time: np.ndarray
    iterations: np.ndarray
    failed: np.ndarray
    statuses: dict
    Q: np.ndarray
    R: np.ndarray
    state_bounds: dict

    @property
    def stage_cost(self) -> np.ndarray:
        """Stage cost of the true trajectory per sample, ``||x_k - x_ref_k||_Q^2 + ||u_k - u_ref_k||_R^2``, (N,)."""
        dx, du = self.x - self.x_ref, self.u - self.u_ref
        return (np.einsum("ki,ij,kj->k", dx, self.Q, dx)
                + np.einsum("ki,ij,kj->k", du, self.R, du))

    @property
    def cost(self) -> float:
        """Mean stage cost over the run."""
        return float(np.mean(self.stage_cost))

    @property
    def violation(self) -> np.ndarray:
        """Per sample, the largest amount by which a true state exceeds its bound (0 inside)."""
        v = np.zeros(self.t.size)
        for i, (lo, hi) in self.state_bounds.items():
            if hi is not None:
                v = np.maximum(v, self.x[:, i] - hi)
            if lo is not None:
                v = np.maximum(v, lo - self.x[:, i])
        return v

    @property
    def estimation_rmse(self) -> float:
        return float(np.sqrt(np.mean((self.x - self.xhat) ** 2)))


def closed_loop(controller: NMPC, estimator: Any, reference: Callable[[float], tuple], x0: Any,
                T: float, *, u0: Any = None, process_std: float = 0.1,
                measurement_std: float = 0.1, seed: int = 0,
                plant: Optional[ca.Function] = None, tighten: float = 0.0) -> ClosedLoop:
    """Simulate the NMPC in closed loop with an estimator, on the CVODES plant with noise.

    Parameters
    ----------
    controller : NMPC
        Its ``system`` is the plant; it is reset first.
    estimator : object with ``make_step(y, u) -> xhat``
        :meth:`kklcasadi.KKLObserver.estimator`, :class:`EKFEstimator` or :class:`TrueState`
        (fed the true state). A fresh one per run.
    reference : callable ``t -> (x_ref (nx,), u_ref (nu,))``
        Set point at time ``t`` (e.g. from :func:`steady_state`).
    x0 : array_like, shape (nx,)
        Initial plant state.
    T : float
        Duration; ``round(T / dt)`` samples.
    u0 : array_like, shape (nu,), optional
        Input on the first interval (before any estimate); default 0.
    process_std, measurement_std : float
        docs/protocol.md noise (process noise on ``xdot`` held per interval).
    seed : int
        Noise seed (the same seed gives the same noise to every estimator).
    plant : casadi.Function, optional
        ``(x, u, w) -> x_next``; default :func:`plant_step` of the controller's system.
    tighten : float
        ``k``: tighten each soft state bound by ``k`` standard deviations of the estimate at every
        sample, ``lo + k sigma_i <= x_i <= hi - k sigma_i`` (``sigma_i^2`` the estimator's ``cov[i, i]``:
        a learned observer's covariance head, ``obs.estimator()``); default 0, the bounds as given.

    Returns
    -------
    ClosedLoop
    """
    if not isinstance(controller, NMPC):
        raise TypeError(f"controller: expected an NMPC, received {type(controller).__name__}.")
    if not callable(getattr(estimator, "make_step", None)):
        raise TypeError(f"estimator: expected an object with make_step(y, u), received "
                        f"{type(estimator).__name__}.")
    k_sigma = nonnegative_number(tighten, "tighten")
    bounded = list(controller.state_bounds)
    if k_sigma > 0 and not hasattr(estimator, "cov"):
        raise ValueError(f"tighten: expected an estimator that reports its covariance (cov; a learned observer "
                         f"with a covariance head) for k = {k_sigma} > 0, received {type(estimator).__name__}.")
    system, dt = controller.system, controller.dt
    n = int(round(nonnegative_number(T, "T") / dt))
    if n < 2:
        raise ValueError(f"T: expected at least 2 samples of dt = {dt}, received T = {T}.")
    step = plant_step(system, dt) if plant is None else plant
    rng = np.random.default_rng(seed)
    w = nonnegative_number(process_std, "process_std") * rng.normal(size=(n - 1, system.nx))
    v = nonnegative_number(measurement_std, "measurement_std") * rng.normal(size=(n, system.ny))
    t = np.arange(n) * dt
    x = np.empty((n, system.nx))
    xhat = np.empty_like(x)
    u = np.empty((n, system.nu))
    refs = [reference(tk) for tk in t]
    x_ref = np.array([np.asarray(r[0], dtype=float).ravel() for r in refs])
    u_ref = np.array([np.asarray(r[1], dtype=float).ravel() for r in refs])
    x[0] = system.check_state(x0, "x0")
    u[0] = np.zeros(system.nu) if u0 is None else _vector(u0, system.nu, "u0")
    seconds, iterations = np.zeros(n - 1), np.zeros(n - 1, dtype=int)
    failed = np.zeros(n - 1, dtype=bool)
    statuses: dict = {}
    controller.reset()
    for k in range(n):
        y = np.asarray(system.h(x[k])).ravel() + v[k]
        if isinstance(estimator, TrueState):
            estimator.x = x[k]
        xhat[k] = estimator.make_step(y, u[k])
        if k + 1 == n:
            break
        x_pred = np.asarray(controller.phi(xhat[k], u[k])).ravel()
        margin = None
        if k_sigma > 0:
            cov = estimator.cov
            if cov is None:
                raise ValueError("tighten: expected an estimator with a covariance head, received one whose cov is "
                                 "None. Load a model with architecture.covariance.")
            margin = k_sigma * np.sqrt(np.diag(cov)[bounded])
        result = controller.solve(x_pred, x_ref[k + 1], u_ref[k + 1], margin=margin)
        u[k + 1] = result.u
        seconds[k], iterations[k] = result.record.seconds, result.record.iterations
        failed[k] = result.fallback
        statuses[result.record.status] = statuses.get(result.record.status, 0) + 1
        x[k + 1] = np.asarray(step(x[k], u[k], w[k])).ravel()
    return ClosedLoop(t, x, xhat, u, x_ref, u_ref, seconds, iterations, failed, statuses,
                      controller.Q, controller.R, dict(controller.state_bounds))


# ---------------------------------------------------------------------- checks
def _weight(value: Any, n: int, argument: str) -> np.ndarray:
    W = np.asarray(value, dtype=float)
    if W.shape == (n,):
        W = np.diag(W)
    if W.shape != (n, n):
        raise ValueError(f"{argument}: expected shape ({n},) or ({n}, {n}), received {W.shape}.")
    if not np.allclose(W, W.T) or np.min(np.linalg.eigvalsh(0.5 * (W + W.T))) < 0:
        raise ValueError(f"{argument}: expected a symmetric positive semi-definite weight, "
                         f"received {W.tolist()}.")
    return 0.5 * (W + W.T)


def _vector(value: Any, n: int, argument: str) -> np.ndarray:
    a = np.asarray(value, dtype=float)
    if a.shape not in ((n,), (n, 1)) and not (n == 1 and a.shape == ()):
        raise ValueError(f"{argument}: expected shape ({n},), received {a.shape}.")
    a = a.reshape(n)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{argument}: expected finite values, received {a.tolist()}.")
    return a


def _bounds(value: Any, nu: int) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise ValueError(f"u_bounds: expected a pair (u_lo, u_hi), received {value!r}.")
    lo = np.broadcast_to(np.asarray(value[0], dtype=float), (nu,)).copy()
    hi = np.broadcast_to(np.asarray(value[1], dtype=float), (nu,)).copy()
    if np.any(lo >= hi):
        raise ValueError(f"u_bounds: expected u_lo < u_hi, received {lo.tolist()} and "
                         f"{hi.tolist()}.")
    return lo, hi


def _state_bounds(value: Optional[Mapping[int, tuple]], nx: int) -> dict:
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise TypeError(f"state_bounds: expected a mapping {{index: (lo, hi)}}, received "
                        f"{type(value).__name__}.")
    out = {}
    for i, pair in value.items():
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < nx:
            raise ValueError(f"state_bounds: expected state indices in [0, {nx}), received {i!r}.")
        if not isinstance(pair, (tuple, list)) or len(pair) != 2 or pair == (None, None):
            raise ValueError(f"state_bounds[{i}]: expected (lo, hi) with at least one number, "
                             f"received {pair!r}.")
        lo, hi = (None if b is None else float(b) for b in pair)
        if lo is not None and hi is not None and lo >= hi:
            raise ValueError(f"state_bounds[{i}]: expected lo < hi, received ({lo}, {hi}).")
        out[int(i)] = (lo, hi)
    return out
