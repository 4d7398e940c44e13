"""A linear latent filter bank of the measurement and the input, and its learned decoder (torch-free).

The observer of this module (method ``bank``) keeps a linear latent state driven by the measured
output, the applied input and a constant,

    zdot = A z + By y(t) + Bu u_k + c,        z(0) = 0,

and decodes the state with a static map of the latent, the newest measurement and the current
input, ``xhat_k = D(z_k, y_k, u_k)``. Over ``[t_k, t_k+1]`` the output is interpolated linearly
between ``y_k`` and ``y_k+1`` (first-order hold, docs/protocol.md) and the input held at ``u_k``; the
discretisation is exact (:meth:`FilterBank.discretise`):

    z_k+1 = Ad z_k + Gy y_k + Gy_next y_k+1 + Gu u_k + g.

:meth:`FilterBank.design` builds ``A`` block-diagonal from first-order low-pass filters
``p / (s + p)`` of each output and input channel (unit DC gain, so every latent has the scale of
its signal), optional second-order resonators, and an optional *clock* ``c' = a (1 - c)`` that
tells the decoder how long the observer has run (the latent starts at 0, as the protocol's
``z(0) = 0`` asks, and the slow filters take seconds to forget it).

The decoder is an MLP (the arrays of :mod:`kklcasadi.model.files`, prefix ``decoder``) on the
feature vector ``[z; y_k; u_k]`` followed by a per-state output transform: where
``asinh_scale[i] > 0`` the network predicts ``asinh(x_i / asinh_scale[i])`` and
``xhat_i = asinh_scale[i] * sinh(v_i)`` (a log-like scale for a state whose magnitude spans
decades, such as Roessler's x3; odd, so it allows either sign), elsewhere ``xhat_i = v_i``.

:func:`estimate` is the reference implementation of the whole estimator over many trials at once
(numpy); :func:`decoder_function` and :meth:`FilterBank.step_function` build the same maps as
CasADi Functions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np

from ...nets import builders as casadi_nets
from ...nets.hold import FOHMatrices, foh_matrices
from ...nets.numpy_mlp import mlp_numpy
from ...nets.specs import DECODER, MLPSpec, check_arrays

__all__ = ["FilterBank", "decoder_features", "decode", "decoder_function", "estimate",
           "bank_arrays", "bank_from_arrays", "observer_step", "ASINH_SCALE"]

#: Array name of the per-state output transform scales (0: identity, > 0: asinh scale).
ASINH_SCALE = "decoder/asinh_scale"


def _matrix(value: Any, shape: tuple[int | None, int | None], arg: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 1 and len(shape) == 2 and shape[1] == 1:
        arr = arr[:, None]
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
        raise ValueError(f"{arg} must have shape {tuple('?' if s is None else s for s in shape)}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{arg} must be finite")
    out = arr.copy()
    out.setflags(write=False)
    return out


def _poles(values: Sequence[float], arg: str) -> np.ndarray:
    p = np.asarray(values, dtype=float).ravel()
    if not np.all(np.isfinite(p)) or np.any(p <= 0):
        raise ValueError(f"{arg} must be finite positive pole speeds (rad/s), got {p.tolist()}")
    if np.unique(p).size != p.size:
        raise ValueError(f"{arg} must be distinct, got {p.tolist()}")
    return p


@dataclass(frozen=True, eq=False)
class FilterBank:
    """Linear latent ``zdot = A z + By y + Bu u + c`` (A Hurwitz), ``z(0) = 0``.

    Parameters
    ----------
    A : array_like, shape (nz, nz)
        Hurwitz.
    By : array_like, shape (nz, ny)
    Bu : array_like, shape (nz, nu)
    c : array_like, shape (nz,)
        Constant drive (the clock; zeros for none).

    Raises
    ------
    ValueError
        On inconsistent shapes, non-finite entries or an ``A`` that is not Hurwitz.
    """

    A: np.ndarray
    By: np.ndarray
    Bu: np.ndarray
    c: np.ndarray

    def __post_init__(self) -> None:
        A = _matrix(self.A, (None, None), "A")
        nz = A.shape[0]
        if A.shape != (nz, nz) or nz == 0:
            raise ValueError(f"A must be a non-empty square matrix, got shape {A.shape}")
        if np.max(np.linalg.eigvals(A).real) >= 0:
            raise ValueError(f"A must be Hurwitz; max Re eig(A) = {np.max(np.linalg.eigvals(A).real):.6g}")
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "By", _matrix(self.By, (nz, None), "By"))
        object.__setattr__(self, "Bu", _matrix(self.Bu, (nz, None), "Bu"))
        object.__setattr__(self, "c", _matrix(self.c, (nz,), "c"))

    @classmethod
    def design(cls, ny: int, nu: int, y_poles: Sequence[float], u_poles: Sequence[float] = (),
               *, y_resonators: Sequence[tuple[float, float]] = (), clock: float | None = None) -> FilterBank:
        """Block-diagonal bank: unit-DC-gain filters of every output and input channel.

        Parameters
        ----------
        ny, nu : int
            Output and input sizes.
        y_poles : sequence of float
            Speeds ``p`` (rad/s) of the first-order filters ``p / (s + p)`` of each output channel.
        u_poles : sequence of float
            The same for each input channel.
        y_resonators : sequence of (zeta, omega)
            Second-order filters of each output channel, ``omega^2 / (s^2 + 2 zeta omega s + omega^2)``
            as the states ``(q, qdot / omega)``; ``0 < zeta``, ``omega > 0`` rad/s.
        clock : float, optional
            Rate ``a`` of the clock latent ``c' = a (1 - c)``, ``c(0) = 0``; ``None`` for no clock.

        Returns
        -------
        FilterBank
            Latents ordered: output filters (channel-major), resonators, input filters, clock.
        """
        for value, arg in ((ny, "ny"), (nu, "nu")):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{arg} must be a non-negative integer, got {value!r}")
        py = _poles(y_poles, "y_poles")
        pu = _poles(u_poles, "u_poles") if len(u_poles) else np.zeros(0)
        blocks: list[np.ndarray] = []
        by_rows: list[np.ndarray] = []
        bu_rows: list[np.ndarray] = []
        c_rows: list[np.ndarray] = []

        def add(block: np.ndarray, by: np.ndarray, bu: np.ndarray, cc: np.ndarray) -> None:
            blocks.append(block)
            by_rows.append(by)
            bu_rows.append(bu)
            c_rows.append(cc)

        for j in range(ny):
            for p in py:
                e = np.zeros((1, ny))
                e[0, j] = p
                add(np.array([[-p]]), e, np.zeros((1, nu)), np.zeros(1))
        for zeta, omega in y_resonators:
            if not (np.isfinite(zeta) and np.isfinite(omega) and zeta > 0 and omega > 0):
                raise ValueError(f"each resonator needs zeta > 0 and omega > 0, got {(zeta, omega)}")
            for j in range(ny):
                e = np.zeros((2, ny))
                e[1, j] = omega
                add(np.array([[0.0, omega], [-omega, -2.0 * zeta * omega]]), e, np.zeros((2, nu)), np.zeros(2))
        for j in range(nu):
            for p in pu:
                e = np.zeros((1, nu))
                e[0, j] = p
                add(np.array([[-p]]), np.zeros((1, ny)), e, np.zeros(1))
        if clock is not None:
            if not (np.isfinite(clock) and clock > 0):
                raise ValueError(f"clock must be a rate > 0 (1/s) or None, got {clock!r}")
            add(np.array([[-float(clock)]]), np.zeros((1, ny)), np.zeros((1, nu)), np.array([float(clock)]))
        n = sum(b.shape[0] for b in blocks)
        A = np.zeros((n, n))
        i = 0
        for b in blocks:
            A[i:i + b.shape[0], i:i + b.shape[0]] = b
            i += b.shape[0]
        return cls(A, np.vstack(by_rows), np.vstack(bu_rows), np.concatenate(c_rows))

    @property
    def nz(self) -> int:
        return self.A.shape[0]

    @property
    def ny(self) -> int:
        return self.By.shape[1]

    @property
    def nu(self) -> int:
        return self.Bu.shape[1]

    def discretise(self, dt: float) -> FOHMatrices:
        """Exact discretisation over one sample period (``y`` first-order hold, ``u`` held):
        :func:`kklcasadi.nets.hold.foh_matrices`.

        Parameters
        ----------
        dt : float
            Sample period (> 0).
        """
        return foh_matrices(self.A, self.By, dt, Bu=self.Bu, c=self.c)

    def run(self, y: Any, u: Any, dt: float) -> np.ndarray:
        """Latent trajectories from ``z_0 = 0`` for many trials at once.

        Parameters
        ----------
        y : array_like, shape (M, N, ny) or (N, ny)
        u : array_like, shape (M, N, nu) or (N, nu)
        dt : float

        Returns
        -------
        numpy.ndarray, shape (M, N, nz) or (N, nz)
        """
        y, u, single = _trials(y, u, self.ny, self.nu)
        m = self.discretise(dt)
        n = y.shape[1]
        z = np.zeros((y.shape[0], n, self.nz))
        drive = y[:, :-1] @ m.Gy.T + y[:, 1:] @ m.Gy_next.T + u[:, :-1] @ m.Gu.T + m.g
        AdT = m.Ad.T
        for k in range(n - 1):
            z[:, k + 1] = z[:, k] @ AdT + drive[:, k]
        return z[0] if single else z

    def step_function(self, dt: float, name: str = "bank_latent_step") -> ca.Function:
        """CasADi ``(z, y, y_next, u) -> z_next``: one exact sample interval (see :meth:`discretise`)."""
        m = self.discretise(dt)
        z, u = ca.MX.sym("z", self.nz), ca.MX.sym("u", self.nu)
        y, y_next = ca.MX.sym("y", self.ny), ca.MX.sym("y_next", self.ny)
        z_next = (ca.mtimes(ca.DM(m.Ad), z) + ca.mtimes(ca.DM(m.Gy), y) + ca.mtimes(ca.DM(m.Gy_next), y_next)
                  + ca.mtimes(ca.DM(m.Gu), u) + ca.DM(m.g))
        return ca.Function(name, [z, y, y_next, u], [z_next], ["z", "y", "y_next", "u"], ["z_next"])


def _trials(y: Any, u: Any, ny: int, nu: int) -> tuple[np.ndarray, np.ndarray, bool]:
    y = np.asarray(y, dtype=float)
    u = np.asarray(u, dtype=float)
    single = y.ndim == 2
    if single:
        y, u = y[None], u[None]
    if y.ndim != 3 or y.shape[2] != ny or y.shape[1] < 2:
        raise ValueError(f"y must have shape (N, ny) or (M, N, ny) with ny = {ny} and N >= 2, got {y.shape}")
    if u.shape != y.shape[:2] + (nu,):
        raise ValueError(f"u must have shape {y.shape[:2] + (nu,)} to match y, got {u.shape}")
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(u))):
        raise ValueError("y and u must be finite")
    return y, u, single


def decoder_features(z: np.ndarray, y: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The decoder's input ``[z; y_k; u_k]`` along the last axis.

    Parameters
    ----------
    z : numpy.ndarray, shape (..., nz)
    y : numpy.ndarray, shape (..., ny)
    u : numpy.ndarray, shape (..., nu)

    Returns
    -------
    numpy.ndarray, shape (..., nz + ny + nu)
    """
    return np.concatenate([z, y, u], axis=-1)


