"""Proposition 1 of the HyperKKL paper, estimated for a model: a computed error certificate.

The paper (Proposition 1) bounds the estimation error ``xi = x - xhat`` of a KKL observer with
learned maps ``T^`` (encoder) and ``T^*`` (decoder) by::

    |xi(t)| <= eps_dec + ell_dec * (kappa exp(-lam t) |xi_z(0)| + kappa / lam * eps_pde + eps_enc)

so asymptotically ``limsup |xi| <= eps_dec + ell_dec (kappa / lam eps_pde + eps_enc)``, with

* ``kappa``, ``lam``: ``|exp(A t)| <= kappa exp(-lam t)``; ``kappa`` is the condition number of
  A's eigenvector matrix, ``lam = -max Re eig(A)``;
* ``eps_pde = sup |R(x, u, w)|`` over the state domain, the input set and the windows, with
  ``R = dT^/dx f(x, u) + dT^/dt - zdot(T^(x), h(x), u, w)``: the time derivative of
  ``zeta = T^(x)`` along the plant minus the observer's own latent field at ``zeta``
  (``zdot = A z + B y`` for autonomous, curriculum and dyn; plus the injection for inject and
  obs). For dyn, ``T^`` depends on the window and ``dT^/dt`` is its derivative along
  ``wdot = (w_k+1 - w_k) / dt``, the training's definition;
* ``eps_enc = sup |T(x) - T^(x)|``, ``eps_dec = sup |T^*(z) - T^*^(z)|`` against the exact map
  ``T`` (``kc.data.phase1`` labels at ``u = 0``, held out by seed; for dyn at windows drawn from
  the input set): the proof needs any injective ``T`` with ``T^*(T(x)) = x``, so the autonomous
  map serves for every method;
* ``ell_dec``: the decoder's Lipschitz constant on the latent set.

For inject and obs the latent field has a ``z``-dependent injection ``g(z, u)``, and the proof
picks up ``g(zeta) - g(zhat)``: with ``ell_inj = sup |dg/dz|``, ``lam`` becomes
``lam_eff = lam - kappa ell_inj`` (Gronwall), and the bound is vacuous if ``lam_eff <= 0``.

The shipped observer is a sampled one (first-order hold of ``y``, exact or RK4 step), and the
continuous-time bound does not cover its discretisation error (it is 0 for an exact linear map
while the sampled observer's error is O(dt^2)). The certificate therefore also reports its
sampled-data analogue, which holds for the observer as implemented: with the one-step residual
``d_k = T^(x_k+1) - step(T^(x_k), y_k, y_k+1, u)`` (``x_k+1`` from CVODES), ``eps_step = sup |d|``,
and ``|xi_z,k+1| <= |step(zeta_k) - step(zhat_k)| + eps_step``::

    |xi_k| <= eps_dec + ell_dec (G_k |xi_z,0| + gain * eps_step + eps_enc)

with ``gain = kappa / (1 - exp(-lam dt))`` and ``G_k = kappa exp(-lam k dt)`` for linear latent
dynamics (the step is ``Ad z + ...``, ``|Ad^j| <= kappa exp(-lam j dt)``), and
``gain = 1 / (1 - rho)``, ``G_k = rho^k`` with ``rho = sup |d step / dz|`` for nonlinear ones.

All suprema and Lipschitz constants are estimated by sampling (a dense Latin hypercube of the
domain, windows and inputs drawn from the protocol's input regimes, latent points on the segments
between ``zeta_k`` and ``zhat_k`` of the protocol runs), so the certificate is an estimate, not a
proof; the spectral-norm product of the decoder's layers is a true global upper bound of its
Lipschitz constant and is reported beside the sampled one. The domain is the smallest box holding
the X0 box and every state of the protocol runs, so that ``x(t)`` stays in it by construction.
The certificate is noise-free (Proposition 1; the paper's Remark 1 needs bounded noise).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import casadi as ca
import numpy as np

from ..model import variants
from ..nets.builders import folded_skip, lora_mlp_function
from ..nets.specs import DECODER, ENCODER
from ..observer.kkl import KKLObserver
from ..plant import signals as sig
from ..plant.data import phase1
from ..plant.design import Design
from ..plant.simulate import simulate_batch
from ..plant.windows import input_windows
from ..validation import positive_int
from .protocol import Protocol

__all__ = ["Certificate", "certificate", "decoder_lipschitz_upper"]

_ACTIVATION_LIPSCHITZ = {"tanh": 1.0, "relu": 1.0, "softplus": 1.0, "identity": 1.0}
_CONTINUOUS_MISS = ("it omits the sampled observer's discretisation error (see the sampled-data "
                    "bound), or a sampled supremum is too small")
_SAMPLED_MISS = "a sampled supremum or Lipschitz estimate is too small (sample more points)"


@dataclass(frozen=True, eq=False)
class Certificate:
    """The terms of Proposition 1 for one model, its bound and the observed error.

    Attributes
    ----------
    system, method : str
    kappa, lam : float
        Of A (``Design``).
    ell_inj : float
        Sampled Lipschitz constant in ``z`` of the latent injection (0 for linear latent dynamics).
    lam_eff : float
        ``lam - kappa ell_inj``.
    eps_pde : float
        Sampled sup of the PDE residual (see the module docstring for the PDE of each method).
    eps_enc, eps_dec : float
        Max encoder and decoder errors on held-out labels.
    ell_dec : float
        Max spectral norm of the decoder's Jacobian over the sampled latent set.
    ell_dec_upper : float
        Product of the layers' spectral norms (normalisation included, activations 1-Lipschitz):
        a global upper bound (for dyn: of the unmodulated decoder, the zero window).
    bound : float
        Proposition 1's asymptotic bound with ``ell_dec`` (``inf`` when ``lam_eff <= 0``).
    bound_upper : float
        The same with ``ell_dec_upper``.
    transient : float
        The decaying term of Proposition 1 at ``t_settle`` (largest ``|xi_z(0)|`` of the runs).
    eps_step, rho_step, gain_step : float
        Sampled-data residual sup, the step's contraction (``exp(-lam dt)`` for linear latent
        dynamics, else the sampled ``sup |d step/dz|``) and the gain of the residual.
    bound_sampled, transient_sampled : float
        The sampled-data bound and its decaying term at ``t_settle``.
    observed : float
        Largest ``|x - xhat|`` over the protocol runs at ``t >= t_settle`` (noise-free).
    t_settle : float
    kinds : tuple of str
        Input regimes of the runs (the input set).
    n_trials, n_points, n_labels : int
    domain : numpy.ndarray, shape (nx, 2)
        The state box sampled.
    diameter : float
        Euclidean diameter of the domain: a bound at least this large says nothing.
    """

    system: str
    method: str
    kappa: float
    lam: float
    ell_inj: float
    lam_eff: float
    eps_pde: float
    eps_enc: float
    eps_dec: float
    ell_dec: float
    ell_dec_upper: float
    bound: float
    bound_upper: float
    transient: float
    eps_step: float
    rho_step: float
    gain_step: float
    bound_sampled: float
    transient_sampled: float
    observed: float
    t_settle: float
    kinds: tuple
    n_trials: int
    n_points: int
    n_labels: int
    domain: np.ndarray
    diameter: float

    @property
    def vacuous(self) -> bool:
        """The continuous-time bound is infinite or at least the domain's diameter."""
        return not np.isfinite(self.bound) or self.bound >= self.diameter

    @property
    def vacuous_sampled(self) -> bool:
        """The sampled-data bound is infinite or at least the domain's diameter."""
        return not np.isfinite(self.bound_sampled) or self.bound_sampled >= self.diameter

    @property
    def holds(self) -> bool:
        """``observed <= bound + transient``."""
        return bool(self.observed <= self.bound + self.transient)

    @property
    def holds_sampled(self) -> bool:
        """``observed <= bound_sampled + transient_sampled``."""
        return bool(self.observed <= self.bound_sampled + self.transient_sampled)

    def to_json(self) -> dict:
        """The terms, bounds and verdicts as plain JSON values (``inf`` as the string "inf")."""
        out: dict = {}
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if isinstance(value, np.ndarray):
                value = value.tolist()
            elif isinstance(value, tuple):
                value = list(value)
            elif isinstance(value, float) and not np.isfinite(value):
                value = str(value)
            out[name] = value
        for name in ("vacuous", "vacuous_sampled", "holds", "holds_sampled"):
            out[name] = bool(getattr(self, name))
        return out

    def __str__(self) -> str:
        def verdict(bound: float, vacuous: bool, holds: bool, why: str) -> str:
            if vacuous:
                return (f"VACUOUS: {bound:.4g} is not below the domain's diameter "
                        f"{self.diameter:.4g}, so it says nothing about this observer")
            return "holds on the runs" if holds else f"VIOLATED by the runs: {why}"

        lines = [
            f"Proposition 1 certificate: {self.system} / {self.method}, noise-free, inputs "
            f"{', '.join(self.kinds)}; {self.n_points} domain points, {self.n_labels} held-out "
            f"labels, {self.n_trials} runs per regime",
            f"  A: kappa {self.kappa:.4g}, lam {self.lam:.4g}; injection Lipschitz ell_inj "
            f"{self.ell_inj:.4g} -> lam_eff {self.lam_eff:.4g}",
            f"  eps_pde {self.eps_pde:.4g}, eps_enc {self.eps_enc:.4g}, eps_dec "
            f"{self.eps_dec:.4g}, ell_dec {self.ell_dec:.4g} sampled "
            f"({self.ell_dec_upper:.4g} spectral-norm product)",
            f"  asymptotic bound {self.bound:.4g} (with the product: {self.bound_upper:.4g}); "
            f"+ transient {self.transient:.3g} at t = {self.t_settle:g} s",
            f"  sampled-data: eps_step {self.eps_step:.4g}, rho {self.rho_step:.4g}, gain "
            f"{self.gain_step:.4g} -> bound {self.bound_sampled:.4g} + transient "
            f"{self.transient_sampled:.3g}",
            f"  observed worst |x - xhat| after {self.t_settle:g} s: {self.observed:.4g}",
            f"  continuous-time bound: "
            f"{verdict(self.bound, self.vacuous, self.holds, _CONTINUOUS_MISS)}",
            f"  sampled-data bound: "
            f"{verdict(self.bound_sampled, self.vacuous_sampled, self.holds_sampled, _SAMPLED_MISS)}",
        ]
        return "\n".join(lines)


