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
from typing import Any, Sequence

import casadi as ca
import numpy as np

from .architecture import DECODER, ENCODER
from .casadi_nets import lora_mlp_function
from .data import phase1
from .design import Design
from .observer import KKLObserver
from .protocol import Protocol
from .simulate import simulate_batch
from .validation import positive_int
from .windows import input_windows

__all__ = ["Certificate", "certificate", "decoder_lipschitz_upper", "cmd_certificate",
           "add_certificate_parser"]

#: The methods a certificate is computed for.
CERTIFIED = ("autonomous", "curriculum", "inject", "obs", "dyn")
_ACTIVATION_LIPSCHITZ = {"tanh": 1.0, "relu": 1.0, "softplus": 1.0, "identity": 1.0}
_KINDS = ("zero", "constant", "sinusoid", "square")
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

    ``|diag(out_std) W_L| * ... * |W_0 diag(1 / in_std)|`` with 1-Lipschitz activations: an upper
    bound of the decoder's Lipschitz constant on all of R^nz (for dyn, of the unmodulated decoder).
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
        if obs.method == "dyn":
            arch = obs.model.spec.architecture
            encoder = lora_mlp_function(arch.encoder, arch.decoder, arch.hyper, obs.model.arrays, nu, window,
                                        ENCODER)
            zeta = encoder(x, w)
        else:
            zeta = obs.encoder(x)
        self.encode = ca.Function("encode", [x, w], [zeta])
        dzeta = ca.jtimes(zeta, x, f(x, u))
        if obs.method == "dyn":
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


