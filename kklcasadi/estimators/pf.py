"""Bootstrap particle filter: the near-optimal reference estimator beside the EKF.

The propagation model is the simulator's own noise model (docs/protocol.md): process noise of std
``process_std`` added to ``xdot``, one draw per particle and sample interval held over it, input
held, integrated by the plant's RK4 step (:func:`kklcasadi.simulate.step_function` with
``method="rk"``, ``substeps`` steps per interval). The simulator of the protocol integrates the same
noisy ODE with CVODES (rtol 1e-8); the only mismatch is the RK4 truncation error, O((dt/substeps)^5)
per interval (about 1e-7 on Duffing at dt = 0.05, far below the per-interval noise displacement
``process_std dt`` = 5e-3). Measurements are ``y_k = h(x_k) + v_k`` with ``v_k ~ N(0,
measurement_std^2 I)``. The prior is uniform on the system's X0 box (the protocol draws x0 from it)
or Gaussian (``x0_mean``, ``x0_cov``).

Each sample: weight by ``y_k`` (log space, normalised per trial), estimate (weighted mean and
variance), then resample the trials whose effective sample size is below ``ess_threshold N``; then
propagate with ``u_k`` to the next sample. Propagation, weighting, normalisation and the moments of
all particles of all trials are one CasADi Function call per sample (the per-particle RK4 step
mapped over the particles, just-in-time compiled with the system C compiler when there is one, or
compiled by a given ``compile`` hook such as the cached libraries of
:class:`kklcasadi.evaluation.compiled.Compiler`, mapped over the trials on threads), evaluated in
place on numpy buffers; the random draws and the resampling are numpy.

Random streams: trial ``i`` draws its prior, process noise, resampling uniforms and roughening jitter, in that order
of use, from ``default_rng(SeedSequence(seed).spawn(M)[i])``; the same seed gives bitwise the same
estimates, and trial ``i`` of a batch does not depend on the other trials of the batch (a batch's
first trials are bitwise the filter run on those trials alone).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from typing import Callable, Optional

import casadi as ca
import numpy as np

from ..estimate import Estimate, check_sample
from ..plant.noise import NoiseModel
from ..plant.noise import noise_model as as_noise_model
from ..plant.simulate import step_function
from ..plant.systems import System
from ..validation import (
    Text,
    covariance,
    error,
    finite_number,
    nonnegative_int,
    nonnegative_number,
    one_of,
    positive_int,
    positive_number,
    state_stds,
)

__all__ = ["ParticleFilter", "PFEstimator", "PFStats", "PFEstimate", "RESAMPLING", "SUBSTEPS", "ROUGHENING"]

#: Resampling schemes accepted by ``resample``.
RESAMPLING = ("systematic", "stratified", "multinomial")
#: RK4 steps per sample interval that the benchmark's filter uses on the paper's plants (the others get
#: the stable count, :func:`kklcasadi.plant.rk4.substeps_for`): one step diverges on the stiff corners of
#: FitzHugh-Nagumo's box, and its truncation error is measurable on Roessler.
SUBSTEPS = {"fhn": 4, "rossler": 4}
#: The roughening of the benchmarks' filter (``kklcasadi evaluate --pf``, ``kklcasadi generalise --pf``).
#: Without it 1000 particles fall behind the EKF at low noise (noise 0.05: Roessler 1.8-2.3x, Van der
#: Pol 1.16x); chosen on validation trials, flat from 0.6 to 1 (docs/protocol.md, "Estimators").
ROUGHENING = 0.6

#: The C compiler of the just-in-time path, and its flags (``-ffp-contract=off``: bitwise the VM).
JIT_COMPILER = "gcc"
JIT_FLAGS = ["-O3", "-ffp-contract=off"]


@dataclass(frozen=True, eq=False)
class PFStats:
    """The particle filter's report of a run (an :class:`kklcasadi.estimate.Estimate`'s ``stats``).

    Attributes
    ----------
    ess : numpy.ndarray, shape (N,) or (M, N)
        The effective sample size ``1 / sum w_i^2`` after weighting by ``y_k`` (before resampling),
        between 1 and ``n_particles``.
    """

    ess: np.ndarray


#: The filter's result is the one :class:`kklcasadi.estimate.Estimate` (``t``, ``xhat``, ``var``: the weighted
#: mean and variance per state, ``stats``: :class:`PFStats`); the name stays.
PFEstimate = Estimate


class ParticleFilter:
    """Bootstrap (sampling-importance-resampling) particle filter for ``xdot = f(x, u) + w``, ``y = h(x) + v``.

    Parameters
    ----------
    system : System
    dt : float
        Sample period.
    n_particles : int
        Particles per trial.
    process_std : float or sequence of float (nx,)
        Std of the process noise added to ``xdot``, drawn per particle and interval and held on it
        (docs/protocol.md: 0.1); one for every state or one per state (0 on the parameters of an
        augmented plant). 0 propagates the particles deterministically.
    measurement_std : float
        Std (scale) of the measurement noise on each output (docs/protocol.md: 0.1); must be > 0.
    noise_model : NoiseModel or str, optional
        The measurement noise's distribution (:mod:`kklcasadi.plant.noise`): the likelihood of the
        weights is its density (Student-t, outliers), or the probability of the measured
        quantisation cell (a Gaussian base); default Gaussian.
    substeps : int
        RK4 steps per sample interval.
    seed : int
        Seed of the trials' random streams (see the module docstring).
    resample : {"systematic", "stratified", "multinomial"}
        Resampling scheme.
    ess_threshold : float
        Resample a trial when its effective sample size is below ``ess_threshold * n_particles``;
        0 never resamples, 1 resamples whenever the weights are not uniform.
    roughening : float
        After each resampling of a trial, jitter its particles by ``roughening * E_j * n_particles **
        (-1 / nx)`` times a standard normal draw in each state ``j``, ``E_j`` the range of the resampled
        particles in that state (Gordon, Salmond and Smith's roughening; they use 0.2). At low noise
        the copies a resampling makes stay together and the cloud loses the spread it needs; 0 (the
        default) does not jitter and draws nothing.
    x0_mean : array_like, shape (nx,), optional
    x0_cov : array_like, shape (nx, nx), optional
        Gaussian prior (give both); default the uniform distribution on ``system.x0_box``.
    jit : bool
        Compile the per-sample Function with the C compiler (bitwise the CasADi VM; the whole
        filter about 5x faster on Duffing); without a compiler on ``PATH`` it runs in the VM with
        a warning.
    compile : callable ``casadi.Function -> casadi.Function``, optional
        How to compile the per-sample Functions instead of the just-in-time build (``jit`` is then
        not used): e.g. ``kklcasadi.evaluation.compiled.Compiler().compile``, whose libraries are
        cached on disk (``kklcasadi evaluate --pf``).
    n_threads : int, optional
        Worker threads over the trials (default: the CPU count); the estimates do not depend on it.
    params : array_like, shape (n_params,), optional
        The parameter values of the filter's model, for a plant with parameters; default the
        nominal ones (:meth:`kklcasadi.System.at`).

    Notes
    -----
    A particle whose state or likelihood leaves the finite range (an RK4 step that diverges, e.g.
    a stiff plant with too few ``substeps``) gets weight 0 and is dropped at the next resampling;
    a trial whose particles all diverge gives NaN from then on. One RK4 step per interval is
    accurate to 1e-7 on Duffing at dt = 0.05 over the X0 box, but not on the stiff corners of
    FitzHugh-Nagumo's box or on Roessler (use ``substeps=4`` there).
    """

    def __init__(self, system: System, dt: float, *, n_particles: int = 1000, process_std: float = 0.1,
                 measurement_std: float = 0.1, substeps: int = 1, seed: int = 0, resample: str = "systematic",
                 ess_threshold: float = 0.5, roughening: float = 0.0, x0_mean: object = None, x0_cov: object = None,
                 jit: bool = True, compile: Optional[Callable[[ca.Function], ca.Function]] = None,
                 n_threads: Optional[int] = None, params: object = None,
                 noise_model: NoiseModel | str | None = None) -> None:
        if not isinstance(system, System):
            raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
        self.system = system if params is None else system.at(params)
        self.dt = positive_number(dt, "dt")
        self.n_particles = positive_int(n_particles, "n_particles")
        self.process_std = state_stds(process_std, self.system.nx)
        self.noise_model = as_noise_model(noise_model)
        self.measurement_std = positive_number(measurement_std, "measurement_std",
                                               "The likelihood needs measurement noise.")
        self.substeps = positive_int(substeps, "substeps")
        self.seed = nonnegative_int(seed, "seed")
        self.resample = one_of(resample, "resample", RESAMPLING)
        threshold = finite_number(ess_threshold, "ess_threshold")
        if not 0.0 <= threshold <= 1.0:
            raise error("ess_threshold", "a number in [0, 1]", ess_threshold)
        self.ess_threshold = threshold
        self.roughening = nonnegative_number(roughening, "roughening")
        if (x0_mean is None) != (x0_cov is None):
            given, missing = ("x0_mean", "x0_cov") if x0_cov is None else ("x0_cov", "x0_mean")
            raise error(missing, f"an array together with {given} (a Gaussian prior needs both)", None)
        if x0_mean is None:
            self.x0_mean = self.x0_cov = None
        else:
            self.x0_mean = self.system.check_state(x0_mean, "x0_mean")
            self.x0_cov = covariance(x0_cov, self.system.nx, "x0_cov")
        if not isinstance(jit, (bool, np.bool_)):
            raise error("jit", "a bool", Text(type(jit).__name__), kind=TypeError)
        if compile is not None and not callable(compile):
            raise error("compile", "a callable casadi.Function -> casadi.Function or None",
                        Text(type(compile).__name__), kind=TypeError)
        self.n_threads = None if n_threads is None else positive_int(n_threads, "n_threads")
        self.compile = compile
        self.jit = compile is None and bool(jit) and shutil.which(JIT_COMPILER) is not None
        if compile is None and jit and not self.jit:
            warnings.warn(f"C compiler {JIT_COMPILER!r} not found on PATH; the particle filter runs in the "
                          "CasADi VM (about 10x slower, same values).", RuntimeWarning, stacklevel=2)
        self.update, self.step = self._functions()

    # ------------------------------------------------------------------ CasADi Functions
    def _functions(self) -> tuple[ca.Function, ca.Function]:
        """``update(X, logw, y)`` and ``step(X, logw, u, E, y)`` over the particles of one trial.

        ``X`` (nx, n) particles, ``logw`` (1, n) log weights, ``u`` (nu, 1) input held over the
        interval, ``E`` (nx, n) standard normal draws (scaled by ``process_std`` inside), ``y``
        (ny, 1) the measurement at the end of the interval. Both return ``X`` (propagated by
        ``step``), ``logw`` normalised after weighting by ``y``, ``ess`` (1, 1), ``mean`` and
        ``var`` (nx, 1).
        """
        s, n = self.system, self.n_particles
        nx, nu, ny = s.nx, s.nu, s.ny
        x, u, e, y = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("e", nx), ca.SX.sym("y", ny)
        plant = step_function(s, self.dt, "rk", substeps=self.substeps)

        def weighted(x_particle: ca.SX) -> tuple[ca.SX, ca.SX]:
            if self.noise_model.gaussian:
                loglik = -0.5 * ca.sumsqr(y - s.h(x_particle)) / self.measurement_std ** 2
            else:
                loglik = ca.sum1(self.noise_model.log_likelihood(y, s.h(x_particle), self.measurement_std))
            finite = ca.fabs(loglik) < ca.inf
            for i in range(nx):
                finite = ca.logic_and(finite, ca.fabs(x_particle[i]) < ca.inf)
            return ca.if_else(finite, x_particle, 0.0), ca.if_else(finite, loglik, -ca.inf)

        x_upd, ll_upd = weighted(x)
        std = self.process_std if np.ndim(self.process_std) == 0 else ca.DM(self.process_std)
        x_next, ll_next = weighted(plant(x, ca.vertcat(u, std * e)))
        particle_update = ca.Function("pf_particle_update", [x, y], [x_upd, ll_upd]).map(n, "serial")
        particle_step = ca.Function("pf_particle_step", [x, u, e, y], [x_next, ll_next]).map(n, "serial")

        X, E = ca.MX.sym("X", nx, n), ca.MX.sym("E", nx, n)
        logw, U, Y = ca.MX.sym("logw", 1, n), ca.MX.sym("u", nu), ca.MX.sym("y", ny)
        names_out = ["X_next", "logw_next", "ess", "mean", "var"]

        def moments(Xw: ca.MX, ll: ca.MX) -> list[ca.MX]:
            lw = logw + ll
            lw = lw - ca.mmax(lw)
            scaled = ca.exp(lw)
            total = ca.sum2(scaled)
            w = scaled / total
            lw = lw - ca.log(total)
            mean = ca.mtimes(Xw, w.T)
            var = ca.mtimes((Xw - ca.repmat(mean, 1, n)) ** 2, w.T)
            return [Xw, lw, 1.0 / ca.sumsqr(w), mean, var]

        base = f"pf_{s.name}_n{n}"
        update = self._build(f"{base}_update", [X, logw, Y], moments(*particle_update(X, ca.repmat(Y, 1, n))),
                             ["X", "logw", "y"], names_out)
        step = self._build(f"{base}_step", [X, logw, U, E, Y],
                           moments(*particle_step(X, ca.repmat(U, 1, n), E, ca.repmat(Y, 1, n))),
                           ["X", "logw", "u", "E", "y"], names_out)
        return update, step

    def _build(self, name: str, inputs: list, outputs: list, names_in: list, names_out: list) -> ca.Function:
        if self.compile is not None:
            return self.compile(ca.Function(name, inputs, outputs, names_in, names_out))
        if not self.jit:
            return ca.Function(name, inputs, outputs, names_in, names_out)
        with tempfile.TemporaryDirectory(prefix="kklcasadi-pf-") as build:
            # the library is loaded when the Function is built: its files go with the directory
            opts = {"jit": True, "compiler": "shell", "jit_name": name, "jit_cleanup": False,
                    "jit_options": {"compiler": JIT_COMPILER, "flags": JIT_FLAGS, "directory": build + os.sep,
                                    "cleanup": False, "verbose": False}}
            return ca.Function(name, inputs, outputs, names_in, names_out, opts)

    # ------------------------------------------------------------------ filtering
    def prior(self, rng: np.random.Generator) -> np.ndarray:
        """Draw the initial particles of one trial, shape (n_particles, nx)."""
        n, nx = self.n_particles, self.system.nx
        if self.x0_mean is None:
            lo, hi = self.system.x0_box[:, 0], self.system.x0_box[:, 1]
            return lo + (hi - lo) * rng.random((n, nx))
        values, vectors = np.linalg.eigh(self.x0_cov)
        root = vectors * np.sqrt(np.clip(values, 0.0, None))
        return self.x0_mean + rng.standard_normal((n, nx)) @ root.T

    def resample_indices(self, weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Indices of the particles kept by one resampling of one trial.

        Parameters
        ----------
        weights : numpy.ndarray, shape (n_particles,)
            Normalised weights.
        rng : numpy.random.Generator
            The trial's stream (one uniform for systematic, ``n`` for stratified and multinomial).

        Returns
        -------
        numpy.ndarray of int, shape (n_particles,), sorted
        """
        n = weights.size
        cumulative = np.cumsum(weights)
        if self.resample == "systematic":
            positions = (np.arange(n) + rng.random()) / n
        elif self.resample == "stratified":
            positions = (np.arange(n) + rng.random(n)) / n
        else:
            positions = np.sort(rng.random(n))
        # positions scaled into [0, total): a particle of weight 0 has an empty interval, never picked
        return np.searchsorted(cumulative, positions * cumulative[-1], side="right")

    def roughen(self, X: np.ndarray, rng: np.random.Generator) -> None:
        """Jitter one trial's resampled particles ``X`` (n_particles, nx) in place (``roughening``; nothing at 0)."""
        if self.roughening > 0:
            n, nx = X.shape
            spread = self.roughening * np.ptp(X, axis=0) * n ** (-1.0 / nx)
            X += spread * rng.standard_normal((n, nx))

    def simulate(self, t: object, y: object, u: object) -> Estimate:
        """Filter one or many measured trajectories.

        Parameters
        ----------
        t : array_like, shape (N,)
            Sample times, spaced by ``dt``.
        y : array_like, shape (N, ny) or (M, N, ny)
        u : array_like, shape (N, nu) or (M, N, nu)
            ``u_k`` is held over ``[t_k, t_k+1)``.

        Returns
        -------
        Estimate
            ``xhat``, ``var`` (N, nx) or (M, N, nx) and ``stats`` a :class:`PFStats` (``ess`` (N,) or (M, N)):
            the filtered estimate after ``y_k``.
        """
        t, y, u, single = self._check(t, y, u)
        m, n_samples = y.shape[:2]
        nx = self.system.nx
        if m == 0:
            return Estimate(t, np.empty((0, n_samples, nx)), var=np.empty((0, n_samples, nx)),
                            stats=PFStats(np.empty((0, n_samples))))
        cloud = _Cloud(self, m)
        xhat, var, ess = np.empty((m, n_samples, nx)), np.empty((m, n_samples, nx)), np.empty((m, n_samples))
        for k in range(n_samples):
            cloud.advance(y[:, k], None if k == 0 else u[:, k - 1])
            xhat[:, k], var[:, k], ess[:, k] = cloud.mean_k, cloud.var_k, cloud.ess_k
        if single:
            return Estimate(t, xhat[0], var=var[0], stats=PFStats(ess[0]))
        return Estimate(t, xhat, var=var, stats=PFStats(ess))

    def estimator(self) -> PFEstimator:
        """The filter one sample at a time: ``xhat = est.make_step(y, u)`` (a :class:`PFEstimator`)."""
        return PFEstimator(self)

    def __call__(self, t: object, y: object, u: object) -> np.ndarray:
        """The protocol's estimator: ``(t (N,), y (M, N, ny), u (M, N, nu)) -> xhat (M, N, nx)``."""
        return self.simulate(t, y, u).xhat

    def _check(self, t: object, y: object, u: object) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        t = np.asarray(t, dtype=float)
        y = np.asarray(y, dtype=float)
        u = np.asarray(u, dtype=float)
        if t.ndim != 1 or t.size == 0:
            raise error("t", "sample times of shape (N,) with N >= 1", Text(f"shape {t.shape}"))
        single = y.ndim == 2
        if single:
            y, u = y[None], u[None]
        ny, nu = self.system.ny, self.system.nu
        if y.ndim != 3 or y.shape[2] != ny or y.shape[1] != t.size:
            raise error("y", f"shape (N, ny) or (M, N, ny) with N = {t.size}, ny = {ny}", Text(f"shape {y.shape}"))
        if u.shape != y.shape[:2] + (nu,):
            raise error("u", f"shape {y.shape[:2] + (nu,)}", Text(f"shape {u.shape}"))
        spacing = np.diff(t)
        if spacing.size and not np.allclose(spacing, self.dt, rtol=1e-9, atol=1e-12):
            raise error("t", f"samples spaced by dt = {self.dt}",
                        Text(f"spacings from {spacing.min():.6g} to {spacing.max():.6g}"))
        for arg, values in (("y", y), ("u", u)):
            bad = np.argwhere(~np.isfinite(values))
            if bad.size:
                raise error(arg, "finite values", Text(f"NaN or inf at trial {bad[0, 0]}, sample {bad[0, 1]}"))
        return t, y, u, single


class _Cloud:
    """The particles of M trials and the filter's in-place calls on them, one sample at a time (what
    :meth:`ParticleFilter.simulate` and :class:`PFEstimator` run): trial ``i`` draws from the stream
    ``SeedSequence(seed).spawn(M)[i]``, the prior first."""

    def __init__(self, pf: ParticleFilter, m: int) -> None:
        nx, ny, nu, n = pf.system.nx, pf.system.ny, pf.system.nu, pf.n_particles
        self.pf = pf
        self.rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(pf.seed).spawn(m)]
        self.X = np.stack([pf.prior(rng) for rng in self.rngs])         # (M, n, nx) = (nx, n M) column-major
        self.logw = np.full((m, n), -np.log(n))
        self.noise = np.empty((m, n, nx))
        self.u_k, self.y_k = np.empty((m, nu)), np.empty((m, ny))
        self.X_out, self.logw_out = np.empty_like(self.X), np.empty_like(self.logw)
        self.ess_k, self.mean_k, self.var_k = np.empty(m), np.empty((m, nx)), np.empty((m, nx))
        results = [self.X_out, self.logw_out, self.ess_k, self.mean_k, self.var_k]
        threads = min(m, pf.n_threads or os.cpu_count() or 1)
        self._update = _in_place(pf.update.map(m, "thread", threads), [self.X, self.logw, self.y_k], results)
        self._step = _in_place(pf.step.map(m, "thread", threads),
                               [self.X, self.logw, self.u_k, self.noise, self.y_k], results)
        self.k = 0

    def advance(self, y: np.ndarray, u_prev: Optional[np.ndarray]) -> None:
        """Take ``y_k`` (M, ny) (and ``u_k-1`` (M, nu) after the first sample): weight (after propagating), read
        ``mean_k``, ``var_k``, ``ess_k``, then resample the trials whose ESS fell below the threshold."""
        pf, X, logw, n = self.pf, self.X, self.logw, self.pf.n_particles
        self.y_k[:] = y
        if self.k == 0:
            self._update()
        else:
            self.u_k[:] = u_prev
            for i, rng in enumerate(self.rngs):
                rng.standard_normal(out=self.noise[i])
            self._step()
        X[:], logw[:] = self.X_out, self.logw_out
        for i in np.flatnonzero(self.ess_k < pf.ess_threshold * n):
            idx = pf.resample_indices(np.exp(logw[i]), self.rngs[i])
            X[i] = X[i][idx]
            logw[i] = -np.log(n)
            pf.roughen(X[i], self.rngs[i])
        self.k += 1