# ---------------------------------------------------------------------- batch evaluation
def _columns(a: np.ndarray) -> np.ndarray:
    """(n, d) -> (d, n)."""
    return np.ascontiguousarray(np.asarray(a, dtype=float).reshape(a.shape[0], -1).T)


def _window_columns(w: np.ndarray) -> np.ndarray:
    """(n, window, nu) -> (window, n * nu), the horizontal stacking of ``Function.map``."""
    n, window, nu = w.shape
    return np.ascontiguousarray(w.transpose(1, 0, 2).reshape(window, n * nu))


def _batched(function: ca.Function, *arrays: np.ndarray, chunk: int = 2000) -> list[np.ndarray]:
    """Evaluate ``function`` at n points; inputs (n, ...) -> outputs (n, rows, cols)."""
    n = arrays[0].shape[0]
    pieces: list[list[np.ndarray]] = [[] for _ in range(function.n_out())]
    for start in range(0, n, chunk):
        part = [a[start:start + chunk] for a in arrays]
        m = part[0].shape[0]
        cols = [_window_columns(a) if a.ndim == 3 else _columns(a) for a in part]
        outs = function.map(m)(*cols)
        outs = outs if isinstance(outs, tuple) else (outs,)
        for i, out in enumerate(outs):
            r, c = function.size_out(i)
            pieces[i].append(np.asarray(out).reshape(r, m, c).transpose(1, 0, 2))
    return [np.concatenate(p, axis=0) for p in pieces]