def certificate(observer: KKLObserver, *, kinds: Sequence[str] = _KINDS, n_points: int = 4000,
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
        Held-out Phase-1 label trajectories (``kc.data.phase1``, ``t_keep`` 10 s each).
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
    if observer.method not in CERTIFIED:
        raise ValueError(f"observer: expected a model whose method is one of {list(CERTIFIED)} (a KKL map T with its "
                         f"input window), received method {observer.method!r}; Proposition 1 needs an encoder T and "
                         "the window convention (bank has no encoder, the streaming variants no window).")
    kinds = tuple(kinds)
    unknown = [k for k in kinds if k not in _KINDS]
    if not kinds or unknown:
        raise ValueError(f"kinds: expected a non-empty subset of {list(_KINDS)}, received "
                         f"{list(kinds)}.")
    n_points = positive_int(n_points, "n_points")
    n_labels = positive_int(n_labels, "n_labels")
    n_trials = positive_int(n_trials, "n_trials")
    if not (np.isfinite(t_settle) and 0 <= t_settle < T):
        raise ValueError(f"t_settle: expected a time in [0, T = {T}), received {t_settle}.")
    obs, plant = observer, observer.system
    dt, window = obs.dt, obs.window
    design = Design(obs.A, obs.B)
    kappa, lam = float(design.kappa), float(design.lam)
    maps = _Maps(obs)
    rng = np.random.default_rng(seed)

    # ---- noise-free protocol runs: observed error, windows of the input set, latent segments
    protocol = Protocol(n_trials=n_trials, T=T, dt=dt, seed=seed).noise_free()
    xs, us, zhats, errors = [], [], [], []
    for kind in kinds:
        batch = protocol.trials(plant, kind)
        ok = batch.ok
        est = obs.simulate(batch.t, batch.y[ok], batch.u[ok])
        xs.append(batch.x[ok])
        us.append(batch.u[ok])
        zhats.append(est.z)
        errors.append(np.linalg.norm(batch.x[ok] - est.xhat, axis=2))
    x_runs, u_runs = np.concatenate(xs), np.concatenate(us)
    z_runs, err = np.concatenate(zhats), np.concatenate(errors)
    t = np.arange(x_runs.shape[1]) * dt
    settled = t >= t_settle
    observed = float(err[:, settled].max())
    k_settle = int(np.argmax(settled))
    windows = input_windows(u_runs, window)                              # (M, N, window, nu)

    box = plant.x0_box
    lo = np.minimum(box[:, 0], x_runs.min(axis=(0, 1)))
    hi = np.maximum(box[:, 1], x_runs.max(axis=(0, 1)))
    domain = np.stack([lo, hi], axis=1)
    diameter = float(np.linalg.norm(hi - lo))

    # ---- PDE residual and sampled-data residual over the domain
    from scipy.stats import qmc

    x_pts = lo + (hi - lo) * qmc.LatinHypercube(d=plant.nx, seed=seed).random(n_points)
    m, n = windows.shape[:2]
    pick_trial, pick_k = rng.integers(0, m, n_points), rng.integers(0, n - 1, n_points)
    w_pts = np.ascontiguousarray(windows[pick_trial, pick_k])
    w_next = np.ascontiguousarray(windows[pick_trial, pick_k + 1])
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
    eps_step = float(np.linalg.norm(zeta_next - predicted, axis=1).max())

    # ---- encoder / decoder errors on held-out labels (windows from the input set for dyn)
    labels = phase1(plant, design, n_traj=n_labels, seed=label_seed, dt=dt)
    n_lab = labels.x.shape[0]
    label_w = np.ascontiguousarray(windows[rng.integers(0, m, n_lab), rng.integers(0, n, n_lab)])
    if obs.method != "dyn":
        label_w = np.zeros_like(label_w)
    eps_enc = float(np.linalg.norm(
        labels.z - _batched(maps.encode, labels.x, label_w)[0][:, :, 0], axis=1).max())
    decoded = _batched(obs.decode, labels.z, label_w)[0][:, :, 0]
    eps_dec = float(np.linalg.norm(labels.x - decoded, axis=1).max())

    # ---- Lipschitz constants on the latent set: segments zeta_k -- zhat_k of the runs
    def segment_points(k_min: int, count: int) -> tuple[np.ndarray, ...]:
        trial = rng.integers(0, m, count)
        k = rng.integers(k_min, n - 1, count)
        w_k = np.ascontiguousarray(windows[trial, k])
        zeta_k = _batched(maps.encode, x_runs[trial, k], w_k)[0][:, :, 0]
        s = rng.uniform(0.0, 1.0, (count, 1))
        z_k = zeta_k + s * (z_runs[trial, k] - zeta_k)
        y_k = np.asarray(plant.h.map(count)(x_runs[trial, k].T)).T
        y_k1 = np.asarray(plant.h.map(count)(x_runs[trial, k + 1].T)).T
        return z_k, w_k, y_k, y_k1, np.ascontiguousarray(windows[trial, k + 1][:, -1, :])

    z_lat, w_lat = segment_points(k_settle, n_points)[:2]
    z_all = np.concatenate([z_lat, zeta])
    w_all = np.concatenate([w_lat, w_pts[good]])
    ell_dec = float(_spectral(_batched(maps.decoder_jacobian, z_all, w_all)[0]).max())
    ell_dec_upper = decoder_lipschitz_upper(obs)

    if obs.linear:
        ell_inj, rho = 0.0, float(np.exp(-lam * dt))
        gain = kappa / (1.0 - rho)
        decay_sampled = kappa * rho ** k_settle
    else:
        z_seg, w_seg, y_seg, y_seg1, u_seg1 = segment_points(0, n_points)
        u_seg = w_seg[:, -1, :]
        ell_inj = float(_spectral(_batched(maps.injection_jacobian, z_seg, y_seg, u_seg,
                                           w_seg)[0]).max())
        rho = float(_spectral(_batched(maps.step_jacobian, z_seg, w_seg, y_seg, y_seg1,
                                       u_seg1)[0]).max())
        gain = 1.0 / (1.0 - rho) if rho < 1 else np.inf
        decay_sampled = rho ** k_settle if rho < 1 else np.inf
    lam_eff = lam - kappa * ell_inj

    xi_z0 = float(np.linalg.norm(_batched(maps.encode, x_runs[:, 0], windows[:, 0])[0][:, :, 0]
                                 - z_runs[:, 0], axis=1).max())
    if lam_eff > 0:
        latent = kappa / lam_eff * eps_pde + eps_enc
        bound = eps_dec + ell_dec * latent
        bound_upper = eps_dec + ell_dec_upper * latent
        transient = ell_dec * kappa * np.exp(-lam_eff * t[k_settle]) * xi_z0
    else:
        bound = bound_upper = transient = np.inf
    bound_sampled = eps_dec + ell_dec * (gain * eps_step + eps_enc)
    transient_sampled = ell_dec * decay_sampled * xi_z0
    domain.setflags(write=False)
    return Certificate(plant.name, obs.method, kappa, lam, ell_inj, lam_eff, eps_pde, eps_enc,
                       eps_dec, ell_dec, ell_dec_upper, float(bound), float(bound_upper),
                       float(transient), eps_step, rho, float(gain), float(bound_sampled),
                       float(transient_sampled), observed, float(t_settle), kinds, n_trials,
                       n_points, int(n_lab), domain, diameter)


# ---------------------------------------------------------------------- command line
def cmd_certificate(args: Any) -> int:
    """``kklcasadi certificate MODEL...``: print each model's certificate; ``--json`` saves them."""
    import json
    from pathlib import Path

    from .observer import load_observer

    records = []
    for model in args.models:
        cert = certificate(load_observer(model), kinds=tuple(args.kinds), n_points=args.points,
                           n_labels=args.labels, n_trials=args.trials, T=args.T,
                           t_settle=args.settle, seed=args.seed)
        print(f"{model}\n{cert}\n")
        records.append({"model": str(model), **cert.to_json()})
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(records, indent=1))
    return 0


def add_certificate_parser(sub: Any) -> Any:
    """Add the ``certificate`` subcommand to a ``kklcasadi`` subparsers object; returns its parser."""
    c = sub.add_parser("certificate", help="estimate Proposition 1's error bound for models and "
                                           "compare it with their observed error")
    c.add_argument("models", nargs="+", help="model directories")
    c.add_argument("--kinds", nargs="+", default=list(_KINDS), choices=_KINDS,
                   help="input regimes of the input set and the runs (zero: u = 0 only)")
    c.add_argument("--points", type=int, default=4000, help="domain sample size")
    c.add_argument("--labels", type=int, default=40, help="held-out label trajectories")
    c.add_argument("--trials", type=int, default=10, help="noise-free runs per regime")
    c.add_argument("--T", type=float, default=30.0, help="run duration (s)")
    c.add_argument("--settle", type=float, default=10.0, help="settle time (s)")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--json", help="write the certificates to this JSON file")
    c.set_defaults(func=cmd_certificate)
    return c