class PFEstimator:
    """Stateful form of a :class:`ParticleFilter`, for loops that receive one sample at a time (a
    :class:`kklcasadi.estimate.StepEstimator`).

    ``make_step(y_k, u_k)`` returns the weighted mean after ``y_k``: bitwise the first trial of
    :meth:`ParticleFilter.simulate` (the stream ``SeedSequence(seed).spawn(M)[0]``), sample by sample.

    Parameters
    ----------
    pf : ParticleFilter

    Attributes
    ----------
    pf : ParticleFilter
    k : int
        Samples taken since the start or the last :meth:`reset`.
    """

    def __init__(self, pf: ParticleFilter) -> None:
        if not isinstance(pf, ParticleFilter):
            raise error("pf", "a kklcasadi.estimators.ParticleFilter", Text(type(pf).__name__), kind=TypeError)
        self.pf = pf
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next :meth:`make_step` draws the prior again (the same stream)."""
        self._cloud: Optional[_Cloud] = None
        self._u: Optional[np.ndarray] = None
        self.k = 0

    def make_step(self, y: object, u: object) -> np.ndarray:
        """Feed ``y_k`` and ``u_k`` (the input held from ``t_k``); return the estimate ``xhat_k`` (nx,)."""
        system = self.pf.system
        y = check_sample(y, "y", system.ny, self.k)
        u = check_sample(u, "u", system.nu, self.k)
        if self._cloud is None:
            self._cloud = _Cloud(self.pf, 1)
        self._cloud.advance(y[None], None if self._u is None else self._u[None])
        self._u = u
        self.k += 1
        return self._cloud.mean_k[0].copy()

    @property
    def stats(self) -> dict:
        """``k`` (samples taken), ``var`` (the weighted variance per state) and ``ess`` (the effective sample
        size before resampling) of the last step (None before the first)."""
        cloud = self._cloud
        return {"k": self.k, "var": None if cloud is None else cloud.var_k[0].copy(),
                "ess": None if cloud is None else float(cloud.ess_k[0])}


def _in_place(f: ca.Function, args: list[np.ndarray], results: list[np.ndarray]) -> Callable[[], None]:
    """``f`` bound to C-contiguous numpy arrays: each call reads ``args`` and writes ``results`` in place.

    CasADi's column-major (r, c) matrix is the C-order array of shape (c, r), so an (M, n, nx)
    array is an (nx, n M) input without a copy.
    """
    buffer, trigger = f.buffer()
    for i, a in enumerate(args):
        buffer.set_arg(i, memoryview(a))
    for i, r in enumerate(results):
        buffer.set_res(i, memoryview(r))

    def call() -> None:
        trigger()
        if buffer.ret() != 0:
            raise RuntimeError(f"evaluating {f.name()!r} failed (status {buffer.ret()})")

    return call