def _spectral(matrices: np.ndarray) -> np.ndarray:
    """Spectral norms of a stack (n, r, c)."""
    return np.linalg.norm(matrices, ord=2, axis=(1, 2))


def decoder_lipschitz_upper(observer: KKLObserver) -> float:
    """Product of the spectral norms of the decoder's layers, normalisation folded in.

    ``|diag(out_std) W_L| * ... * |W_0 diag(1 / in_std)|`` with 1-Lipschitz activations, plus
    ``|diag(out_std) Wskip diag(1 / in_std)|`` for a skip path: an upper bound of the decoder's Lipschitz
    constant on all of R^nz (for dyn, of the unmodulated decoder).
    """
    arrays = observer.model.arrays
    arch = observer.model.spec.architecture.decoder
    n_layers = len(arch.layer_shapes)
    lip = _ACTIVATION_LIPSCHITZ[arch.activation] ** (n_layers - 1)
    for i in range(n_layers):
        W = np.asarray(arrays[f"{DECODER}/W{i}"], dtype=float)
        if i == 0:
            W = W / np.asarray(arrays[f"{DECODER}/in_std"], dtype=float)[None, :]
        if i == n_layers - 1:
            W = np.asarray(arrays[f"{DECODER}/out_std"], dtype=float)[:, None] * W
        lip *= np.linalg.norm(W, 2)
    if arch.skip:
        lip += np.linalg.norm(folded_skip(arrays, DECODER)[0], 2)
    return float(lip)