def _check_decoder(arrays: Mapping[str, Any], arch: Mapping[str, Any]) -> MLPSpec:
    spec = MLPSpec.from_card(arch, "architecture.decoder", DECODER)
    check_arrays(arrays, {**spec.array_shapes(DECODER), ASINH_SCALE: (spec.n_out,)}, "bank arrays")
    scale = np.asarray(arrays[ASINH_SCALE], dtype=float)
    if not np.all(np.isfinite(scale)) or np.any(scale < 0):
        raise ValueError(f"{ASINH_SCALE} must be finite and >= 0 (0: no transform), got {scale.tolist()}")
    return spec


def decode(arrays: Mapping[str, Any], arch: Mapping[str, Any], features: Any) -> np.ndarray:
    """Evaluate the decoder with its output transform in numpy (float64).

    Parameters
    ----------
    arrays : Mapping[str, array_like]
        ``decoder/*`` MLP arrays and ``decoder/asinh_scale`` (nx,).
    arch : Mapping
        ``{"sizes": [nz + ny + nu, ..., nx], "activation": ...}``.
    features : array_like, shape (..., nz + ny + nu)

    Returns
    -------
    numpy.ndarray, shape (..., nx)
    """
    spec = _check_decoder(arrays, arch)
    f = np.asarray(features, dtype=float)
    if f.shape[-1] != spec.n_in:
        raise ValueError(f"features must have {spec.n_in} entries along the last axis, got shape {f.shape}")
    v = mlp_numpy(spec, arrays, DECODER, f)
    scale = np.asarray(arrays[ASINH_SCALE], dtype=float)
    return np.where(scale > 0, scale * np.sinh(v), v)


