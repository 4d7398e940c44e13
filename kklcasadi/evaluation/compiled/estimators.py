"""Estimators as compiled trajectories mapped over trials: the fast path of the benchmarks.

:class:`CompiledEstimator` is the estimator protocol of the fast benchmark path: an estimator
that gives one trial's estimate as a CasADi Function ``(y (ny, N), u (nu, N), s0) -> xhat (nx, N)``
and its initial state ``s0``; calling it compiles that Function and maps it over the trials on
threads. :func:`observer_estimator` and :func:`ekf_estimator` adapt a
:class:`~kklcasadi.observer.kkl.KKLObserver` and an :class:`~kklcasadi.estimators.ekf.EKF`;
each is bitwise its reference path (``obs.simulate``, ``ekf.simulate``).
"""

from __future__ import annotations

import hashlib
import os
import time
from abc import ABC, abstractmethod
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, Callable, Optional, Sequence

import casadi as ca
import numpy as np

from ...compiler import Compiler, c_name, children_cpu, code_digest
from ...model.variants.inflation import fold
from ..protocol import Profile, phase
from .shortcuts import reuse_decoded, skip_at_zero_input, split_step

if TYPE_CHECKING:
    from ...estimators.ekf import EKF
    from ...estimators.pf import ParticleFilter
    from ...observer.kkl import KKLObserver

__all__ = ["CompiledEstimator", "CompiledObserver", "CompiledEKF", "CompiledRecord", "observer_estimator",
           "ekf_estimator", "pf_estimator", "precompile", "GROUP"]

#: Default largest group of trials with the same inputs that one trajectory runs together.
GROUP = 2