class _Maps:
    """The observer's maps and their derivatives as CasADi Functions of one point."""

    def __init__(self, obs: KKLObserver) -> None:
        self.obs = obs
        nx, nu, nz, window = obs.nx, obs.nu, obs.nz, obs.window
        f, h = obs.system.f, obs.system.h
        x, u = ca.MX.sym("x", nx), ca.MX.sym("u", nu)
        w, wdot = ca.MX.sym("w", window, nu), ca.MX.sym("wdot", window, nu)
        z, y, y_next = ca.MX.sym("z", nz), ca.MX.sym("y", obs.ny), ca.MX.sym("y_next", obs.ny)
        modulated = variants.get(obs.method).modulated
        if modulated:
            arch = obs.model.spec.architecture
            encoder = lora_mlp_function(arch.encoder, arch.decoder, arch.hyper, obs.model.arrays, nu, window,
                                        ENCODER)
            zeta = encoder(x, w)
        else:
            zeta = obs.encoder(x)
        self.encode = ca.Function("encode", [x, w], [zeta])
        dzeta = ca.jtimes(zeta, x, f(x, u))
        if modulated:
            dzeta = dzeta + ca.jtimes(zeta, w, wdot)
        residual = dzeta - obs.rhs(zeta, h(x), u, w)
        self.pde = ca.Function("pde", [x, u, w, wdot], [residual])
        self.decoder_jacobian = ca.Function("decoder_jacobian", [z, w],
                                            [ca.jacobian(obs.decode(z, w), z)])
        z_next = obs.step(z, w, y, y_next, u)[0]
        self.step = ca.Function("step", [z, w, y, y_next, u], [z_next])
        if not obs.linear:
            self.injection_jacobian = ca.Function(
                "injection_jacobian", [z, y, u, w],
                [ca.jacobian(obs.rhs(z, y, u, w), z) - ca.DM(obs.A)])
            self.step_jacobian = ca.Function("step_jacobian", [z, w, y, y_next, u],
                                             [ca.jacobian(z_next, z)])


