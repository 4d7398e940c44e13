"""A linear latent filter bank of the measurement and the input (torch-free): the ``bank`` variant's latent.

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

The latent may end in model copies of the plant (:class:`kklcasadi.model.variants.copies.ModelCopies`,
arrays ``copies/*``): their latents follow the filters' in ``z`` (:func:`latent_size`, :func:`latent_run`,
:func:`latent_step`); then, optionally, the augmented EKF's block
(:class:`kklcasadi.model.variants.ekfblock.EKFBlock`). The decoder that reads the latent is
:mod:`kklcasadi.model.variants.bankdecoder`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np

from ...nets.hold import FOHMatrices, foh_matrices
from ...validation import error
from .copies import ModelCopies, copy_count
from .ekfblock import EKFBlock

__all__ = ["FilterBank", "bank_arrays", "bank_from_arrays", "latent_size", "latent_run", "latent_step", "as_trials",
           "check_copies"]


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
        y, u, single = as_trials(y, u, self.ny, self.nu)
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


def as_trials(y: Any, u: Any, ny: int, nu: int) -> tuple[np.ndarray, np.ndarray, bool]:
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


def latent_step(bank: FilterBank, dt: float, name: str = "latent_step", *,
                copies: ModelCopies | None = None, ekf: EKFBlock | None = None) -> ca.Function:
    """CasADi ``(z, y, y_next, u) -> z_next`` (nz,): the filter bank's exact step (:meth:`FilterBank.step_function`),
    the model copies' (:meth:`ModelCopies.step_function`) and the augmented EKF block's
    (:meth:`EKFBlock.step_function`), what :func:`latent_run` takes per sample."""
    filters = bank.step_function(dt)
    if copies is None and ekf is None:
        return filters
    parts = [(bank.nz, filters)] + ([] if copies is None else [(copies.nz, copies.step_function(dt))]) \
        + ([] if ekf is None else [(ekf.nz, ekf.step_function())])
    z, u = ca.MX.sym("z", sum(n for n, _ in parts)), ca.MX.sym("u", bank.nu)
    y, y_next = ca.MX.sym("y", bank.ny), ca.MX.sym("y_next", bank.ny)
    out, i = [], 0
    for n, step in parts:
        out.append(step(z[i:i + n], y, y_next, u))
        i += n
    return ca.Function(name, [z, y, y_next, u], [ca.vertcat(*out)], ["z", "y", "y_next", "u"], ["z_next"])


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


def latent_size(arrays: Mapping[str, Any], ekf: EKFBlock | None = None) -> int:
    """The latent's size: the filter bank's latents, the model copies' (``copies/gains``), if any, and the
    augmented EKF block's (``ekf``; it has no arrays)."""
    return bank_from_arrays(arrays).nz + copy_count(arrays) + (0 if ekf is None else ekf.nz)


def check_copies(arrays: Mapping[str, Any], copies: ModelCopies | None) -> None:
    n = copy_count(arrays)
    if n and copies is None:
        raise ValueError(f"copies: expected the ModelCopies of the arrays' copies/gains ({n} latents: "
                         "ModelCopies.from_arrays(arrays, system, substeps)), received None.")
    if copies is not None and copies.nz != n:
        raise ValueError(f"copies: expected model copies with {n} latents (the arrays' copies/gains), received "
                         f"{copies.nz}.")


def latent_run(bank: FilterBank, y: np.ndarray, u: np.ndarray, dt: float, *,
               copies: ModelCopies | None = None, ekf: EKFBlock | None = None) -> np.ndarray:
    """The latent from ``z_0 = 0`` for many trials: the filter bank's, then the model copies', then the augmented
    EKF block's.

    Parameters
    ----------
    bank : FilterBank
    y : numpy.ndarray, shape (M, N, ny)
    u : numpy.ndarray, shape (M, N, nu)
    dt : float
    copies : ModelCopies or None
        The latent's model copies, if any (a model's: :meth:`kklcasadi.model.variants.bank.BankSpec.model_copies`).
    ekf : EKFBlock or None
        The latent's augmented EKF block, if any (a model's: :meth:`kklcasadi.model.variants.bank.BankSpec.ekf_block`;
        its sample period is ``dt``).

    Returns
    -------
    numpy.ndarray, shape (M, N, nz)
    """
    if ekf is not None and ekf.dt != dt:
        raise error("dt", f"the EKF block's sample period {ekf.dt}", dt)
    parts = [bank.run(y, u, dt)] + ([] if copies is None else [copies.run(y, u, dt)]) \
        + ([] if ekf is None else [ekf.run(y, u)])
    return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=-1)
