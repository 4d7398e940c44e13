"""Extended Kalman filter with exact CasADi Jacobians: the baseline a control engineer would pick.

The plant is discretised with RK4 over each sample interval (input held), and the state-transition
Jacobian is the exact derivative of that RK4 step (``casadi.jacobian``). docs/protocol.md settings:
``Q = (0.1 dt)^2 I``, ``R = 0.01``, started at the X0 box centre with the box's variance.
A whole trajectory is one ``mapaccum`` call and many trials one ``map`` over it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..plant.rk4 import rk4_step
from ..plant.systems import System
from ..validation import Text, error, nonnegative_number, positive_number

__all__ = ["EKF", "EKFEstimate", "NOISE_FLOOR"]

#: Smallest noise std :meth:`EKF.for_noise` uses (a zero level would make the filter singular).
NOISE_FLOOR = 1e-6


@dataclass(frozen=True, eq=False)
class EKFEstimate:
    """``t`` (N,), ``xhat`` (N, nx) or (M, N, nx), ``P`` diagonal variances with the same shape."""

    t: np.ndarray
    xhat: np.ndarray
    var: np.ndarray


class EKF:
    """Discrete-time EKF for ``xdot = f(x, u)``, ``y = h(x)`` sampled every ``dt``.

    Parameters
    ----------
    system : System
    dt : float
        Sample period.
    Q : array_like, shape (nx, nx), optional
        Process noise covariance per step; default ``(0.1 dt)^2 I`` (docs/protocol.md).
    R : array_like, shape (ny, ny), optional
        Measurement noise covariance; default ``0.01 I``.
    x0 : array_like, shape (nx,), optional
        Initial estimate; default the X0 box centre.
    P0 : array_like, shape (nx, nx), optional
        Initial covariance; default the variance of the uniform distribution on the box.
    substeps : int
        RK4 steps per sample interval.
    """

    def __init__(self, system: System, dt: float, *, Q: object = None, R: object = None, x0: object = None,
                 P0: object = None, substeps: int = 1) -> None:
        if not isinstance(system, System):
            raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
        dt = positive_number(dt, "dt")
        nx, ny = system.nx, system.ny
        width = system.x0_box[:, 1] - system.x0_box[:, 0]
        self.system = system
        self.dt = dt
        self.Q = self._matrix(np.eye(nx) * (0.1 * dt) ** 2 if Q is None else Q, (nx, nx), "Q")
        self.R = self._matrix(0.01 * np.eye(ny) if R is None else R, (ny, ny), "R")
        self.x0 = system.x0_box.mean(axis=1) if x0 is None else system.check_state(x0, "x0")
        self.P0 = self._matrix(np.diag(width ** 2 / 12.0) if P0 is None else P0, (nx, nx), "P0")

        x = ca.SX.sym("x", nx)
        u = ca.SX.sym("u", system.nu)
        x_next = rk4_step(lambda _s, xx: system.f(xx, u), x, self.dt, substeps)
        P = ca.SX.sym("P", nx, nx)
        y = ca.SX.sym("y", ny)
        # measurement update with y at the current estimate
        H = system.h_jac(x)
        S = ca.mtimes([H, P, H.T]) + ca.DM(self.R)
        K = ca.mtimes([P, H.T, ca.inv(S)])
        x_upd = x + ca.mtimes(K, y - system.h(x))
        I_KH = ca.DM.eye(nx) - ca.mtimes(K, H)
        P_upd = ca.mtimes([I_KH, P, I_KH.T]) + ca.mtimes([K, ca.DM(self.R), K.T])   # Joseph form
        self.update = ca.Function("ekf_update", [x, P, y], [x_upd, P_upd], ["x", "P", "y"], ["x_upd", "P_upd"])
        # time update over one interval with u held
        F = ca.jacobian(x_next, x)
        P_pred = ca.mtimes([F, P, F.T]) + ca.DM(self.Q)
        self.predict = ca.Function("ekf_predict", [x, P, u], [x_next, P_pred], ["x", "P", "u"],
                                   ["x_pred", "P_pred"])
        # one full step: predict with u_k, then update with y_k+1; state packs [x; vec(P)]
        xs = ca.MX.sym("s", nx + nx * nx)
        uk = ca.MX.sym("u", system.nu)
        yk1 = ca.MX.sym("y", ny)
        xp, Pp = self.predict(xs[:nx], ca.reshape(xs[nx:], nx, nx), uk)
        xu, Pu = self.update(xp, Pp, yk1)
        self.step = ca.Function("ekf_step", [xs, ca.vertcat(uk, yk1)], [ca.vertcat(xu, ca.vec(Pu))],
                                ["s", "uy"], ["s_next"])

    @classmethod
    def for_noise(cls, system: System, dt: float, *, process_std: float, measurement_std: float,
                  **options: object) -> EKF:
        """The EKF tuned for the simulator's noise model (``kklcasadi.simulate``).

        ``Q = (process_std dt)^2 I`` (noise of std ``process_std`` on every ``xdot``, held over a
        sample) and ``R = measurement_std^2 I``; a level of 0 is floored at :data:`NOISE_FLOOR` so
        that the filter stays well defined on noise-free data. ``EKF(system, dt)`` is the
        protocol's 0.1 and 0.1.

        Parameters
        ----------
        system : System
        dt : float
        process_std, measurement_std : float
            Noise levels, >= 0.
        **options
            ``x0``, ``P0``, ``substeps`` of :class:`EKF`.
        """
        q = max(nonnegative_number(process_std, "process_std"), NOISE_FLOOR)
        r = max(nonnegative_number(measurement_std, "measurement_std"), NOISE_FLOOR)
        dt = positive_number(dt, "dt")
        return cls(system, dt, Q=(q * dt) ** 2 * np.eye(system.nx), R=r ** 2 * np.eye(system.ny), **options)

    @staticmethod
    def _matrix(value: object, shape: tuple[int, int], arg: str) -> np.ndarray:
        m = np.atleast_2d(np.asarray(value, dtype=float))
        if m.shape != shape:
            raise error(arg, f"shape {shape}", Text(f"shape {m.shape}"))
        if not np.allclose(m, m.T) or np.min(np.linalg.eigvalsh(m)) < 0:
            raise error(arg, "a symmetric positive semi-definite matrix", m.tolist())
        return m

    def simulate(self, t: object, y: object, u: object, *, n_threads: int | None = None) -> EKFEstimate:
        """Filter one or many measured trajectories.

        Parameters
        ----------
        t : array_like, shape (N,)
            Sample times, spaced by ``dt``.
        y : array_like, shape (N, ny) or (M, N, ny)
        u : array_like, shape (N, nu) or (M, N, nu)

        Returns
        -------
        EKFEstimate
            ``xhat`` with shape (N, nx) or (M, N, nx): the filtered estimate after ``y_k``.
        """
        t = np.asarray(t, dtype=float)
        y = np.asarray(y, dtype=float)
        u = np.asarray(u, dtype=float)
        single = y.ndim == 2
        if single:
            y, u = y[None], u[None]
        nx, ny, nu = self.system.nx, self.system.ny, self.system.nu
        if y.ndim != 3 or y.shape[2] != ny or y.shape[1] != t.size:
            raise error("y", f"shape (N, ny) or (M, N, ny) with N = {t.size}, ny = {ny}", Text(f"shape {y.shape}"))
        if u.shape != y.shape[:2] + (nu,):
            raise error("u", f"shape {y.shape[:2] + (nu,)}", Text(f"shape {u.shape}"))
        spacing = np.diff(t)
        if spacing.size and not np.allclose(spacing, self.dt, rtol=1e-9, atol=1e-12):
            raise error("t", f"samples spaced by dt = {self.dt}",
                        Text(f"spacings from {spacing.min():.6g} to {spacing.max():.6g}"))
        bad = np.argwhere(~np.isfinite(y))
        if bad.size:
            raise error("y", "finite values", Text(f"NaN or inf at trial {bad[0, 0]}, sample {bad[0, 1]}"))
        m, n = y.shape[:2]
        x0, P0 = (np.asarray(a) for a in self.update.map(m)(np.tile(self.x0[:, None], (1, m)),
                                                             np.tile(self.P0, (1, m)), y[:, 0].T))
        P0 = P0.reshape(nx, m, nx).transpose(1, 0, 2)                      # (M, nx, nx)
        s0 = np.vstack([x0, P0.transpose(0, 2, 1).reshape(m, nx * nx).T])  # column-major vec(P) per trial
        uy = np.concatenate([u[:, :-1], y[:, 1:]], axis=2)                 # (M, N-1, nu+ny)
        traj = self.step.mapaccum("ekf_traj", n - 1)
        threads = n_threads or os.cpu_count() or 1
        out = np.asarray(traj.map(m, "thread", min(threads, m))(s0, uy.reshape(m * (n - 1), -1).T))
        out = out.T.reshape(m, n - 1, nx + nx * nx)
        xhat = np.concatenate([x0.T[:, None, :], out[:, :, :nx]], axis=1)
        diag_idx = np.arange(nx) * (nx + 1)
        var = np.concatenate([np.diagonal(P0, axis1=1, axis2=2)[:, None, :], out[:, :, nx + diag_idx]], axis=1)
        if single:
            return EKFEstimate(t, xhat[0], var[0])
        return EKFEstimate(t, xhat, var)
