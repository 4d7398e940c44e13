"""Extended Kalman filter with exact CasADi Jacobians: the baseline a control engineer would pick.

The plant is discretised with RK4 over each sample interval (input held), and the state-transition
Jacobian is the exact derivative of that RK4 step (``casadi.jacobian``). docs/protocol.md settings:
``Q = (0.1 dt)^2 I``, ``R = 0.01``, started at the X0 box centre with the box's variance.
A whole trajectory is one ``mapaccum`` call and many trials one ``map`` over it; :meth:`EKF.generate_c`
writes the filter step as C (CasADi's code generation and the kernels of :mod:`kklcasadi.observer.codegen`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import casadi as ca
import numpy as np

from ..estimate import Estimate, check_sample
from ..observer.codegen import DEFAULT_FLAGS, c_targets, casadi_source, check_c_name, check_flags, renamed
from ..plant.rk4 import rk4_step, stable_substeps
from ..plant.systems import System
from ..validation import Text, covariance, error, nonnegative_number, one_of, positive_int, positive_number, state_stds
from ..writes import write_dir

__all__ = ["EKF", "EKFEstimator", "EKFEstimate", "NOISE_FLOOR", "EKF_FORMS", "noise_covariances"]

#: Smallest noise std :meth:`EKF.for_noise` uses (a zero level would make the filter singular).
NOISE_FLOOR = 1e-6
#: Forms of the EKF step (:meth:`EKF.step_of`, :meth:`EKF.generate_c`).
EKF_FORMS = ("sx", "dense")


#: The EKF's result is the one :class:`kklcasadi.estimate.Estimate` (``t``, ``xhat``, ``var``); the name stays.
EKFEstimate = Estimate


def noise_covariances(system: System, dt: float, *, process_std: float | Sequence[float],
                      measurement_std: float) -> tuple[np.ndarray, np.ndarray]:
    """``Q = diag(process_std dt)^2`` (nx, nx) and ``R = measurement_std^2 I`` (ny, ny) of the simulator's
    noise model, each std floored at :data:`NOISE_FLOOR` (see :meth:`EKF.for_noise`)."""
    q = np.maximum(state_stds(process_std, system.nx), NOISE_FLOOR) * np.ones(system.nx)
    r = max(nonnegative_number(measurement_std, "measurement_std"), NOISE_FLOOR)
    dt = positive_number(dt, "dt")
    return np.diag((q * dt) ** 2), r ** 2 * np.eye(system.ny)


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
    substeps : int or "auto"
        RK4 steps per sample interval; ``"auto"`` (default): the fewest that keep RK4 stable over the
        plant's box (:func:`kklcasadi.plant.rk4.stable_substeps`: 1 on Duffing, Van der Pol and
        Roessler at dt = 0.05, 5 on FitzHugh-Nagumo, whose fast mode one RK4 step amplifies near the
        box's edges). The number taken is :attr:`substeps`.
    params : array_like, shape (n_params,), optional
        The parameter values of the filter's model, for a plant with parameters; default the
        nominal ones (:meth:`kklcasadi.System.at`).

    Attributes
    ----------
    substeps : int
        The RK4 steps per interval the filter runs.
    """

    def __init__(self, system: System, dt: float, *, Q: object = None, R: object = None, x0: object = None,
                 P0: object = None, substeps: int | str = "auto", params: object = None) -> None:
        if not isinstance(system, System):
            raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
        if params is not None:
            system = system.at(params)
        dt = positive_number(dt, "dt")
        nx, ny = system.nx, system.ny
        width = system.x0_box[:, 1] - system.x0_box[:, 0]
        self.system = system
        self.dt = dt
        self.Q = covariance(np.eye(nx) * (0.1 * dt) ** 2 if Q is None else Q, nx, "Q")
        self.R = covariance(0.01 * np.eye(ny) if R is None else R, ny, "R")
        self.x0 = system.x0_box.mean(axis=1) if x0 is None else system.check_state(x0, "x0")
        self.P0 = covariance(np.diag(width ** 2 / 12.0) if P0 is None else P0, nx, "P0")
        if isinstance(substeps, str):
            if substeps != "auto":
                raise error("substeps", 'a positive int or "auto"', substeps)
            substeps = stable_substeps(system, dt)
        self.substeps = positive_int(substeps, "substeps")

        x = ca.SX.sym("x", nx)
        u = ca.SX.sym("u", system.nu)
        x_next = rk4_step(lambda _s, xx: system.f(xx, u), x, self.dt, self.substeps)
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
        # the start: the update of the prior (x0, P0) with y_0, packed as the step's state
        y0 = ca.MX.sym("y0", ny)
        xs0, Ps0 = self.update(ca.DM(self.x0), ca.DM(self.P0), y0)
        self.start = ca.Function("ekf_start", [y0], [ca.vertcat(xs0, ca.vec(Ps0))], ["y0"], ["s0"])
        # the same step with the covariance algebra as dense matrix products (see generate_c's form)
        self._rk4 = ca.Function("ekf_rk4", [x, u], [x_next, ca.densify(F)], ["x", "u"], ["x_next", "F"])
        self._measure = ca.Function("ekf_measure", [x], [system.h(x), ca.densify(H)], ["x"], ["y", "H"])

    def _dense_step(self) -> ca.Function:
        """:attr:`step` with ``P`` propagated and updated by dense matrix products (MX ``mtimes``, which the
        C code makes axpy kernels): the same filter, summed in another order."""
        nx, ny, nu = self.system.nx, self.system.ny, self.system.nu
        s, uy = ca.MX.sym("s", nx + nx * nx), ca.MX.sym("uy", nu + ny)
        x_pred, F = self._rk4(s[:nx], uy[:nu])
        P_pred = ca.mtimes(ca.mtimes(F, ca.reshape(s[nx:], nx, nx)), F.T) + ca.DM(self.Q)
        h, H = self._measure(x_pred)
        PHt = ca.mtimes(P_pred, H.T)
        K = ca.mtimes(PHt, ca.inv(ca.mtimes(H, PHt) + ca.DM(self.R)))
        I_KH = ca.DM.eye(nx) - ca.mtimes(K, H)
        P_upd = ca.mtimes(ca.mtimes(I_KH, P_pred), I_KH.T) + ca.mtimes(ca.mtimes(K, ca.DM(self.R)), K.T)
        x_upd = x_pred + ca.mtimes(K, uy[nu:] - h)
        return ca.Function("ekf_step_dense", [s, uy], [ca.vertcat(x_upd, ca.vec(P_upd))], ["s", "uy"], ["s_next"])

    def step_of(self, form: str = "sx") -> ca.Function:
        """The filter step ``(s, uy) -> s_next`` (see :meth:`generate_c`) in ``form``.

        ``"sx"``: :attr:`step`, the one :meth:`simulate` runs (CasADi SX scalar code: sparse
        Jacobians exploited, one straight-line C function); ``"dense"``: the covariance algebra as
        dense matrix products, about ``4 nx^3`` multiply-adds in short loops, equal to :attr:`step`
        to rounding (the summation order differs).
        """
        return self.step if one_of(form, "form", EKF_FORMS) == "sx" else self._dense_step()

    @classmethod
    def for_noise(cls, system: System, dt: float, *, process_std: float | Sequence[float],
                  measurement_std: float, **options: Any) -> EKF:
        """The EKF tuned for the simulator's noise model (``kklcasadi.simulate``).

        ``Q = diag(process_std dt)^2`` (noise of std ``process_std`` on every ``xdot``, or one std
        per state, held over a sample) and ``R = measurement_std^2 I``; a level of 0 is floored at
        :data:`NOISE_FLOOR` so that the filter stays well defined on noise-free data. ``EKF(system, dt)`` is the
        protocol's 0.1 and 0.1.

        Parameters
        ----------
        system : System
        dt : float
        process_std : float or sequence of float (nx,)
            Process-noise std, >= 0: one for every state or one per state.
        measurement_std : float
            Measurement-noise std, >= 0.
        **options
            ``x0``, ``P0``, ``substeps``, ``params`` of :class:`EKF`.
        """
        Q, R = noise_covariances(system, dt, process_std=process_std, measurement_std=measurement_std)
        return cls(system, dt, Q=Q, R=R, **options)

    def generate_c(self, out_dir: Union[str, os.PathLike], name: str = "ekf", *, form: str = "sx",
                   overwrite: bool = False, matvec: str = "axpy", math: str = "vector", dispatch: bool = True,
                   flags: Sequence[str] = DEFAULT_FLAGS) -> list[Path]:
        """Write the filter step as C99: ``name.c`` and ``name.h``.

        The code is CasADi's code generation of :meth:`step_of` ``(form)`` and :attr:`start` with
        the rewrites of :func:`kklcasadi.generate_c` (its ``matvec``, ``math``, ``dispatch`` and
        ``flags`` mean the same here): with ``math="libm"`` the C step is bitwise the CasADi VM's
        of that form, with the default ``"vector"`` within
        :data:`kklcasadi.observer.codegen.VECTOR_MATH_TOLERANCE` (the same where the plant has no
        ``exp``/``tanh``). No dynamic allocation. ``form="sx"`` (default) is the step
        :meth:`simulate` runs, one straight-line function: the fewest operations, but its source
        grows faster than ``nx^2`` (1.2 MB at nx = 32, where ``gcc -O3`` takes over a minute and
        ``-O1`` 8 s); ``"dense"`` is a few loops at every size (the axpy kernels), 2.4x faster at
        nx = 64 (``kklcasadi bench scaling``).

        ``name_start(arg: y_0) -> res: s_0`` and ``name_step(arg: s_k, uy_k) -> res: s_k+1``, with the
        state ``s = [xhat (NX); vec(P) (NX*NX, column-major)]`` and ``uy_k = [u_k; y_k+1]``: the
        prediction over one sample with ``u_k`` held, then the update with ``y_k+1``; the estimate
        after ``y_k`` is ``s_k[0..NX-1]``, as :meth:`simulate` gives it.

        Parameters
        ----------
        out_dir : path
            Output directory; created if missing.
        name : str
            Prefix of the files, C symbols and macros (``NAME_NX``, ``NAME_NS``, ``NAME_SZ_W``, ...).
        overwrite : bool
            Replace existing files of the same names.

        Returns
        -------
        list of Path
            ``[name.c, name.h]``.
        """
        name = check_c_name(name)
        flags = check_flags(flags)
        out, paths = c_targets(out_dir, [f"{name}.c", f"{name}.h"], overwrite)
        functions = [renamed(self.step_of(form), f"{name}_step"), renamed(self.start, f"{name}_start")]
        source, casadi_header, sizes = casadi_source(functions, name, matvec=matvec, math=math, dispatch=dispatch)
        nx, macro = self.system.nx, name.upper()
        defines = {"NX": nx, "NU": self.system.nu, "NY": self.system.ny, "NS": nx + nx * nx, **sizes}
        lines = "\n".join(f"#define {macro}_{key} {value}" for key, value in defines.items())
        header = f"""/* {name}.h -- extended Kalman filter step generated by kklcasadi (kklcasadi.estimators.ekf).
 *
 * Plant {self.system.name!r}, sample period {self.dt!r} s, RK4 prediction with the input held, exact
 * Jacobians, Joseph-form update.
 *
 * {name}_start(arg, res, iw, w, mem): arg[0] y_0 (NY) -> res[0] s_0 (NS), the prior updated with y_0.
 * {name}_step(arg, res, iw, w, mem): arg[0] s_k (NS), arg[1] [u_k; y_k+1] (NU + NY) -> res[0] s_k+1 (NS).
 * s = [xhat (NX); P (NX x NX, column-major)]: the estimate after y_k is s_k[0..NX-1].
 * Work arrays: arg[{macro}_SZ_ARG], res[{macro}_SZ_RES], iw[{macro}_SZ_IW], w[{macro}_SZ_W]; outputs
 * must not alias inputs; mem = 0.
 * Build: gcc {' '.join(flags)} -c {name}.c
 */
#ifndef {macro}_H
#define {macro}_H

{lines}
#define {macro}_DT {self.dt!r}

{casadi_header.strip()}

#endif /* {macro}_H */
"""
        write_dir(out, {paths[0].name: f"/* {name}.c -- extended Kalman filter step generated by kklcasadi; see "
                                       f"{name}.h. */\n{source}", paths[1].name: header},
                  overwrite=overwrite, argument="out_dir")
        return paths

    def simulate(self, t: object, y: object, u: object, *, n_threads: int | None = None) -> Estimate:
        """Filter one or many measured trajectories.

        Parameters
        ----------
        t : array_like, shape (N,)
            Sample times, spaced by ``dt``.
        y : array_like, shape (N, ny) or (M, N, ny)
        u : array_like, shape (N, nu) or (M, N, nu)

        Returns
        -------
        Estimate
            ``xhat`` with shape (N, nx) or (M, N, nx): the filtered estimate after ``y_k``; ``var`` the
            diagonal of ``P`` there.
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
            return Estimate(t, xhat[0], var=var[0])
        return Estimate(t, xhat, var=var)

    def estimator(self) -> EKFEstimator:
        """The filter one sample at a time: ``xhat = est.make_step(y, u)`` (an :class:`EKFEstimator`)."""
        return EKFEstimator(self)


class EKFEstimator:
    """Stateful form of an :class:`EKF`, for loops that receive one sample at a time (a
    :class:`kklcasadi.estimate.StepEstimator`).

    ``make_step(y_k, u_k)``: the first call updates the prior ``(x0, P0)`` with ``y_0``; later calls
    predict over the last interval with the input the previous call was given, then update with
    ``y_k``: the estimates of :meth:`EKF.simulate`, sample by sample (bitwise: the same predict and
    update Functions on the same numbers).

    Parameters
    ----------
    ekf : EKF

    Attributes
    ----------
    ekf : EKF
    k : int
        Samples taken since the start or the last :meth:`reset`.
    """

    def __init__(self, ekf: EKF) -> None:
        if not isinstance(ekf, EKF):
            raise error("ekf", "a kklcasadi.EKF", Text(type(ekf).__name__), kind=TypeError)
        self.ekf = ekf
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next :meth:`make_step` starts again from the prior."""
        self._x: Optional[np.ndarray] = None
        self._P: Optional[np.ndarray] = None
        self._u: Optional[np.ndarray] = None
        self.k = 0

    @property
    def P(self) -> Optional[np.ndarray]:
        """The covariance ``P_k`` (nx, nx) after the last step, or None before the first."""
        return None if self._P is None else self._P.copy()

    @property
    def cov(self) -> Optional[np.ndarray]:
        """The covariance of the last estimate's error (nx, nx): :attr:`P` (what
        :func:`kklcasadi.estimators.nmpc.closed_loop` tightens its bounds by)."""
        return self.P

    def make_step(self, y: object, u: object) -> np.ndarray:
        """Feed ``y_k`` and ``u_k`` (the input held from ``t_k``); return the estimate ``xhat_k`` (nx,)."""
        ekf = self.ekf
        y = check_sample(y, "y", ekf.system.ny, self.k)
        u = check_sample(u, "u", ekf.system.nu, self.k)
        x: Any
        P: Any
        if self._x is None:
            x, P = ekf.x0, ekf.P0
        else:
            x, P = ekf.predict(self._x, self._P, self._u)
        x, P = ekf.update(x, P, y)
        self._x, self._P, self._u = np.asarray(x).ravel(), np.asarray(P), u
        self.k += 1
        return self._x.copy()

    @property
    def stats(self) -> dict:
        """``k`` (samples taken) and ``var`` (the diagonal of ``P_k``, None before the first step)."""
        return {"k": self.k, "var": None if self._P is None else np.diag(self._P).copy()}