def decoder_function(arrays: Mapping[str, Any], arch: Mapping[str, Any], name: str = "bank_decoder") -> ca.Function:
    """CasADi ``(z, y, u) -> xhat``: the decoder MLP on ``[z; y; u]`` and the output transform.

    Parameters
    ----------
    arrays : Mapping[str, array_like]
        ``bank/*`` arrays (for the sizes nz, ny, nu), ``decoder/*`` MLP arrays and
        ``decoder/asinh_scale`` (nx,).
    arch : Mapping
        The decoder's card entry ``{"sizes": [nz + ny + nu, ..., nx], "activation": ...}``.
    name : str
        Function name.

    Returns
    -------
    ca.Function
        Inputs ``z`` (nz,), ``y`` (ny,), ``u`` (nu,); output ``xhat`` (nx,).
    """
    bank = bank_from_arrays(arrays)
    spec = _check_decoder(arrays, arch)
    if spec.n_in != bank.nz + bank.ny + bank.nu:
        raise ValueError(f"decoder input size {spec.n_in} != nz + ny + nu = {bank.nz + bank.ny + bank.nu}")
    mlp = casadi_nets.mlp_function(MLPSpec.from_card(arch, "architecture", DECODER), arrays, DECODER, f"{name}_mlp")
    z, y, u = ca.MX.sym("z", bank.nz), ca.MX.sym("y", bank.ny), ca.MX.sym("u", bank.nu)
    v = mlp(ca.vertcat(z, y, u))
    scale = np.asarray(arrays[ASINH_SCALE], dtype=float)
    out = ca.vertcat(*[float(s) * ca.sinh(v[i]) if s > 0 else v[i] for i, s in enumerate(scale)])
    return ca.Function(name, [z, y, u], [out], ["z", "y", "u"], ["xhat"])


