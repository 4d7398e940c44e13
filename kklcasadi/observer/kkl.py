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

The observer state is ``(z_k, w_k)`` and the last measurement ``y_k``: over ``[t_k, t_k+1]`` the
latent ODE sees ``y`` interpolated linearly from ``y_k`` to ``y_k+1`` (first-order hold) and the
input held at ``u_k`` (``docs/protocol.md`` "Observer"). ``w_k`` is the observer's input memory
(:attr:`KKLObserver.memory`): for windowed variants the window of
:func:`kklcasadi.plant.windows.input_windows` (the last ``window`` input samples up to and including
``u_k``, oldest first, filled with ``u_0`` before ``t = 0``), for streaming ones ``[h_k; u_k]``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Union

import casadi as ca
import numpy as np

from ..model import variants
from ..model.card import ModelSpec
from ..model.files import CARD_FILE, Model, derive_model, load_model
from ..model.monitor import FeatureMonitor
from ..model.shipped import resolve
from ..model.variants import MODEL_BASED_INJECTION
from ..nets.hold import foh_matrices
from ..plant import systems
from ..plant.rk4 import rk4_step
from ..plant.systems import System
from ..validation import positive_int

__all__ = ["KKLObserver", "Estimate", "Estimator", "load_observer", "make_inject_model",
           "DISCRETIZATIONS", "INTEGRATOR_SOLVERS", "MODEL_BASED_INJECTION", "DOMAIN_MARGIN"]

#: Relative margin of the domain monitor: estimates up to this share of the trained range outside
#: it still count as in the domain (a transient grazing the edge is not flagged).
DOMAIN_MARGIN = 0.1
#: Discretisations of the latent ODE over one sample interval.
DISCRETIZATIONS = ("exact", "rk4")
#: ``ca.integrator`` plugins accepted by :meth:`KKLObserver.integrator`.
INTEGRATOR_SOLVERS = ("cvodes", "idas", "rk", "collocation")

PathLike = Union[str, os.PathLike]