@dataclass(frozen=True, eq=False)
class _Runs:
    """Noise-free protocol runs of the observer: states, inputs' windows, latents and errors."""

    x: np.ndarray              # (M, N, nx)
    windows: np.ndarray        # (M, N, window, nu)
    z: np.ndarray              # (M, N, nz), the observer's latent
    t: np.ndarray              # (N,)
    observed: float            # max |x - xhat| at t >= t_settle
    k_settle: int
    domain: np.ndarray         # (nx, 2): the X0 box and every state of the runs

    @classmethod
    def simulate(cls, obs: KKLObserver, kinds: Sequence[str], n_trials: int, T: float, seed: int,
                 t_settle: float) -> _Runs:
        protocol = Protocol(n_trials=n_trials, T=T, dt=obs.dt, seed=seed).noise_free()
        xs, us, zhats, errors = [], [], [], []
        for kind in kinds:
            batch = protocol.trials(obs.system, kind)
            ok = batch.ok
            est = obs.simulate(batch.t, batch.y[ok], batch.u[ok])
            xs.append(batch.x[ok])
            us.append(batch.u[ok])
            zhats.append(est.z)
            errors.append(np.linalg.norm(batch.x[ok] - est.xhat, axis=2))
        x, u, err = np.concatenate(xs), np.concatenate(us), np.concatenate(errors)
        t = np.arange(x.shape[1]) * obs.dt
        settled = t >= t_settle
        box = obs.system.x0_box
        domain = np.stack([np.minimum(box[:, 0], x.min(axis=(0, 1))), np.maximum(box[:, 1], x.max(axis=(0, 1)))],
                          axis=1)
        domain.setflags(write=False)
        return cls(x, input_windows(u, obs.window), np.concatenate(zhats), t, float(err[:, settled].max()),
                   int(np.argmax(settled)), domain)

    def segment_points(self, obs: KKLObserver, maps: _Maps, rng: np.random.Generator, k_min: int,
                       count: int) -> tuple[np.ndarray, ...]:
        """Points ``z`` on the segments ``zeta_k -- zhat_k`` with their ``w_k, y_k, y_k+1, u_k+1``."""
        m, n = self.windows.shape[:2]
        trial = rng.integers(0, m, count)
        k = rng.integers(k_min, n - 1, count)
        w_k = np.ascontiguousarray(self.windows[trial, k])
        zeta_k = _batched(maps.encode, self.x[trial, k], w_k)[0][:, :, 0]
        s = rng.uniform(0.0, 1.0, (count, 1))
        z_k = zeta_k + s * (self.z[trial, k] - zeta_k)
        y_k = np.asarray(obs.system.h.map(count)(self.x[trial, k].T)).T
        y_k1 = np.asarray(obs.system.h.map(count)(self.x[trial, k + 1].T)).T
        return z_k, w_k, y_k, y_k1, np.ascontiguousarray(self.windows[trial, k + 1][:, -1, :])


@dataclass(frozen=True, eq=False)
class _Residuals:
    """The PDE residual and the sampled-data residual over the domain, and the points sampled."""

    eps_pde: float
    eps_step: float
    zeta: np.ndarray           # (n_good, nz): T^(x) at the sampled states that stepped
    w: np.ndarray              # (n_good, window, nu): their windows

    @classmethod
    def sample(cls, obs: KKLObserver, maps: _Maps, runs: _Runs, n_points: int, seed: int,
               rng: np.random.Generator) -> _Residuals:
        from scipy.stats import qmc

        plant, dt = obs.system, obs.dt
        lo, hi = runs.domain[:, 0], runs.domain[:, 1]
        x_pts = lo + (hi - lo) * qmc.LatinHypercube(d=plant.nx, seed=seed).random(n_points)
        m, n = runs.windows.shape[:2]
        pick_trial, pick_k = rng.integers(0, m, n_points), rng.integers(0, n - 1, n_points)
        w_pts = np.ascontiguousarray(runs.windows[pick_trial, pick_k])
        w_next = np.ascontiguousarray(runs.windows[pick_trial, pick_k + 1])
        u_pts, u_next = w_pts[:, -1, :], w_next[:, -1, :]
        residual = _batched(maps.pde, x_pts, u_pts, w_pts, (w_next - w_pts) / dt)[0]
        eps_pde = float(np.linalg.norm(residual[:, :, 0], axis=1).max())

        inputs = [np.stack([a, b]) for a, b in zip(u_pts, u_next)]
        stepped = simulate_batch(plant, x_pts, inputs, 2 * dt, dt)
        good = stepped.ok
        x_next = stepped.x[good, 1]
        zeta = _batched(maps.encode, x_pts[good], w_pts[good])[0][:, :, 0]
        zeta_next = _batched(maps.encode, x_next, w_next[good])[0][:, :, 0]
        y_pts = np.asarray(plant.h.map(int(good.sum()))(x_pts[good].T)).T
        y_next = np.asarray(plant.h.map(int(good.sum()))(x_next.T)).T
        predicted = _batched(maps.step, zeta, w_pts[good], y_pts, y_next, u_next[good])[0][:, :, 0]
        return cls(eps_pde, float(np.linalg.norm(zeta_next - predicted, axis=1).max()), zeta, w_pts[good])