class CompiledEstimator(ABC):
    """An estimator that runs each trial through one CasADi Function, compiled, mapped over trials.

    Subclasses give :meth:`trajectory`: one trial of ``n`` samples,
    ``(y (ny, n), u (nu, n), s0 (ns, 1)) -> xhat (nx, n)``, ``u_k`` held over ``[t_k, t_k+1)``,
    started from the estimator's :meth:`initial_state` ``s0``. Calling the estimator compiles that
    Function (once per ``n``) and maps it over the trials on threads. It is an
    :data:`kklcasadi.evaluation.protocol.BatchEstimator`.

    An estimator whose :attr:`shares_inputs` is True also gives the trajectory of a group of ``K``
    trials with the same inputs (``y (ny, K n)``, column ``k K + j`` the sample ``k`` of trial ``j``,
    ``u (nu, n)``), which does the work that depends on the inputs alone once for the group; a call
    groups its trials by their inputs (bitwise equal rows of ``u``), at most :attr:`group` per group.

    Parameters
    ----------
    nx, nu, ny : int
        Sizes of the plant.
    dt : float
        Sample period the estimator runs at.
    compiler : Compiler or None
        How to compile; None runs the CasADi VM (the reference path).
    n_threads : int, optional
        Worker threads over trials (default: the CPU count).
    group : int
        Largest group of trials with the same inputs run together (default :data:`GROUP`).
    profile : Profile, optional
        Where to record the time spent compiling (:class:`kklcasadi.evaluation.protocol.Profile`).
    """

    #: Whether trials with the same inputs share work (see :meth:`trajectory`).
    shares_inputs: bool = False

    def __init__(self, nx: int, nu: int, ny: int, dt: float, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None, group: int = GROUP, profile: Optional[Profile] = None) -> None:
        if compiler is not None and not isinstance(compiler, Compiler):
            raise TypeError(f"compiler: expected a kklcasadi.evaluation.compiled.Compiler or None, received "
                            f"{type(compiler).__name__}.")
        for name, value in (("n_threads", n_threads), ("group", group)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ValueError(f"{name}: expected a positive int{' or None' if name == 'n_threads' else ''}, "
                                 f"received {value!r}.")
        self.nx, self.nu, self.ny, self.dt = nx, nu, ny, float(dt)
        self.compiler = compiler
        self.n_threads = n_threads
        self.group = group
        self.profile = profile
        self._functions: dict[tuple[int, int], ca.Function] = {}

    @abstractmethod
    def trajectory(self, n: int, group: int = 1) -> ca.Function:
        """``group`` trials with the same inputs over ``n`` >= 2 samples (VM):
        ``(y (ny, group n), u (nu, n), s0 (ns, 1)) -> xhat (nx, group n)``, column ``k group + j``."""

    @abstractmethod
    def initial_state(self) -> np.ndarray:
        """The ``s0`` (ns,) every trial starts from."""

    def identity(self, n: int, group: int = 1) -> Optional[str]:
        """A string that determines :meth:`trajectory` ``(n, group)`` completely, with which a warm library cache
        skips building it (:meth:`Compiler.build_known`); None (this default): build it every time."""
        return None

    def function(self, n: int, group: int = 1) -> ca.Function:
        """:meth:`trajectory` as it runs: compiled (cached per ``n`` and ``group``), or the VM Function."""
        if (n, group) not in self._functions:
            children = os.times()
            with phase(self.profile, "compile"):
                if self.compiler is None or not self.compiler.available():
                    f = self.trajectory(n, group)       # the VM (a missing compiler says so)
                    self._functions[n, group] = f if self.compiler is None else self.compiler.compile(f)
                else:
                    self._functions[n, group] = self.compiler.build_known(
                        self.identity(n, group), lambda: self.trajectory(n, group)).load()
            if self.profile is not None:
                self.profile.add("compile", 0.0, children_cpu(children))
        return self._functions[n, group]

    def __call__(self, t: Any, y: Any, u: Any) -> np.ndarray:
        """Estimate M trials.

        Parameters
        ----------
        t : array_like, shape (N,)
            Sample times spaced by :attr:`dt`, N >= 2.
        y : array_like, shape (M, N, ny)
        u : array_like, shape (M, N, nu)

        Returns
        -------
        numpy.ndarray, shape (M, N, nx)
        """
        t, y, u = self._check(t, y, u)
        m, n = y.shape[:2]
        xhat = np.empty((m, n, self.nx))
        threads = self.n_threads or os.cpu_count() or 1
        for indices in self._grouped(u):                      # (G, K): G groups of K trials, same inputs
            g, k = indices.shape
            mapped = self.function(n, k).map(g, "thread", min(threads, g))
            out = mapped(y[indices].transpose(3, 0, 2, 1).reshape(self.ny, g * n * k),
                         u[indices[:, 0]].transpose(2, 0, 1).reshape(self.nu, g * n), self.initial_state())
            xhat[indices] = np.asarray(out).reshape(self.nx, g, n, k).transpose(1, 3, 2, 0)
        return xhat

    def _grouped(self, u: np.ndarray) -> list[np.ndarray]:
        """The trials as index arrays (G, K) per group size K: groups of at most :attr:`group` trials
        whose inputs are bitwise equal (one array of (M, 1) without :attr:`shares_inputs`)."""
        m = u.shape[0]
        if not self.shares_inputs or self.group == 1 or m == 0:
            return [np.arange(m)[:, None]] if m else []
        bits = np.ascontiguousarray(u).reshape(m, -1).view(np.uint64)
        _, first, inverse = np.unique(bits, axis=0, return_index=True, return_inverse=True)
        by_size: dict[int, list[np.ndarray]] = {}
        for label in np.argsort(first):                        # in the order of the trials
            members = np.flatnonzero(inverse.ravel() == label)
            for start in range(0, members.size, self.group):
                chunk = members[start:start + self.group]
                by_size.setdefault(chunk.size, []).append(chunk)
        return [np.array(chunks) for _, chunks in sorted(by_size.items())]

    def _check(self, t: Any, y: Any, u: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        if t.ndim != 1 or t.size < 2:
            raise ValueError(f"t: expected sample times of shape (N,) with N >= 2, received shape {t.shape}.")
        steps = np.diff(t)
        if not np.allclose(steps, self.dt, rtol=1e-9, atol=1e-12 * max(1.0, abs(t[-1]))):
            k = int(np.argmax(np.abs(steps - self.dt)))
            raise ValueError(f"t: expected samples spaced by dt = {self.dt}, received t[{k + 1}] - t[{k}] = "
                             f"{steps[k]}.")
        n = t.size
        y = np.asarray(y, dtype=float)
        u = np.asarray(u, dtype=float)
        if y.ndim != 3 or y.shape[1:] != (n, self.ny):
            raise ValueError(f"y: expected shape (M, {n}, {self.ny}), received {y.shape}.")
        if u.shape != (y.shape[0], n, self.nu):
            raise ValueError(f"u: expected shape ({y.shape[0]}, {n}, {self.nu}), received {u.shape}.")
        for name, values in (("y", y), ("u", u)):
            bad = np.argwhere(~np.isfinite(values))
            if bad.size:
                raise ValueError(f"{name}: expected finite values, received {values[tuple(bad[0])]} at trial "
                                 f"{bad[0, 0]}, sample {bad[0, 1]}.")
        return t, y, u


class CompiledObserver(CompiledEstimator):
    """A :class:`~kklcasadi.observer.kkl.KKLObserver` as a :class:`CompiledEstimator`.

    The trajectory is the observer's own Functions: ``s0 = z_0 = 0`` (docs/protocol.md), the
    memory ``w_0 = memory_init(y_0, u_0)``, ``xhat_0 = decode(z_0, w_0)``, then ``step`` folded with
    ``mapaccum``; bitwise :meth:`KKLObserver.simulate`. The step skips the model-based injection
    where the input is 0 (:func:`skip_at_zero_input`), and where the memory does work of its own
    (:func:`split_step`) that work is done once per group of trials with the same inputs and
    reused while the memory and the next input repeat those of the previous sample.

    Parameters
    ----------
    observer : KKLObserver
    compiler, n_threads, group, profile
        See :class:`CompiledEstimator`.
    shortcuts : bool
        False: the step as it is folded over the samples, trial by trial (1000 steps of the
        observer step per protocol trial: the per-step cost the shortcuts are measured against).
    """

    def __init__(self, observer: KKLObserver, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None, group: int = GROUP, profile: Optional[Profile] = None,
                 shortcuts: bool = True) -> None:
        from ...observer.kkl import KKLObserver

        if not isinstance(observer, KKLObserver):
            raise TypeError(f"observer: expected a kklcasadi.KKLObserver, received {type(observer).__name__}.")
        super().__init__(observer.nx, observer.nu, observer.ny, observer.dt, compiler=compiler,
                         n_threads=n_threads, group=group, profile=profile)
        self.observer = observer
        self.shortcuts = bool(shortcuts)
        step, self.carries = observer.step, False
        injection = observer.model_injection
        if shortcuts and injection is not None:
            reused = reuse_decoded(step, injection, observer.decode)
            if reused is not None:
                step, of_xhat = reused
                step, self.carries = skip_at_zero_input(step, of_xhat), True
            step = skip_at_zero_input(step, injection)
        self.step = step
        y0 = observer.memory_init.sparsity_jac(0, 0).nnz() > 0        # the first memory reads y_0
        self.split = None if y0 or not shortcuts else split_step(step)
        self.shares_inputs = self.split is not None

    def trajectory(self, n: int, group: int = 1) -> ca.Function:
        obs = self.observer
        if group != 1 and self.split is None:
            raise ValueError(f"group: expected 1 for an observer whose trials share no work, received {group!r}.")
        y, u, z0 = ca.MX.sym("y", obs.ny, group * n), ca.MX.sym("u", obs.nu, n), ca.MX.sym("z0", obs.nz)
        w0 = obs.memory_init(y[:, 0], u[:, 0])
        name = (f"{c_name(obs.system.name)}_{c_name(obs.method)}_n{n}" + (f"_g{group}" if group > 1 else "")
                + ("" if self.shortcuts else "_plain"))
        first = ca.repmat(obs.decode(z0, w0), 1, group)
        carried = [first] if self.carries else []                # the estimate a step reads (reuse_decoded)
        if self.split is None:
            states = list(range(2 + len(carried)))
            steps = self.step.mapaccum("trajectory", n - 1, states, states)
            xhat = steps(z0, w0, *carried, y[:, :n - 1], y[:, 1:], u[:, 1:])[2]
        else:
            states = list(range(4 + len(carried)))
            # two levels of unrolled steps (the default tens: three), each copying the states it stores
            steps = self._group_step(group).mapaccum("trajectory", n - 1, states, states, {"base": 32})
            rows, cols = obs.memory_shape
            key0 = ca.DM.nan(rows * cols + obs.nu)                  # no previous memory: compute at the first step
            s0 = ca.DM.zeros(self.split.shared.size1_out(0))
            xhat = steps(ca.repmat(z0, 1, group), w0, key0, s0, *carried, y[:, :group * (n - 1)], y[:, group:],
                         u[:, 1:])[4]
        return ca.Function(name, [y, u, z0], [ca.horzcat(first, xhat)], ["y", "u", "s0"], ["xhat"])

    def identity(self, n: int, group: int = 1) -> str:
        """The package's code, the options and ``n``, ``group``, and the observer's Functions serialised (its
        step, memory, decoder and model-based injection: what :meth:`trajectory` and the shortcuts are built from)."""
        obs = self.observer
        digest = hashlib.sha256("\0".join((code_digest(), type(self).__name__, obs.system.name, obs.method, str(n),
                                           str(group), str(self.shortcuts))).encode())
        for f in (obs.step, obs.memory_init, obs.decode, obs.model_injection):
            digest.update(b"\0" + (b"none" if f is None else f.serialize().encode()))
        return digest.hexdigest()

    def _group_step(self, group: int) -> ca.Function:
        """One sample of ``group`` trials with the same inputs, the shared part memoised.

        ``(Z (nz, group), w, key, s, [Xhat (nx, group)], Y (ny, group), Y_next (ny, group), u_next)
        -> (Z_next, w_next, key_next, s_next, Xhat_next)``; ``key = [vec(w); u_next]`` of the sample
        whose shared part ``s`` is (NaN before the first); ``Xhat``, the previous estimates, where
        the step reads them (:func:`reuse_decoded`).
        """
        obs, split = self.observer, self.split
        rows, cols = obs.memory_shape
        Z, w = ca.MX.sym("Z", obs.nz, group), ca.MX.sym("w", rows, cols)
        key, s = ca.MX.sym("key", rows * cols + obs.nu), ca.MX.sym("s", split.shared.size1_out(0))
        X = [ca.MX.sym("Xhat", obs.nx, group)] if self.carries else []
        Y, Y_next, u_next = ca.MX.sym("Y", obs.ny, group), ca.MX.sym("Y_next", obs.ny, group), ca.MX.sym("u", obs.nu)
        reuse = ca.Function("reuse", [s, w, u_next], [s])
        compute = ca.Function("compute", [s, w, u_next], [split.shared(w, u_next)])
        memo = ca.Function.if_else("shared_memo", reuse, compute)
        key_next = ca.vertcat(ca.vec(w), u_next)
        s_next = memo(ca.mmin(key_next == key), s, w, u_next)
        trials = [split.core(Z[:, j], w, *[x[:, j] for x in X], Y[:, j], Y_next[:, j], u_next, s_next)
                  for j in range(group)]
        return ca.Function("group_step", [Z, w, key, s, *X, Y, Y_next, u_next],
                           [ca.horzcat(*[z for z, _ in trials]), split.w_next(s_next, (rows, cols)), key_next, s_next,
                            ca.horzcat(*[x for _, x in trials])])

    def initial_state(self) -> np.ndarray:
        """``z_0 = 0`` (nz,)."""
        return np.zeros(self.observer.nz)


class CompiledEKF(CompiledEstimator):
    """An :class:`~kklcasadi.estimators.ekf.EKF` as a :class:`CompiledEstimator`; bitwise :meth:`EKF.simulate`.

    The trajectory is the filter's own Functions: ``s0 = [x0; vec(P0)]`` (its prior), ``update``
    at ``(x0, P0, y_0)``, then ``step`` (predict with ``u_k``, update with ``y_k+1``) folded with
    ``mapaccum``.

    Parameters
    ----------
    ekf : EKF
    compiler, n_threads, profile
        See :class:`CompiledEstimator`.
    """

    def __init__(self, ekf: EKF, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None, profile: Optional[Profile] = None) -> None:
        from ...estimators.ekf import EKF

        if not isinstance(ekf, EKF):
            raise TypeError(f"ekf: expected a kklcasadi.estimators.ekf.EKF, received {type(ekf).__name__}.")
        system = ekf.system
        super().__init__(system.nx, system.nu, system.ny, ekf.dt, compiler=compiler, n_threads=n_threads,
                         profile=profile)
        self.ekf = ekf

    def trajectory(self, n: int, group: int = 1) -> ca.Function:
        if group != 1:
            raise ValueError(f"group: expected 1 (the EKF's trials share no work), received {group!r}.")
        ekf, nx = self.ekf, self.nx
        y, u = ca.MX.sym("y", self.ny, n), ca.MX.sym("u", self.nu, n)
        prior = ca.MX.sym("s0", nx + nx * nx)
        x0, P0 = ekf.update(prior[:nx], ca.reshape(prior[nx:], nx, nx), y[:, 0])
        steps = ekf.step.mapaccum("ekf_traj", n - 1)
        states = steps(ca.vertcat(x0, ca.vec(P0)), ca.vertcat(u[:, :n - 1], y[:, 1:]))
        return ca.Function(f"{c_name(ekf.system.name)}_ekf_n{n}", [y, u, prior],
                           [ca.horzcat(x0, states[:nx, :])], ["y", "u", "s0"], ["xhat"])

    def initial_state(self) -> np.ndarray:
        """The prior ``[x0; vec(P0)]`` (nx + nx^2,), ``vec`` column-major."""
        return np.concatenate([self.ekf.x0, self.ekf.P0.ravel(order="F")])


class CompiledRecord(CompiledEstimator):
    """An observer's estimates with its latent and the covariance of its head, compiled and mapped over trials.

    Each trial's Function gives, per sample, the rows ``[xhat (nx); z (nz); vec(P) (nx^2)]`` (``P`` only where the
    observer has a covariance head, :attr:`~kklcasadi.observer.kkl.KKLObserver.step_covariance`); calling it returns
    those rows as ``(M, N, rows)``, and :meth:`record` splits them. The same Functions as
    :meth:`KKLObserver.simulate` (``z_0 = 0``, ``memory_init``, ``decode``, ``covariance`` at the first sample,
    then the step folded), so compiled with :class:`Compiler`'s flags it gives the same values bitwise.

    Parameters
    ----------
    observer : KKLObserver
    compiler, n_threads, profile
        See :class:`CompiledEstimator`.
    """

    def __init__(self, observer: KKLObserver, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None, profile: Optional[Profile] = None) -> None:
        from ...observer.kkl import KKLObserver

        if not isinstance(observer, KKLObserver):
            raise TypeError(f"observer: expected a kklcasadi.KKLObserver, received {type(observer).__name__}.")
        self.observer = observer
        self.covariance = observer.covariance is not None
        rows = observer.nx + observer.nz + (observer.nx ** 2 if self.covariance else 0)
        super().__init__(rows, observer.nu, observer.ny, observer.dt, compiler=compiler, n_threads=n_threads,
                         profile=profile)

    def trajectory(self, n: int, group: int = 1) -> ca.Function:
        if group != 1:
            raise ValueError(f"group: expected 1, received {group!r}.")
        obs = self.observer
        nx = obs.nx
        y, u, z0 = ca.MX.sym("y", obs.ny, n), ca.MX.sym("u", obs.nu, n), ca.MX.sym("z0", obs.nz)
        w0 = obs.memory_init(y[:, 0], u[:, 0])
        x0 = obs.decode(z0, w0)
        step = obs.step_covariance if obs.step_covariance is not None else obs.step
        start = [ca.DM(obs.inflation_start)] if step.n_in() == 6 else []    # the covariance inflation's m_0
        out = fold(step, "trajectory", n - 1)(z0, w0, y[:, :n - 1], y[:, 1:], u[:, 1:], *start)
        rows = [ca.horzcat(x0, out[2]), ca.horzcat(z0, out[0])]
        if self.covariance:
            rows.append(ca.horzcat(ca.vec(obs.covariance(z0, w0, x0)), ca.reshape(out[3], nx * nx, n - 1)))
        name = f"{c_name(obs.system.name)}_{c_name(obs.method)}_record_n{n}"
        return ca.Function(name, [y, u, z0], [ca.vertcat(*rows)], ["y", "u", "s0"], ["record"])

    def initial_state(self) -> np.ndarray:
        """``z_0 = 0`` (nz,)."""
        return np.zeros(self.observer.nz)

    def record(self, t: Any, y: Any, u: Any) -> tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
        """``xhat (M, N, nx)``, ``z (M, N, nz)`` and ``cov (M, N, nx, nx)`` (None without a head) of M trials."""
        rows = self(t, y, u)
        nx, nz = self.observer.nx, self.observer.nz
        cov = None
        if self.covariance:                                   # vec is column-major: P[i, j] at row i + nx j
            cov = rows[..., nx + nz:].reshape(rows.shape[:2] + (nx, nx)).swapaxes(-1, -2)
        return rows[..., :nx], rows[..., nx:nx + nz], cov


def observer_estimator(observer: KKLObserver, *, compiler: Optional[Compiler] = Compiler(),
                       n_threads: Optional[int] = None, group: int = GROUP, profile: Optional[Profile] = None,
                       shortcuts: bool = True) -> CompiledObserver:
    """The fast estimator of an observer: its trajectory compiled, mapped over trials.

    Parameters
    ----------
    observer : KKLObserver
    compiler : Compiler or None
        None: the CasADi VM (the reference, ``observer.simulate``'s path).
    n_threads : int, optional
        Worker threads over trials (default: the CPU count).
    group : int
        Largest group of trials with the same inputs run together (:class:`CompiledEstimator`).
    profile : optional
        See :class:`CompiledEstimator`.
    shortcuts : bool
        False: the plain step folded (:class:`CompiledObserver`).

    Returns
    -------
    CompiledObserver
        ``est(t (N,), y (M, N, ny), u (M, N, nu)) -> xhat (M, N, nx)``.
    """
    return CompiledObserver(observer, compiler=compiler, n_threads=n_threads, group=group, profile=profile,
                            shortcuts=shortcuts)


def ekf_estimator(ekf: EKF, *, compiler: Optional[Compiler] = Compiler(), n_threads: Optional[int] = None,
                  profile: Optional[Profile] = None) -> CompiledEKF:
    """The fast estimator of an EKF (see :func:`observer_estimator`); the filter is unchanged."""
    return CompiledEKF(ekf, compiler=compiler, n_threads=n_threads, profile=profile)


def pf_estimator(system: Any, dt: float, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None, profile: Optional[Profile] = None, **options: Any) -> ParticleFilter:
    """A :class:`~kklcasadi.estimators.pf.ParticleFilter` whose per-sample Functions are compiled by ``compiler``.

    The libraries are cached with the observers' (:class:`Compiler`), instead of the filter's own
    just-in-time build into a temporary directory; the values are the same bitwise.

    Parameters
    ----------
    system : System
    dt : float
    compiler : Compiler or None
        None: the CasADi VM.
    n_threads : int, optional
        Worker threads over trials (default: the CPU count).
    profile : Profile, optional
        Gets the time spent building and compiling as the phase ``compile``.
    **options
        The filter's other options (``n_particles``, ``process_std``, ``measurement_std``,
        ``substeps``, ``seed``, ...).

    Returns
    -------
    ParticleFilter
        A protocol estimator: ``pf(t, y, u) -> xhat``.
    """
    from ...estimators.pf import ParticleFilter

    if compiler is not None and not isinstance(compiler, Compiler):
        raise TypeError(f"compiler: expected a kklcasadi.evaluation.compiled.Compiler or None, received "
                        f"{type(compiler).__name__}.")
    children = os.times()
    with phase(profile, "compile"):
        pf = ParticleFilter(system, dt, compile=_vm if compiler is None else compiler.compile, n_threads=n_threads,
                            **options)
    if profile is not None:
        profile.add("compile", 0.0, children_cpu(children))
    return pf


def _vm(f: ca.Function) -> ca.Function:
    return f


def precompile(estimators: Sequence[CompiledEstimator], n: int, *, groups: Sequence[int] = (1,),
               jobs: Optional[int] = None, meanwhile: Optional[Callable[[], Any]] = None) -> Any:
    """Build and compile the trajectories of ``estimators`` for ``n`` samples, ``jobs`` compilers at a time.

    CasADi writes the sources in this thread; the C compilers then run on ``jobs`` threads (default:
    the CPU count) while this thread runs ``meanwhile()`` (e.g. simulating the trials); the
    libraries are loaded when both are done. Estimators without a compiler (VM) and trajectories
    already built are left as they are. Each estimator's ``profile`` gets a ``compile`` phase: the
    time this thread spent writing sources and waiting for the compilers, and the CPU time of both.

    Parameters
    ----------
    estimators : sequence of CompiledEstimator
    n : int
        Samples per trial.
    groups : sequence of int
        Sizes of the groups of trials with the same inputs that the calls will run (2 for the
        noise-free and noisy cells in one call); an estimator whose trials share no work compiles
        the size 1 only, the others each size up to their :attr:`CompiledEstimator.group`.
    jobs : int, optional
        Compilers at a time.
    meanwhile : callable, optional
        Run in this thread while the compilers run.

    Returns
    -------
    object
        What ``meanwhile()`` returned (None without it).
    """
    pending = []
    for est in estimators:
        sizes = sorted({min(int(g), est.group) for g in groups}) if est.shares_inputs else [1]
        for size in sizes:
            if (n, size) in est._functions or est.compiler is None:
                continue
            if not est.compiler.available():
                est.function(n, size)                              # the VM, with the compiler's warning
                continue
            wall, cpu = time.perf_counter(), time.process_time()
            build = est.compiler.build_known(est.identity(n, size), lambda: est.trajectory(n, size))
            pending.append((est, size, build, time.perf_counter() - wall, time.process_time() - cpu))
    children = os.times()
    with ThreadPoolExecutor(max(1, jobs or os.cpu_count() or 1)) as pool:
        futures = [pool.submit(build.run) for _, _, build, _, _ in pending]
        result = meanwhile() if meanwhile is not None else None
        waited = time.perf_counter()
        for future in futures:
            future.result()
        waited = time.perf_counter() - waited
    compilers = children_cpu(children)
    for est, size, build, wall, cpu in pending:
        est._functions[n, size] = build.load()
        share = 1 / len(pending)
        if est.profile is not None:
            est.profile.add("compile", wall + waited * share, cpu + compilers * share)
    return result