@dataclass(frozen=True, eq=False)
class Estimate:
    """An observer run on a sampled trajectory.

    Attributes
    ----------
    t : numpy.ndarray, shape (N,)
        Sample times.
    xhat : numpy.ndarray, shape (N, nx) or (M, N, nx)
        State estimates ``xhat_k``; ``(M, N, nx)`` for M trials.
    z : numpy.ndarray, shape (N, nz) or (M, N, nz)
        Latent states ``z_k``, ``z_0 = 0``.
    in_domain : numpy.ndarray of bool, shape (N,) or (M, N), or None
        The domain monitor per sample (:meth:`KKLObserver.in_domain`): whether ``(xhat_k, z_k)``
        lies in the trained boxes (with the margin :data:`DOMAIN_MARGIN`) and, where the model has a
        decoder-input monitor, whether the decoder's input ``[z_k; vec(w_k)]`` lies within its
        threshold of the fitting data; None when the model records neither.
    """

    t: np.ndarray
    xhat: np.ndarray
    z: np.ndarray
    in_domain: Optional[np.ndarray] = None


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
        ``step(z, w, y, y_next, u_next) -> (z_next, w_next, xhat_next)``: one sample interval,
        ``y`` interpolated linearly from ``y`` to ``y_next``, ``u`` held at ``w[-1]``;
        ``w_next`` is ``w`` shifted by one with ``u_next`` appended and
        ``xhat_next = decode(z_next, w_next)``.
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
        _check_system(spec, system, str(model.path / CARD_FILE))
        self.model, self.system = model, system
        self.method: str = spec.method
        self.variant: variants.Variant = spec.variant
        self.nx, self.nu, self.ny = system.nx, system.nu, system.ny
        self.A, self.B = model.A, model.B
        self.nz = self.A.shape[0]
        self.dt, self.window = model.dt, model.window
        self.linear = self.variant.linear
        self.discretization = _check_discretization(discretization, self.linear, self.method)
        self.substeps = positive_int(substeps, "substeps")
        self.domain = spec.domain
        self._domain_bounds = None if self.domain is None else _domain_bounds(self.domain)

        nets = self.variant.networks(spec.architecture, model.arrays, system, self.window)
        exact = self.discretization == "exact"
        self._exact_step = nets.exact_step if exact else None
        self.foh_matrices = (foh_matrices(self.A, self.B, self.dt)
                             if exact and nets.exact_step is None else None)
        self.memory = nets.memory if nets.memory is not None else variants.window_memory(self.window, self.nu, self.ny)
        self.memory_shape: tuple[int, int] = self.memory.shape
        self.memory_init: ca.Function = self.memory.init
        self.encoder = nets.encoder
        self._context, self._input_term = nets.context, nets.input_term
        self.model_injection = nets.model_injection
        self.model_based_injection = nets.model_injection is not None
        self._A, self._B = ca.sparsify(ca.DM(self.A)), ca.sparsify(ca.DM(self.B))

        z, w = ca.MX.sym("z", self.nz), ca.MX.sym("w", *self.memory_shape)
        y, u = ca.MX.sym("y", self.ny), ca.MX.sym("u", self.nu)
        self.decode = ca.Function("decode", [z, w], [nets.decoder(z, w)], ["z", "w"], ["xhat"])
        self.rhs = ca.Function("rhs", [z, y, u, w], [self._field(z, y, u, self._context_of(w))],
                               ["z", "y", "u", "w"], ["zdot"])
        self.step = self._build_step()
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
        self.domain_check = self._build_domain_check()

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

    def _build_step(self) -> ca.Function:
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
        return ca.Function("step", [z, w, y, y_next, u_next],
                           [z_next, w_next, self.decode(z_next, w_next)],
                           ["z", "w", "y", "y_next", "u_next"], ["z_next", "w_next", "xhat_next"])

    def _build_domain_check(self) -> Optional[ca.Function]:
        if self._domain_bounds is None and self.monitor is None:
            return None
        z, w, xhat = ca.MX.sym("z", self.nz), ca.MX.sym("w", *self.memory_shape), ca.MX.sym("xhat", self.nx)
        inside = ca.MX(1.0)
        if self._domain_bounds is not None:
            lo, hi = (ca.DM(b) for b in self._domain_bounds)
            point = ca.vertcat(xhat, z)
            inside = ca.mmin(ca.vertcat(point - lo, hi - point)) >= 0
        if self.monitor is not None:
            inside = ca.logic_and(inside, self.monitor.expression(ca.vertcat(z, ca.vec(w))))
            if self.monitor.spec.spread is not None:
                inside = ca.logic_and(inside, self.spread(z, w) <= self.monitor.spec.spread[0])
        return ca.Function("domain_check", [z, w, xhat], [inside], ["z", "w", "xhat"], ["in_domain"])

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
        if self._domain_bounds is None and self.monitor is None:
            return None
        xhat, z = np.asarray(xhat, dtype=float), np.asarray(z, dtype=float)
        inside = np.ones(xhat.shape[:-1], dtype=bool)
        if self._domain_bounds is not None:
            point = np.concatenate([xhat, z], axis=-1)
            lo, hi = self._domain_bounds
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
                inside &= self.spread_of(z, w) <= self.monitor.spec.spread[0]
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
            The integrator: ``x0`` is ``z_k`` (nz, 1), ``p`` (2 ny + nu + window nu, 1), ``xf``
            is ``z_k+1``.
        """
        if solver not in INTEGRATOR_SOLVERS:
            raise ValueError(f"solver: expected one of {list(INTEGRATOR_SOLVERS)}, received "
                             f"{solver!r}.")
        z, t = ca.MX.sym("z", self.nz), ca.MX.sym("t")
        rows, cols = self.memory_shape
        p = ca.MX.sym("p", 2 * self.ny + self.nu + rows * cols)
        y, y_next, u, w = ca.vertsplit(p, np.cumsum([0, self.ny, self.ny, self.nu, rows * cols]).tolist())
        y_t = y + t / self.dt * (y_next - y)
        ode = self.rhs(z, y_t, u, ca.reshape(w, rows, cols))
        return ca.integrator(f"{self.method}_latent", solver, {"x": z, "p": p, "t": t, "ode": ode},
                             0.0, self.dt, opts)

    def simulate(self, t: Any, y: Any, u: Any, *, z0: Any = None,
                 n_threads: Optional[int] = None) -> Estimate:
        """Run the observer on sampled measurements and inputs.

        ``z_0 = 0`` (or ``z0``), ``w_0 = memory_init(y_0, u_0)`` (the window filled with ``u_0``),
        ``xhat_0 = decode(z_0, w_0)``; then :attr:`step` over every interval, as one ``mapaccum``
        call per trajectory and one ``map(M, "thread")`` over trials.

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

        Returns
        -------
        Estimate
            ``xhat`` (N, nx) and ``z`` (N, nz), or (M, N, .) when ``y`` and ``u`` are 3-D.

        Raises
        ------
        ValueError
            Wrong shapes (naming the argument, the expected and the received shape), ``t`` not
            spaced by ``dt``, or a NaN/inf in ``y`` or ``u`` (naming the trial and sample) or
            in ``z0``.
        """
        if n_threads is not None:
            positive_int(n_threads, "n_threads")
        t = _check_time(t, self.dt)
        n = t.size
        ys, batched_y = _check_samples(y, "y", n, self.ny)
        us, batched_u = _check_samples(u, "u", n, self.nu)
        if batched_y != batched_u or ys.shape[0] != us.shape[0]:
            raise ValueError(f"y and u: expected the same number of trials (both (N, .) or both "
                             f"(M, N, .)), received y {np.shape(y)} and u {np.shape(u)}.")
        for name, values in (("y", ys), ("u", us)):
            _check_finite(values, name, t, batched_y)
        m, nz, nu = ys.shape[0], self.nz, self.nu
        z_start = _check_initial(z0, m, nz, batched_y)                          # (nz, M)

        w0_cols = self.memory_init.map(m)(ys[:, 0].T, us[:, 0].T)          # (rows, M cols)
        xhat = np.empty((m, n, self.nx))
        z = np.empty((m, n, nz))
        xhat[:, 0] = np.asarray(self.decode.map(m)(z_start, w0_cols)).T
        z[:, 0] = z_start.T
        rows, cols = self.memory_shape
        memory = np.empty((m, n, rows, cols)) if self.monitor is not None else None
        if memory is not None:
            memory[:, 0] = np.asarray(w0_cols).reshape(rows, m, cols).transpose(1, 0, 2)
        if n > 1:
            trajectory = self.step.mapaccum("trajectory", n - 1, [0, 1], [0, 1])
            if m > 1:
                threads = (os.cpu_count() or 1) if n_threads is None else n_threads
                trajectory = trajectory.map(m, "thread", min(threads, m))
            columns = m * (n - 1)
            z_out, w_out, xhat_out = trajectory(
                z_start, w0_cols,
                ys[:, :-1].reshape(columns, self.ny).T, ys[:, 1:].reshape(columns, self.ny).T,
                us[:, 1:].reshape(columns, nu).T)
            z[:, 1:] = np.asarray(z_out).T.reshape(m, n - 1, nz)
            xhat[:, 1:] = np.asarray(xhat_out).T.reshape(m, n - 1, self.nx)
            if memory is not None:
                memory[:, 1:] = np.asarray(w_out).reshape(rows, m, n - 1, cols).transpose(1, 2, 0, 3)
        flags = self.in_domain(xhat, z, memory)
        for array in (xhat, z) if flags is None else (xhat, z, flags):
            array.setflags(write=False)
        if batched_y:
            return Estimate(t, xhat, z, flags)
        return Estimate(t, xhat[0], z[0], None if flags is None else flags[0])

    def estimator(self) -> Estimator:
        """A stateful, do-mpc-style estimator: ``xhat = est.make_step(y, u)`` per sample."""
        return Estimator(self)


class Estimator:
    """Stateful form of a :class:`KKLObserver`, for loops that receive one sample at a time.

    ``make_step(y_k, u_k)`` returns ``xhat_k``; the sequence equals :meth:`KKLObserver.simulate`
    sample by sample. The first call initialises ``z_0 = 0`` and the window with ``u_0``.

    Parameters
    ----------
    observer : KKLObserver

    Attributes
    ----------
    observer : KKLObserver
    k : int
        Samples taken since the start or the last :meth:`reset`.
    """

    def __init__(self, observer: KKLObserver) -> None:
        if not isinstance(observer, KKLObserver):
            raise TypeError(f"observer: expected a KKLObserver, received "
                            f"{type(observer).__name__}.")
        self.observer = observer
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next :meth:`make_step` starts again from ``z = 0``."""
        self._z: Optional[np.ndarray] = None
        self._w: Optional[np.ndarray] = None
        self._y: Optional[np.ndarray] = None
        self.k = 0
        self._in_domain: Optional[bool] = None
        self._out_of_domain = 0

    @property
    def z(self) -> Optional[np.ndarray]:
        """Latent state ``z_k`` (nz,) after the last step, or None before the first."""
        return None if self._z is None else self._z.copy()

    @property
    def w(self) -> Optional[np.ndarray]:
        """Input memory ``w_k`` (``observer.memory_shape``; the window (window, nu) for windowed
        variants) after the last step, or None before the first."""
        return None if self._w is None else self._w.copy()

    def make_step(self, y: Any, u: Any) -> np.ndarray:
        """Feed ``y_k`` and ``u_k`` (the input held from ``t_k``); return the estimate ``xhat_k``.

        Parameters
        ----------
        y : array_like, shape (ny,)
        u : array_like, shape (nu,)

        Returns
        -------
        numpy.ndarray, shape (nx,)
        """
        obs = self.observer
        y = _check_sample(y, "y", obs.ny, self.k)
        u = _check_sample(u, "u", obs.nu, self.k)
        if self._z is None:
            z, w = np.zeros(obs.nz), np.asarray(obs.memory_init(y, u))
            xhat = obs.decode(z, w)
        else:
            z_next, w, xhat = obs.step(self._z, self._w, self._y, y, u)
            z, w = np.asarray(z_next).ravel(), np.asarray(w)
        self._z, self._w, self._y = z, w, y
        self.k += 1
        xhat = np.asarray(xhat).ravel()
        inside = obs.in_domain(xhat, z, w)
        self._in_domain = None if inside is None else bool(inside)
        self._out_of_domain += inside is not None and not inside
        return xhat

    @property
    def stats(self) -> dict:
        """What the last :meth:`make_step` did: ``k`` (samples taken), ``in_domain`` (whether the
        last estimate lies in the trained domain, None without a recorded domain) and
        ``out_of_domain_steps`` (how many estimates so far did not)."""
        return {"k": self.k, "in_domain": self._in_domain, "out_of_domain_steps": self._out_of_domain}


