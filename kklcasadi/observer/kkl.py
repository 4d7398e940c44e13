"""The learned KKL observer as pure CasADi: latent ODE, sample-interval step, integrator, C code.

:func:`load_observer` reads a model directory (``docs/model-format.md``) and builds a
:class:`KKLObserver` for any variant of :mod:`kklcasadi.model.variants` (``docs/design.md``):

=================  ==========================================================  ===================
method             latent dynamics                                             estimate
=================  ==========================================================  ===================
autonomous,        ``zdot = A z + B y``                                         ``T*(z)``
curriculum
obs                ``zdot = A z + B y + G(z, P GRU(w)) u``                      ``T*(z)``
                   (plus the ``inject`` term when the card sets
                   ``"model_based_injection": true``: a learned residual)
dyn                ``zdot = A z + B y``                                         ``T*(z; w)`` (LoRA)
inject             ``zdot = A z + B y + dT/dx(xhat) (f(xhat, u) - f(xhat, 0))``  ``T*(z)``
                   at ``xhat = T*(z)``, exact, from the encoder and the plant
obs_stream,        as obs / dyn, with the GRU context carried from sample to
dyn_stream         sample (one cell per step) instead of re-read from a window
=================  ==========================================================  ===================

At ``u = 0`` every variant's latent field is exactly (bitwise) the autonomous one: the learned
injection is ``G u``, the LoRA modulation vanishes for a zero window or context, and the
model-based term differences two evaluations of the same plant function. The estimates agree
bitwise when both observers use the same discretisation (e.g. ``discretization="rk4"`` for the
autonomous one); with the defaults (the exact step for linear latents, RK4 for ``obs`` and
``inject``) they differ by RK4's error: at most 4e-5 (Duffing), 6e-5 (Van der Pol), 1.9e-3
(FitzHugh-Nagumo) and 2.9e-3 (Roessler) on the shipped autonomous vs inject models, 20 zero-input
protocol trials.

Over 600 lines: one object's construction ties the step, its covariance and inflation, the domain check and the
runs (simulate, the integrator, the estimator) to the same Functions, so that they agree bitwise.

The observer state is ``(z_k, w_k)`` and the last measurement ``y_k``: over ``[t_k, t_k+1]`` the
latent ODE sees ``y`` interpolated linearly from ``y_k`` to ``y_k+1`` (first-order hold) and the
input held at ``u_k`` (``docs/protocol.md`` "Observer"). ``w_k`` is the observer's input memory
(:attr:`KKLObserver.memory`): for windowed variants the window of
:func:`kklcasadi.plant.windows.input_windows` (the last ``window`` input samples up to and including
``u_k``, oldest first, filled with ``u_0`` before ``t = 0``), for streaming ones ``[h_k; u_k]``.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Optional, Union

import casadi as ca
import numpy as np

from ..compiler import CompilerWarning
from ..estimate import Estimate
from ..model import variants
from ..model.files import CARD_FILE, Model, derive_model, load_model
from ..model.monitor import FeatureMonitor
from ..model.shipped import resolve
from ..model.variants import MODEL_BASED_INJECTION
from ..model.variants.inflation import fold
from ..nets.hold import foh_matrices
from ..plant import systems
from ..plant.rk4 import rk4_step
from ..plant.systems import System
from ..validation import positive_int
from .checks import (
    DISCRETIZATIONS,
    DOMAIN_MARGIN,
    box_rows,
    check_discretization,
    check_exact_only,
    check_finite,
    check_initial,
    check_samples,
    check_system,
    check_time,
    domain_bounds,
    domain_rows,
)
from .estimator import Estimator

__all__ = ["KKLObserver", "Estimate", "Estimator", "load_observer", "make_inject_model",
           "DISCRETIZATIONS", "INTEGRATOR_SOLVERS", "COMPILED_FROM", "MODEL_BASED_INJECTION", "DOMAIN_MARGIN"]

#: Steps (all trials together) from which :meth:`KKLObserver.simulate` runs the compiled step by default.
COMPILED_FROM = 20_000
#: ``ca.integrator`` plugins accepted by :meth:`KKLObserver.integrator`.
INTEGRATOR_SOLVERS = ("cvodes", "idas", "rk", "collocation")

PathLike = Union[str, os.PathLike]


class KKLObserver:
    """A learned KKL observer as CasADi Functions.

    Build it with :func:`load_observer`. All Functions have named inputs and outputs, accept
    numeric, SX or MX arguments, and can be used in ``Opti``, mapped, serialised
    (``obs.step.save(path)``) or compiled (:meth:`generate_c`).

    Parameters
    ----------
    model : kklcasadi.model.files.Model
        A loaded model directory.
    system : System
        The plant the model was trained for (its name and sizes must match the card).
    discretization : {"exact", "rk4"}, optional
        Discretisation of the latent ODE over one sample interval. Default: ``"exact"`` (matrix
        exponential with the first-order-hold terms) for the linear latent dynamics of
        ``autonomous``, ``curriculum`` and ``dyn``; ``"rk4"`` for ``obs`` and ``inject``, whose
        latent dynamics are nonlinear (``"exact"`` is refused for them).
    substeps : int
        RK4 steps per sample interval (``discretization="rk4"`` only).

    Attributes
    ----------
    method : str
        The card's method.
    system : System
    model : kklcasadi.model.files.Model
    nx, nu, ny, nz, window : int
        Sizes; ``w`` is (window, nu).
    dt : float
        Sample period.
    A, B : numpy.ndarray
        The latent design, (nz, nz) and (nz, ny).
    linear : bool
        Whether the latent dynamics are linear, so that the exact discretisation applies.
    model_based_injection : bool
        Whether ``zdot`` holds the model-based term (``inject``, or ``obs`` with the card field).
    discretization : str
    substeps : int
    foh_matrices : FOHMatrices or None
        ``Ad, Gy, Gy_next`` (:mod:`kklcasadi.nets.hold`) with ``z_k+1 = Ad z_k + Gy y_k + Gy_next y_k+1`` when
        ``discretization == "exact"`` and the latent is ``A z + B y`` (else None; a variant with
        more linear terms, such as ``bank``, brings its own exact step).
    encoder : casadi.Function or None
        ``encoder(x) -> z``, the exported T (the window-free one); None for ``bank``.
    rhs : casadi.Function
        ``rhs(z (nz,1), y (ny,1), u (nu,1), w (window,nu)) -> zdot (nz,1)``.
    decode : casadi.Function
        ``decode(z (nz,1), w (window,nu)) -> xhat (nx,1)``.
    step : casadi.Function
        ``step(z, w, y, y_next, u_next) -> (z_next, w_next, xhat_next)``: one sample interval, ``y``
        interpolated linearly from ``y`` to ``y_next``, ``u`` held at ``w[-1]``; ``w_next`` is ``w`` shifted by
        one with ``u_next`` appended and ``xhat_next = decode(z_next, w_next)``.
    model_injection : casadi.Function or None
        ``model_injection(z, u) -> dz``, the model-based term, when present.
    monitor : kklcasadi.model.monitor.FeatureMonitor or None
        The decoder-input domain monitor of the card's ``monitor`` entry, when present.
    spread : casadi.Function or None
        ``spread(z, w) -> s``: how far the members of a decoder ensemble disagree (a ``bank`` with
        ``members`` >= 2; :meth:`spread_of` over many samples); with the card's ``monitor.spread``
        the domain check also asks ``s`` <= its threshold. None for a single decoder.
    domain_check : casadi.Function or None
        ``domain_check(z, w, xhat) -> in_domain`` (1 or 0): the domain monitor of one sample (the
        card's boxes and, with :attr:`monitor`, the decoder's input ``[z; vec(w)]``); None when the
        card records neither. The C function ``name_in_domain`` of :func:`kklcasadi.generate_c`.
    decoded : casadi.Function or None
        ``decoded(z, w) -> (xhat, spread)``: :attr:`decode` and :attr:`spread` from one evaluation of the
        ensemble's members (the same values); None without a spread.
    domain_check_of_spread : casadi.Function or None
        ``(z, w, xhat, spread) -> in_domain``: :attr:`domain_check` with the spread given (from :attr:`decoded`);
        None where the check tests no spread.
    covariance : casadi.Function or None
        ``covariance(z, w, xhat) -> P (nx, nx)``: the covariance of the error of the estimate ``xhat`` at
        ``(z, w)``, from the card's covariance head (a ``bank`` with ``architecture.covariance``;
        :mod:`kklcasadi.model.variants.covariance`); None without one. The C function ``name_covariance``.
    step_covariance : casadi.Function or None
        ``step_covariance(z, w, y, y_next, u_next) -> (z_next, w_next, xhat_next, P_next)``: :attr:`step`
        with the covariance of ``xhat_next`` (its first three outputs are :attr:`step`'s, bit for bit);
        None without a covariance head. The C function ``name_step`` of a model with a head. With
        ``architecture.inflation`` (:attr:`inflation`, ``(m, y, xhat, P, z) -> (m_next, P_inflated)``) it carries ``m``
        (a sixth input, :attr:`inflation_start` first, and a fifth output) and inflates ``P_next`` (not the first's).
    step_covariance_spread : casadi.Function or None
        :attr:`step_covariance` and the ensemble's spread (a sixth output) where ``architecture.inflation.spread``
        reads it (estimate and spread from one run of the members, :attr:`decoded`); None otherwise.
    """

    def __init__(self, model: Model, system: System, *, discretization: Optional[str] = None,
                 substeps: int = 1) -> None:
        if not isinstance(model, Model):
            raise TypeError(f"model: expected a kklcasadi.model.files.Model (see load_model), "
                            f"received {type(model).__name__}.")
        if not isinstance(system, System):
            raise TypeError(f"system: expected a kklcasadi.System, received "
                            f"{type(system).__name__}.")
        spec = model.spec
        check_system(spec, system, str(model.path / CARD_FILE))
        self.model, self.system = model, system
        self.method: str = spec.method
        self.variant: variants.Variant = spec.variant
        self.nx, self.nu, self.ny = system.nx, system.nu, system.ny
        self.A, self.B = model.A, model.B
        self.nz = self.A.shape[0]
        self.dt, self.window = model.dt, model.window
        self.linear = self.variant.linear
        self.discretization = check_discretization(discretization, self.linear, self.method)
        self.substeps = positive_int(substeps, "substeps")
        self.domain = spec.domain
        self._domain_bounds = None if self.domain is None else domain_bounds(self.domain)
        self._domain_rows = None if self.domain is None else domain_rows(system, system.nx + self.domain.z_lo.size)

        nets = self.variant.networks(spec.architecture, model.arrays, system, self.window)
        self.exact_only = check_exact_only(nets.exact_only, "discretization", self.discretization, model.path)
        exact = self.discretization == "exact"
        self._exact_step = nets.exact_step if exact else None
        self.foh_matrices = foh_matrices(self.A, self.B, self.dt) if exact and nets.exact_step is None else None
        self.memory = nets.memory if nets.memory is not None else variants.window_memory(self.window, self.nu, self.ny)
        self.memory_shape: tuple[int, int] = self.memory.shape
        self.memory_init: ca.Function = self.memory.init
        self.encoder, self.model_injection = nets.encoder, nets.model_injection
        self._context, self._input_term = nets.context, nets.input_term
        self.model_based_injection = nets.model_injection is not None
        self._A, self._B = ca.sparsify(ca.DM(self.A)), ca.sparsify(ca.DM(self.B))

        z, w = ca.MX.sym("z", self.nz), ca.MX.sym("w", *self.memory_shape)
        y, u = ca.MX.sym("y", self.ny), ca.MX.sym("u", self.nu)
        self.decode = ca.Function("decode", [z, w], [nets.decoder(z, w)], ["z", "w"], ["xhat"])
        self.rhs = ca.Function("rhs", [z, y, u, w], [self._field(z, y, u, self._context_of(w))],
                               ["z", "y", "u", "w"], ["zdot"])
        self.covariance: Optional[ca.Function] = nets.covariance
        self.inflation: Optional[ca.Function] = nets.inflation
        self.inflation_start = np.zeros(0) if nets.inflation_start is None else nets.inflation_start   # its m_0
        self.decoded: Optional[ca.Function] = nets.decoded
        self.step, self.step_covariance, self.step_covariance_spread = self._build_step()
        self.monitor = None if spec.monitor is None else FeatureMonitor.from_arrays(spec.monitor, model.arrays)
        features = self.nz + self.memory_shape[0] * self.memory_shape[1]
        if self.monitor is not None and self.monitor.features != features:
            raise ValueError(f"{model.path / CARD_FILE}: 'monitor.features': expected the decoder's input size nz + "
                             f"memory = {features}, received {self.monitor.features}. Calibrate the monitor on this "
                             "model's decoder features (kklcasadi.model.monitor.calibrate).")
        self.spread = nets.spread
        if self.monitor is not None and self.monitor.spec.spread is not None and self.spread is None:
            raise ValueError(f"{model.path / CARD_FILE}: 'monitor.spread': expected a decoder ensemble (a 'bank' with "
                             "architecture.bank.members >= 2) for the spread test, received a single decoder. Remove "
                             "'monitor.spread' or add the members' networks.")
        self.domain_check, self.domain_check_of_spread = self._build_domain_check()
        self._trajectories: Optional[Any] = None                  # simulate's compiled trajectories, when first run

    # ------------------------------------------------------------------ construction
    def _context_of(self, w: ca.MX) -> Optional[ca.MX]:
        """What the latent field needs from the window, once per step (obs: ``P GRU(w)``)."""
        return None if self._context is None else self._context(w)

    def _field(self, z: ca.MX, y: ca.MX, u: ca.MX, context: Optional[ca.MX]) -> ca.MX:
        """``A z + B y`` plus the variant's input term, exactly 0 at ``u = 0``."""
        zdot = ca.mtimes(self._A, z) + ca.mtimes(self._B, y)
        if self._input_term is not None:
            zdot = zdot + self._input_term(z, u, context)
        return zdot

    def _build_step(self) -> tuple[ca.Function, Optional[ca.Function], Optional[ca.Function]]:
        """:attr:`step`, :attr:`step_covariance` and :attr:`step_covariance_spread` (the same expressions)."""
        z, w = ca.MX.sym("z", self.nz), ca.MX.sym("w", *self.memory_shape)
        y, y_next = ca.MX.sym("y", self.ny), ca.MX.sym("y_next", self.ny)
        u_next = ca.MX.sym("u_next", self.nu)
        if self.foh_matrices is not None:
            m = self.foh_matrices
            ad, gy, gy_next = (ca.sparsify(ca.DM(a)) for a in (m.Ad, m.Gy, m.Gy_next))
            z_next = ca.mtimes(ad, z) + ca.mtimes(gy, y) + ca.mtimes(gy_next, y_next)
        elif self._exact_step is not None:
            z_next = self._exact_step(z, y, y_next, self.memory.held(w))
        else:
            u = self.memory.held(w)
            context = self._context_of(w)
            z_next = rk4_step(lambda s, zz: self._field(zz, y + s * (y_next - y), u, context),
                              z, self.dt, self.substeps)
        w_next = self.memory.next(w, y_next, u_next)
        xhat_next = self.decode(z_next, w_next)
        names = ["z", "w", "y", "y_next", "u_next"], ["z_next", "w_next", "xhat_next"]
        step = ca.Function("step", [z, w, y, y_next, u_next], [z_next, w_next, xhat_next], *names)
        if self.covariance is None:
            return step, None, None
        spread = []              # the inflation's spread test: the estimate and the spread from one members' run
        if self.inflation is not None and self.inflation.n_in() == 6 and self.decoded is not None:
            xhat_next, *spread = self.decoded(z_next, w_next)
        P_next, state = self.covariance(z_next, w_next, xhat_next), ca.MX.sym("m", self.inflation_start.size)
        if self.inflation is None:
            return step, ca.Function("step_covariance", [z, w, y, y_next, u_next], [z_next, w_next, xhat_next, P_next],
                                     names[0], names[1] + ["P_next"]), None
        m_next, P_next = self.inflation(state, y_next, xhat_next, P_next, z_next, *spread)   # its state m, carried
        inputs, outputs = [z, w, y, y_next, u_next, state], [z_next, w_next, xhat_next, P_next, m_next]
        names = names[0] + ["m"], names[1] + ["P_next", "m_next"]
        return (step, ca.Function("step_covariance", inputs, outputs, *names),
                ca.Function("step_covariance_spread", inputs, outputs + spread, names[0], names[1] + ["spread"])
                if spread else None)

    def _build_domain_check(self) -> tuple[Optional[ca.Function], Optional[ca.Function]]:
        """:attr:`domain_check`, and where it tests the ensemble's spread the same check of a spread given
        (:attr:`domain_check_of_spread`)."""
        if self._domain_bounds is None and self.monitor is None:
            return None, None
        z, w, xhat = ca.MX.sym("z", self.nz), ca.MX.sym("w", *self.memory_shape), ca.MX.sym("xhat", self.nx)
        inside = ca.MX(1.0)
        if self._domain_bounds is not None:
            point, lo, hi = box_rows(ca.vertcat(xhat, z), self._domain_bounds, self._domain_rows)
            inside = ca.mmin(ca.vertcat(point - ca.DM(lo), ca.DM(hi) - point)) >= 0
        if self.monitor is not None:
            inside = ca.logic_and(inside, self.monitor.expression(ca.vertcat(z, ca.vec(w))))
        names = ["z", "w", "xhat"], ["in_domain"]
        if self.monitor is None or self.monitor.spec.spread is None or self.spread is None:
            return ca.Function("domain_check", [z, w, xhat], [inside], *names), None
        s, bound = ca.MX.sym("spread"), self.monitor.spec.spread[0]
        return (ca.Function("domain_check", [z, w, xhat], [ca.logic_and(inside, self.spread(z, w) <= bound)], *names),
                ca.Function("domain_check_of_spread", [z, w, xhat, s], [ca.logic_and(inside, s <= bound)],
                            names[0] + ["spread"], names[1]))

    def in_domain(self, xhat: Any, z: Any, w: Any = None) -> Optional[np.ndarray]:
        """Whether estimates lie in the domain the maps were trained on (the domain monitor).

        Parameters
        ----------
        xhat : array_like, shape (..., nx)
        z : array_like, shape (..., nz)
        w : array_like, shape (..., *memory_shape), optional
            The observer's memory at the same samples; needed where the model has a decoder-input
            monitor (:attr:`monitor`).

        Returns
        -------
        numpy.ndarray of bool, shape (...), or None
            True where ``xhat`` and ``z`` are within the card's state and latent boxes, widened by
            :data:`DOMAIN_MARGIN` of their ranges, and (with a decoder-input monitor) where
            ``[z; vec(w)]`` is within the monitor's threshold of its nearest prototype (``vec``
            column-major, as ``ca.vec``) and, with the monitor's ``spread`` test, where the
            decoder ensemble's members agree within its threshold (:meth:`spread_of`); None when
            the model records neither.
        """
        return self._in_domain(xhat, z, w)

    def _in_domain(self, xhat: Any, z: Any, w: Any, spread: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
        """:meth:`in_domain`, with the ensemble's ``spread`` at the samples where it was computed already."""
        if self._domain_bounds is None and self.monitor is None:
            return None
        xhat, z = np.asarray(xhat, dtype=float), np.asarray(z, dtype=float)
        inside = np.ones(xhat.shape[:-1], dtype=bool)
        if self._domain_bounds is not None:
            point, lo, hi = box_rows(np.concatenate([xhat, z], axis=-1), self._domain_bounds, self._domain_rows)
            inside &= np.all((point >= lo) & (point <= hi), axis=-1)
        if self.monitor is not None:
            if w is None:
                raise ValueError(f"w: expected the observer's memory (shape (..., {self.memory_shape[0]}, "
                                 f"{self.memory_shape[1]})) for the decoder-input monitor, received None.")
            w = np.asarray(w, dtype=float)
            if w.shape != z.shape[:-1] + self.memory_shape:
                raise ValueError(f"w: expected shape {z.shape[:-1] + self.memory_shape}, received {w.shape}.")
            flat = np.swapaxes(w, -1, -2).reshape(z.shape[:-1] + (-1,))          # column-major vec
            inside &= self.monitor.inside(np.concatenate([z, flat], axis=-1))
            if self.monitor.spec.spread is not None:
                inside &= (self.spread_of(z, w) if spread is None else spread) <= self.monitor.spec.spread[0]
        return inside

    def spread_of(self, z: Any, w: Any) -> np.ndarray:
        """How far the members of the decoder ensemble disagree at each sample (:attr:`spread`).

        Parameters
        ----------
        z : array_like, shape (..., nz)
        w : array_like, shape (..., *memory_shape)

        Returns
        -------
        numpy.ndarray, shape (...)
        """
        if self.spread is None:
            raise ValueError(f"observer: expected a decoder ensemble (architecture.bank.members >= 2) for a spread, "
                             f"received {self!r} with a single decoder.")
        z, w = np.asarray(z, dtype=float), np.asarray(w, dtype=float)
        lead = z.shape[:-1]
        if z.shape[-1:] != (self.nz,) or w.shape != lead + self.memory_shape:
            raise ValueError(f"z, w: expected shapes (..., {self.nz}) and (..., {self.memory_shape[0]}, "
                             f"{self.memory_shape[1]}) with one leading shape, received {z.shape} and {w.shape}.")
        n = int(np.prod(lead)) if lead else 1
        zz = z.reshape(n, self.nz).T
        ww = np.swapaxes(w.reshape((n,) + self.memory_shape), 0, 1).reshape(self.memory_shape[0], -1)
        return np.asarray(self.spread.map(n)(zz, ww)).reshape(lead)

    def __repr__(self) -> str:
        return (f"KKLObserver(method={self.method!r}, system={self.system.name!r}, nz={self.nz}, "
                f"window={self.window}, dt={self.dt}, discretization={self.discretization!r})")

    # ------------------------------------------------------------------ use
    def integrator(self, solver: str = "cvodes", **opts: Any) -> ca.Function:
        """The latent ODE over one sample interval as a :func:`casadi.integrator`.

        The parameter vector is ``p = [y_k; y_k+1; u; vec(w)]`` (``vec`` column-major, as
        ``ca.vec``), and the first-order hold is written with the integrator's time ``t`` in
        ``[0, dt]``: ``y(t) = y_k + t / dt (y_k+1 - y_k)``.

        Parameters
        ----------
        solver : {"cvodes", "idas", "rk", "collocation"}
        **opts
            Options of :func:`casadi.integrator` (e.g. ``abstol``, ``reltol``,
            ``number_of_finite_elements``).

        Returns
        -------
        casadi.Function
            The integrator: ``x0`` is ``z_k`` (nz, 1), ``p`` (2 ny + nu + window nu, 1), ``xf`` is ``z_k+1``.
        """
        if solver not in INTEGRATOR_SOLVERS:
            raise ValueError(f"solver: expected one of {list(INTEGRATOR_SOLVERS)}, received {solver!r}.")
        check_exact_only(self.exact_only, "integrator", solver, self.model.path)
        z, t = ca.MX.sym("z", self.nz), ca.MX.sym("t")
        rows, cols = self.memory_shape
        p = ca.MX.sym("p", 2 * self.ny + self.nu + rows * cols)
        y, y_next, u, w = ca.vertsplit(p, np.cumsum([0, self.ny, self.ny, self.nu, rows * cols]).tolist())
        ode = self.rhs(z, y + t / self.dt * (y_next - y), u, ca.reshape(w, rows, cols))   # y first-order hold
        return ca.integrator(f"{self.method}_latent", solver, {"x": z, "p": p, "t": t, "ode": ode}, 0.0, self.dt, opts)

    def simulate(self, t: Any, y: Any, u: Any, *, z0: Any = None,
                 n_threads: Optional[int] = None, vm: Optional[bool] = None) -> Estimate:
        """Run the observer on sampled measurements and inputs.

        ``z_0 = 0`` (or ``z0``), ``w_0 = memory_init(y_0, u_0)`` (the window filled with ``u_0``),
        ``xhat_0 = decode(z_0, w_0)``; then :attr:`step` over every interval, mapped over the trials on
        threads: compiled to C (:mod:`kklcasadi.observer.compiled`: gcc, cached on disk, a chunk of samples
        per call; bitwise the CasADi VM's values) where the trials hold at least :data:`COMPILED_FROM` steps
        in all, else one ``mapaccum`` per trajectory in the CasADi VM (a first compile costs about a
        second, a cached library's look-up a fraction of one: more than a short run in the VM).

        Parameters
        ----------
        t : array_like, shape (N,)
            Sample times ``t_k``, spaced by ``dt``.
        y : array_like, shape (N, ny) or (M, N, ny)
            Measurements (``(N,)`` is accepted when ny = 1).
        u : array_like, shape (N, nu) or (M, N, nu)
            Inputs, held over ``[t_k, t_k+1)`` (``(N,)`` is accepted when nu = 1).
        z0 : array_like, shape (nz,) or (M, nz), optional
            Initial latent state; default 0 (docs/protocol.md). ``(nz,)`` is used for every trial.
        n_threads : int, optional
            Worker threads for M trials (default: the CPU count).
        vm : bool, optional
            True: the CasADi VM; False: the compiled step whatever the length; None (default): by the
            length, as above. Where the compiled step is due and there is no C compiler, the VM runs
            with a one-line :class:`~kklcasadi.compiler.CompilerWarning` (the same values).

        Returns
        -------
        Estimate
            ``xhat`` (N, nx), ``z`` (N, nz) and ``in_domain`` (N,) (None where the model records no domain),
            or (M, N, .) when ``y`` and ``u`` are 3-D; ``var`` and ``stats`` None.

        Raises
        ------
        ValueError
            Wrong shapes (naming the argument, the expected and the received shape), ``t`` not
            spaced by ``dt``, or a NaN/inf in ``y`` or ``u`` (naming the trial and sample) or
            in ``z0``.
        """
        if n_threads is not None:
            positive_int(n_threads, "n_threads")
        if vm is not None and not isinstance(vm, bool):
            raise TypeError(f"vm: expected True, False or None, received {type(vm).__name__}.")
        t = check_time(t, self.dt)
        n = t.size
        ys, batched_y = check_samples(y, "y", n, self.ny)
        us, batched_u = check_samples(u, "u", n, self.nu)
        if batched_y != batched_u or ys.shape[0] != us.shape[0]:
            raise ValueError(f"y and u: expected the same number of trials (both (N, .) or both "
                             f"(M, N, .)), received y {np.shape(y)} and u {np.shape(u)}.")
        for name, values in (("y", ys), ("u", us)):
            check_finite(values, name, t, batched_y)
        m, nz, nu = ys.shape[0], self.nz, self.nu
        z_start = check_initial(z0, m, nz, batched_y)                          # (nz, M)

        w0_cols = self.memory_init.map(m)(ys[:, 0].T, us[:, 0].T)          # (rows, M cols)
        xhat = np.empty((m, n, self.nx))
        z = np.empty((m, n, nz))
        xhat[:, 0] = np.asarray(self.decode.map(m)(z_start, w0_cols)).T
        z[:, 0] = z_start.T
        nx = self.nx
        cov = None if self.covariance is None else np.empty((m, n, nx, nx))
        if self.covariance is not None and cov is not None:
            cov[:, 0] = _blocks(self.covariance.map(m)(z_start, w0_cols, xhat[:, 0].T), nx).reshape(m, nx, nx)
        rows, cols = self.memory_shape
        memory = np.empty((m, n, rows, cols)) if self.monitor is not None else None
        if memory is not None:
            memory[:, 0] = np.asarray(w0_cols).reshape(rows, m, cols).transpose(1, 0, 2)
        threads = (os.cpu_count() or 1) if n_threads is None else n_threads
        due = n > 1 and (vm is False or (vm is None and m * (n - 1) >= COMPILED_FROM))
        compiled = self._compiled() if due else None
        spread = None
        if compiled is not None:
            z[:, 1:], w_steps, xhat[:, 1:], P_steps, spread_steps = compiled.run(z_start, np.asarray(w0_cols), ys,
                                                                                 us, n_threads=threads)
            if memory is not None:
                memory[:, 1:] = w_steps
            if cov is not None:
                cov[:, 1:] = P_steps
            if spread_steps is not None and self.spread is not None:   # the monitor's spread, computed with the steps
                spread = np.empty((m, n))
                spread[:, 0] = np.asarray(self.spread.map(m)(z_start, w0_cols)).ravel()
                spread[:, 1:] = spread_steps
        elif n > 1:
            step = self.step if cov is None or self.step_covariance is None else self.step_covariance
            trajectory = fold(step, "trajectory", n - 1)
            if m > 1:
                trajectory = trajectory.map(m, "thread", min(threads, m))
            columns = m * (n - 1)
            z_out, w_out, xhat_out, *P_out = trajectory(                        # (and m_0 where it is carried)
                z_start, w0_cols, ys[:, :-1].reshape(columns, self.ny).T, ys[:, 1:].reshape(columns, self.ny).T,
                us[:, 1:].reshape(columns, nu).T, *[np.tile(self.inflation_start[:, None], (1, m))][:step.n_in() - 5])
            if cov is not None:               # (nx, nx * columns): block j is the covariance of column j
                cov[:, 1:] = _blocks(P_out[0], nx).reshape(m, n - 1, nx, nx)
            z[:, 1:] = np.asarray(z_out).T.reshape(m, n - 1, nz)
            xhat[:, 1:] = np.asarray(xhat_out).T.reshape(m, n - 1, self.nx)
            if memory is not None:
                memory[:, 1:] = np.asarray(w_out).reshape(rows, m, n - 1, cols).transpose(1, 2, 0, 3)
        flags = self._in_domain(xhat, z, memory, spread)
        for array in (xhat, z, flags, cov):
            if array is not None:
                array.setflags(write=False)
        if batched_y:
            return Estimate(t, xhat, z=z, in_domain=flags, cov=cov)
        return Estimate(t, xhat[0], z=z[0], in_domain=None if flags is None else flags[0],
                        cov=None if cov is None else cov[0])

    def _compiled(self) -> Optional[Any]:
        """The compiled trajectories of :meth:`simulate` (:class:`~kklcasadi.observer.compiled.CompiledTrajectory`),
        or None with a one-line :class:`~kklcasadi.compiler.CompilerWarning` where there is no C compiler."""
        from .compiled import BITWISE, CompiledTrajectory  # here, not above: the C kernels' package imports this module

        if not BITWISE.available():
            warnings.warn(f"C compiler {BITWISE.command!r} not found on PATH; KKLObserver.simulate runs the CasADi VM "
                          "(slower, the same values). Install gcc, or pass vm=True to choose the VM.", CompilerWarning,
                          stacklevel=3)
            return None
        if self._trajectories is None:
            self._trajectories = CompiledTrajectory(self)
        return self._trajectories

    def estimator(self, *, guard: Any = None) -> Estimator:
        """A stateful, do-mpc-style estimator: ``xhat = est.make_step(y, u)`` per sample.

        ``guard``: a :class:`kklcasadi.observer.guard.SampleGuard`, with which one absurd sample does
        not poison the rest of the run (:func:`kklcasadi.observer.guard.guarded_estimator` passes the
        model's own).
        """
        return Estimator(self, guard=guard)


def _blocks(matrix: Any, nx: int) -> np.ndarray:
    """The (nx, nx) blocks of a mapped Function's output (nx, nx C), as (C, nx, nx)."""
    return np.asarray(matrix).reshape(nx, -1, nx).transpose(1, 0, 2)


# ---------------------------------------------------------------------- loading
def load_observer(path: PathLike, *, system: Optional[System] = None,
                  discretization: Optional[str] = None, substeps: int = 1) -> KKLObserver:
    """Load a model directory, or a shipped model by name, as a :class:`KKLObserver` (no torch needed).

    Parameters
    ----------
    path : str or path-like
        A model directory (``weights.npz`` + ``card.json``), or the name of a shipped model,
        ``"SYSTEM/METHOD"`` such as ``"duffing/bank"``, from any directory (a directory of that
        name that exists where it is given wins; :func:`kklcasadi.model.shipped.resolve`).
    system : System, optional
        The plant; default ``kklcasadi.plant.systems.get(card["system"]["name"])``. Its name, nx, nu
        and ny must match the card. A plant with parameters (a family) is taken at its nominal values
        (:meth:`kklcasadi.System.at`): the model was trained for the family, and its card records the
        nominal plant and, in ``training.params``, the box the runs drew from.
    discretization : {"exact", "rk4"}, optional
        See :class:`KKLObserver`.
    substeps : int
        RK4 steps per sample interval.

    Returns
    -------
    KKLObserver

    Raises
    ------
    ValueError
        A damaged or inconsistent model directory (see :func:`kklcasadi.model.files.load_model`),
        an unregistered system name without ``system``, or a system that does not match the card.
    """
    model = load_model(resolve(path))
    if system is None:
        name = model.card["system"]["name"]
        if name not in systems.names():
            raise ValueError(f"{model.path / CARD_FILE}: 'system.name': {name!r} is not a "
                             f"registered system (known: {', '.join(systems.names())}). Pass the "
                             "plant: load_observer(path, system=kc.System(...)).")
        system = variants.copies.copies_plant(model.card, model.path / CARD_FILE) or systems.get(name)
    elif isinstance(system, System) and system.n_params:
        system = system.at(system.param_nominal)
    return KKLObserver(model, system, discretization=discretization, substeps=substeps)


def make_inject_model(base: PathLike, out_dir: PathLike, *, overwrite: bool = False) -> Path:
    """Write an ``inject`` model from an autonomous (or curriculum) model; no training.

    Same as :func:`kklcasadi.model.files.derive_model` with ``method="inject"``.

    Parameters
    ----------
    base : str or path-like
        A model directory with method ``autonomous`` or ``curriculum``.
    out_dir : str or path-like
        Where to write the ``inject`` model (e.g. ``models/duffing/inject``).
    overwrite : bool
        Replace an existing model in ``out_dir``.

    Returns
    -------
    Path
        The new model directory.
    """
    return derive_model(base, out_dir, "inject", overwrite=overwrite)