def observer_step(arrays: Mapping[str, Any], arch: Mapping[str, Any], dt: float, name: str = "step") -> ca.Function:
    """The whole observer step in the signature of :attr:`kklcasadi.observer.kkl.KKLObserver.step` (window 1).

    ``(z, w, y, y_next, u_next) -> (z_next, w_next, xhat_next)`` with ``w = u_k`` (1, nu), the input
    held over the interval: ``z_next`` from the exact FOH map, ``w_next = u_next``,
    ``xhat_next = D(z_next, y_next, u_next)``.

    Parameters
    ----------
    arrays, arch
        As in :func:`decoder_function`.
    dt : float
        Sample period.
    name : str
        Function name.
    """
    bank = bank_from_arrays(arrays)
    latent = bank.step_function(dt)
    dec = decoder_function(arrays, arch)
    z, w = ca.MX.sym("z", bank.nz), ca.MX.sym("w", 1, bank.nu)
    y, y_next, u_next = ca.MX.sym("y", bank.ny), ca.MX.sym("y_next", bank.ny), ca.MX.sym("u_next", bank.nu)
    z_next = latent(z, y, y_next, w.T)
    return ca.Function(name, [z, w, y, y_next, u_next], [z_next, u_next.T, dec(z_next, y_next, u_next)],
                       ["z", "w", "y", "y_next", "u_next"], ["z_next", "w_next", "xhat_next"])


def bank_arrays(bank: FilterBank) -> dict[str, np.ndarray]:
    """The bank as arrays ``bank/A`` (nz, nz), ``bank/By`` (nz, ny), ``bank/Bu`` (nz, nu), ``bank/c`` (nz,)."""
    return {"bank/A": np.array(bank.A), "bank/By": np.array(bank.By), "bank/Bu": np.array(bank.Bu),
            "bank/c": np.array(bank.c)}


def bank_from_arrays(arrays: Mapping[str, Any]) -> FilterBank:
    """Inverse of :func:`bank_arrays` (validated)."""
    missing = [k for k in ("bank/A", "bank/By", "bank/Bu", "bank/c") if k not in arrays]
    if missing:
        raise ValueError(f"arrays lack the filter-bank entries {missing}")
    return FilterBank(arrays["bank/A"], arrays["bank/By"], arrays["bank/Bu"], arrays["bank/c"])


def estimate(arrays: Mapping[str, Any], arch: Mapping[str, Any], y: Any, u: Any, dt: float) -> np.ndarray:
    """Reference implementation of the ``bank`` estimator: ``xhat_k = D(z_k, y_k, u_k)``, ``z_0 = 0``.

    Parameters
    ----------
    arrays : Mapping[str, array_like]
        ``bank/*`` (see :func:`bank_arrays`) and ``decoder/*`` arrays.
    arch : Mapping
        The decoder's card entry ``{"sizes": [nz + ny + nu, ..., nx], "activation": ...}``.
    y : array_like, shape (M, N, ny) or (N, ny)
        Measurements ``y_k``.
    u : array_like, shape (M, N, nu) or (N, nu)
        Inputs ``u_k`` held over ``[t_k, t_k+1)``.
    dt : float
        Sample period.

    Returns
    -------
    numpy.ndarray, shape (M, N, nx) or (N, nx)
    """
    bank = bank_from_arrays(arrays)
    y, u, single = _trials(y, u, bank.ny, bank.nu)
    z = bank.run(y, u, dt)
    xhat = decode(arrays, arch, decoder_features(z, y, u))
    return xhat[0] if single else xhat