# ---------------------------------------------------------------------- checks
def _domain_bounds(domain: Any) -> tuple[np.ndarray, np.ndarray]:
    """``[x; z]`` lower and upper bounds of the domain monitor, widened by :data:`DOMAIN_MARGIN`."""
    lo = np.concatenate([domain.x_lo, domain.z_lo])
    hi = np.concatenate([domain.x_hi, domain.z_hi])
    margin = DOMAIN_MARGIN * np.maximum(hi - lo, 1e-9)
    return lo - margin, hi + margin


def _check_system(spec: ModelSpec, system: System, where: str) -> None:
    expected = spec.system
    if system.name != expected.name:
        raise ValueError(f"{where}: 'system.name': the model was trained for {expected.name!r}, "
                         f"received the system {system.name!r}. Pass the plant the model was "
                         "trained for, or load the model trained for this plant.")
    for key in ("nx", "nu", "ny"):
        if getattr(system, key) != getattr(expected, key):
            raise ValueError(f"{where}: 'system.{key}': the model expects {key} = "
                             f"{getattr(expected, key)}, the system {system.name!r} has {key} = "
                             f"{getattr(system, key)}. Pass the plant the model was trained for.")
    if expected.fingerprint is not None and system.fingerprint != expected.fingerprint:
        raise ValueError(f"{where}: 'system.fingerprint': the model was trained for a plant {expected.name!r} "
                         f"with other dynamics or another box (fingerprint {expected.fingerprint[:12]}..., the plant "
                         f"passed has {system.fingerprint[:12]}...). Pass the plant the model was trained for, "
                         "or train a model for this plant.")