def _label_errors(obs: KKLObserver, maps: _Maps, design: Design, runs: _Runs, n_labels: int, label_seed: int,
                  rng: np.random.Generator) -> tuple[float, float, int]:
    """``eps_enc``, ``eps_dec`` on held-out Phase-1 labels (windows from the input set where the maps
    are modulated by it), and the number of labels."""
    labels = phase1(obs.system, design, n_traj=n_labels, seed=label_seed, dt=obs.dt)
    n_lab = labels.x.shape[0]
    m, n = runs.windows.shape[:2]
    label_w = np.ascontiguousarray(runs.windows[rng.integers(0, m, n_lab), rng.integers(0, n, n_lab)])
    if not variants.get(obs.method).modulated:
        label_w = np.zeros_like(label_w)
    eps_enc = float(np.linalg.norm(labels.z - _batched(maps.encode, labels.x, label_w)[0][:, :, 0], axis=1).max())
    decoded = _batched(obs.decode, labels.z, label_w)[0][:, :, 0]
    return eps_enc, float(np.linalg.norm(labels.x - decoded, axis=1).max()), int(n_lab)


def certificate(observer: KKLObserver, *, kinds: Sequence[str] = sig.BENCHMARK_KINDS, n_points: int = 4000,
                n_labels: int = 40, n_trials: int = 10, T: float = 30.0, t_settle: float = 10.0,
                seed: int = 0, label_seed: int = 10_000) -> Certificate:
    """Estimate the terms of Proposition 1 for ``observer`` and compare its bound with its error.

    Parameters
    ----------
    observer : KKLObserver
    kinds : sequence of str
        Input regimes (docs/protocol.md, ``id`` ranges) defining the input set and the runs;
        ``("zero",)`` certifies the autonomous case ``u = 0``.
    n_points : int
        Latin-hypercube states of the domain, each with a window drawn from the runs' inputs.
    n_labels : int
        Held-out Phase-1 label trajectories (:func:`kklcasadi.plant.data.phase1`, ``t_keep`` 10 s each).
    n_trials : int
        Noise-free protocol runs per regime (``Protocol(n_trials, T, seed)``).
    T : float
        Duration of the runs (s).
    t_settle : float
        The observed error and the transient terms are taken at ``t >= t_settle``.
    seed : int
        Seed of the runs and of the sampling.
    label_seed : int
        Seed of the held-out labels (keep it away from the training seeds).

    Returns
    -------
    Certificate
    """
    if not isinstance(observer, KKLObserver):
        raise TypeError(f"observer: expected a KKLObserver (kc.load_observer), received "
                        f"{type(observer).__name__}.")
    certified = [v.name for v in variants.VARIANTS.values() if v.certified]
    if not variants.get(observer.method).certified:
        raise ValueError(f"observer: expected a model whose method is one of {certified} (a KKL map T with its "
                         f"input window), received method {observer.method!r}; Proposition 1 needs an encoder T and "
                         "the window convention (bank has no encoder, the streaming variants no window).")
    kinds = tuple(kinds)
    unknown = [k for k in kinds if k not in sig.BENCHMARK_KINDS]
    if not kinds or unknown:
        raise ValueError(f"kinds: expected a non-empty subset of {list(sig.BENCHMARK_KINDS)}, received "
                         f"{list(kinds)}.")
    n_points = positive_int(n_points, "n_points")
    n_labels = positive_int(n_labels, "n_labels")
    n_trials = positive_int(n_trials, "n_trials")
    if not (np.isfinite(t_settle) and 0 <= t_settle < T):
        raise ValueError(f"t_settle: expected a time in [0, T = {T}), received {t_settle}.")
    obs = observer
    design = Design(obs.A, obs.B)
    kappa, lam = float(design.kappa), float(design.lam)
    maps = _Maps(obs)
    rng = np.random.default_rng(seed)

    runs = _Runs.simulate(obs, kinds, n_trials, T, seed, t_settle)
    residuals = _Residuals.sample(obs, maps, runs, n_points, seed, rng)
    eps_enc, eps_dec, n_lab = _label_errors(obs, maps, design, runs, n_labels, label_seed, rng)

    # ---- Lipschitz constants on the latent set: segments zeta_k -- zhat_k of the runs
    z_lat, w_lat = runs.segment_points(obs, maps, rng, runs.k_settle, n_points)[:2]
    z_all = np.concatenate([z_lat, residuals.zeta])
    w_all = np.concatenate([w_lat, residuals.w])
    ell_dec = float(_spectral(_batched(maps.decoder_jacobian, z_all, w_all)[0]).max())
    if obs.linear:
        ell_inj, rho = 0.0, float(np.exp(-lam * obs.dt))
        gain = kappa / (1.0 - rho)
        decay_sampled = kappa * rho ** runs.k_settle
    else:
        z_seg, w_seg, y_seg, y_seg1, u_seg1 = runs.segment_points(obs, maps, rng, 0, n_points)
        u_seg = w_seg[:, -1, :]
        ell_inj = float(_spectral(_batched(maps.injection_jacobian, z_seg, y_seg, u_seg, w_seg)[0]).max())
        rho = float(_spectral(_batched(maps.step_jacobian, z_seg, w_seg, y_seg, y_seg1, u_seg1)[0]).max())
        gain = 1.0 / (1.0 - rho) if rho < 1 else np.inf
        decay_sampled = rho ** runs.k_settle if rho < 1 else np.inf
    lam_eff = lam - kappa * ell_inj

    # ---- the bounds
    ell_dec_upper = decoder_lipschitz_upper(obs)
    xi_z0 = float(np.linalg.norm(_batched(maps.encode, runs.x[:, 0], runs.windows[:, 0])[0][:, :, 0]
                                 - runs.z[:, 0], axis=1).max())
    if lam_eff > 0:
        latent = kappa / lam_eff * residuals.eps_pde + eps_enc
        bound = eps_dec + ell_dec * latent
        bound_upper = eps_dec + ell_dec_upper * latent
        transient = ell_dec * kappa * np.exp(-lam_eff * runs.t[runs.k_settle]) * xi_z0
    else:
        bound = bound_upper = transient = np.inf
    return Certificate(
        system=obs.system.name, method=obs.method, kappa=kappa, lam=lam, ell_inj=ell_inj, lam_eff=lam_eff,
        eps_pde=residuals.eps_pde, eps_enc=eps_enc, eps_dec=eps_dec, ell_dec=ell_dec, ell_dec_upper=ell_dec_upper,
        bound=float(bound), bound_upper=float(bound_upper), transient=float(transient),
        eps_step=residuals.eps_step, rho_step=rho, gain_step=float(gain),
        bound_sampled=float(eps_dec + ell_dec * (gain * residuals.eps_step + eps_enc)),
        transient_sampled=float(ell_dec * decay_sampled * xi_z0), observed=runs.observed,
        t_settle=float(t_settle), kinds=kinds, n_trials=n_trials, n_points=n_points, n_labels=n_lab,
        domain=runs.domain, diameter=float(np.linalg.norm(runs.domain[:, 1] - runs.domain[:, 0])))