def _check_discretization(discretization: Optional[str], linear: bool, method: str) -> str:
    if discretization is None:
        return "exact" if linear else "rk4"
    if discretization not in DISCRETIZATIONS:
        raise ValueError(f"discretization: expected one of {list(DISCRETIZATIONS)} or None, "
                         f"received {discretization!r}.")
    if discretization == "exact" and not linear:
        raise ValueError(f"discretization: 'exact' needs linear latent dynamics; method {method!r}"
                         " has an input term that depends on z. Use 'rk4' (the default).")
    return discretization


def _check_time(t: Any, dt: float) -> np.ndarray:
    given = np.asarray(t)
    eps = np.finfo(given.dtype).eps if np.issubdtype(given.dtype, np.floating) else np.finfo(float).eps
    t = given.astype(float)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"t: expected sample times of shape (N,), N >= 1, received shape "
                         f"{t.shape}.")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"t: expected finite sample times, received a NaN/inf at sample "
                         f"{int(np.argmin(np.isfinite(t)))}.")
    steps = np.diff(t)
    # the spacing of stored times is exact to the rounding of their dtype (float32 times: ~1e-6 s at t = 50 s)
    tolerance = max(1e-9 * dt, 1e-12 * max(1.0, abs(t[-1])), 2 * eps * max(1.0, float(np.max(np.abs(t)))))
    if steps.size and not np.all(np.abs(steps - dt) <= tolerance):
        k = int(np.argmax(np.abs(steps - dt)))
        raise ValueError(f"t: expected samples spaced by the observer's dt = {dt}, received "
                         f"t[{k + 1}] - t[{k}] = {steps[k]}. Resample the data at dt.")
    return t


def _check_samples(values: Any, argument: str, n: int, dim: int) -> tuple[np.ndarray, bool]:
    """Return ``values`` as (M, N, dim) and whether it was given with a trial axis."""
    array = np.asarray(values, dtype=float)
    if array.ndim == 1 and dim == 1:
        array = array[:, None]
    if array.ndim == 2 and array.shape == (n, dim):
        return array[None], False
    if array.ndim == 3 and array.shape[1:] == (n, dim) and array.shape[0] >= 1:
        return array, True
    raise ValueError(f"{argument}: expected shape (N, {dim}) or (M, N, {dim}) with N = {n} "
                     f"samples (the length of t), received {np.shape(values)}.")


def _check_finite(values: np.ndarray, argument: str, t: np.ndarray, batched: bool) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        trial, k, _ = (int(i) for i in np.argwhere(bad)[0])
        at = f"trial {trial}, sample {k}" if batched else f"sample {k}"
        raise ValueError(f"{argument}: expected finite values, received "
                         f"{values[trial, k].tolist()} at {at} (t = {t[k]:.6g}). Remove or "
                         "repair the bad samples before running the observer.")


def _check_initial(z0: Any, m: int, nz: int, batched: bool) -> np.ndarray:
    """The initial latent states as columns (nz, M); 0 by default."""
    if z0 is None:
        return np.zeros((nz, m))
    array = np.asarray(z0, dtype=float)
    if array.shape == (nz,):
        array = np.repeat(array[None], m, axis=0)
    elif not (batched and array.shape == (m, nz)):
        expected = f"({nz},) or (M, {nz}) = ({m}, {nz})" if batched else f"({nz},)"
        raise ValueError(f"z0: expected shape {expected}, received {array.shape}.")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"z0: expected finite values, received {array.tolist()}.")
    return np.ascontiguousarray(array.T)


def _check_sample(value: Any, argument: str, dim: int, k: int) -> np.ndarray:
    array = np.asarray(value, dtype=float)
    if array.shape not in ((dim,), (dim, 1)) and not (dim == 1 and array.shape == ()):
        raise ValueError(f"{argument}: expected shape ({dim},) at sample {k}, received "
                         f"{array.shape}.")
    array = array.reshape(dim)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{argument}: expected finite values at sample {k}, received "
                         f"{array.tolist()}. Skip or repair the sample; the estimator state is "
                         "unchanged.")
    return array


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
        system = systems.get(name)
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
