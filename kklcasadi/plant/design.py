"""The latent design ``(A, B)`` of a KKL observer: ``zdot = A z + B y``.

:class:`Design` validates a pair: ``A`` Hurwitz and ``(A, B)`` controllable, judged by the PBH test
at every eigenvalue of ``A`` with a relative margin (:attr:`Design.controllability_margin`), which
is right at every size (the rank of the controllability matrix is not: its columns grow like
``|eig(A)|^nz``). :meth:`Design.paper` is the HyperKKL paper's pair; :meth:`Design.default` spreads
real poles over the plant's own time scales, one block of latents per output.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import scipy.linalg

from ..validation import Text, error, finite_array, positive_int
from .systems import System

__all__ = ["Design", "time_scales", "MIN_MARGIN", "MIN_SPREAD", "MAX_SPREAD"]

#: Smallest accepted :attr:`Design.controllability_margin`: below it a pair is uncontrollable to
#: working precision (an unreachable defective eigenvalue shows only about ``eps^(1/2)``).
MIN_MARGIN = 1e-7
#: Bounds on the ratio of the fastest to the slowest pole rate that :meth:`Design.default` spreads.
MIN_SPREAD, MAX_SPREAD = 5.0, 25.0
#: Singular values of ``A - lam I`` below this (relative to ``|A|``) count an eigenvector of ``lam``.
_CLUSTER = 1e-4
#: States of the X0 box at which :meth:`Design.default` reads the plant's time scales.
_SCALE_SAMPLES = 64


def _frozen(arr: np.ndarray) -> np.ndarray:
    out = np.array(arr, dtype=float, copy=True)
    out.setflags(write=False)
    return out


def _pbh(A: np.ndarray, B: np.ndarray) -> tuple[float, complex, int, np.ndarray]:
    """The PBH margin ``min_lam s_min([A - lam I, B]) / |[A, B]|_2`` over the eigenvalues of ``A``.

    Each conjugate pair is evaluated once. A defective eigenvalue is computed only to about
    ``eps^(1/k)``, but the singular value there is still below ``eps^(1/2)`` when its mode is
    unreachable (it shrinks like a power of the eigenvalue's error).

    Returns
    -------
    margin : float
    lam : complex
        Where the minimum is attained.
    multiplicity : int
        Geometric multiplicity of ``lam``: singular values of ``A - lam I`` below ``_CLUSTER |A|``.
    w : numpy.ndarray, shape (nz,)
        The left singular vector of the minimum (the least reachable direction of the latent).
    """
    nz = A.shape[0]
    if _filter_bank(A, B):
        return _pbh_filters(A, B)
    eig = np.linalg.eigvals(A)
    scale = float(np.linalg.norm(np.hstack([A, B]), 2))
    points = eig[eig.imag >= 0]
    values = [scipy.linalg.svdvals(np.hstack([A - lam * np.eye(nz), B]), check_finite=False)[-1]
              for lam in points]
    lam = complex(points[int(np.argmin(values))])
    u, _, _ = np.linalg.svd(np.hstack([A - lam * np.eye(nz), B]))
    radius = _CLUSTER * float(np.linalg.norm(A, 2))
    multiplicity = int(np.sum(scipy.linalg.svdvals(A - lam * np.eye(nz)) <= radius))
    return float(min(values)) / scale, lam, multiplicity, u[:, -1]


def _filter_bank(A: np.ndarray, B: np.ndarray) -> bool:
    """Whether ``A`` is diagonal and every latent is driven by one output at most (as
    :meth:`Design.from_poles` and :meth:`Design.default` make them)."""
    return bool(np.all(A == np.diag(np.diag(A))) and np.all(np.count_nonzero(B, axis=1) <= 1))


def _pbh_filters(A: np.ndarray, B: np.ndarray, iterations: int = 200) -> tuple[float, complex, int, np.ndarray]:
    """:func:`_pbh` of a diagonal ``A`` whose latents are driven by one output each, in ``O(nz^2)``.

    At ``lam = a_j``, ``M M^T = D + B B^T`` with ``M = [A - lam I, B]`` and ``D = diag((a_i - lam)^2)``
    is block-diagonal by output (a latent that no output drives is a block of its own), and the
    smallest eigenvalue of a block ``D_b + b b^T`` is the smallest root ``mu`` of the secular equation
    ``1 + sum_i b_i^2 / (d_i - mu) = 0``, in ``[min d, min(second d, min d + |b|^2)]``: found by
    bisection on ``mu - min d`` for all eigenvalues at once. ``s_min(M) = sqrt(min mu)``; the left
    singular vector is the block's eigenvector ``b_i / (d_i - mu)``.
    """
    nz = A.shape[0]
    a = np.diag(A)
    scale = float(np.linalg.norm(np.hstack([A, B]), 2))
    lam = a[:, None]                                                    # (nz eigenvalues, 1)
    d = (a[None, :] - lam) ** 2                                         # d[j, i] = (a_i - a_j)^2
    driver = np.where(np.count_nonzero(B, axis=1) == 1, np.argmax(B != 0, axis=1), -1)
    best = np.full(nz, np.inf)
    vectors = np.zeros((nz, nz))
    for group in np.unique(driver):
        rows = np.flatnonzero(driver == group)
        if group < 0:                                                    # undriven latents: mu = d_i
            values = d[:, rows]
            pick = np.argmin(values, axis=1)
            mu = values[np.arange(nz), pick]
            better = mu < best
            best[better] = mu[better]
            vectors[better] = 0.0
            vectors[better, rows[pick[better]]] = 1.0
            continue
        b2 = B[rows, group] ** 2
        db = d[:, rows]                                                  # (nz, block)
        order = np.sort(db, axis=1)
        low = order[:, 0]
        second = order[:, 1] if len(rows) > 1 else np.full(nz, np.inf)
        gap = np.minimum(second, low + b2.sum()) - low                  # mu - low lies in (0, gap]
        shifted = db - low[:, None]                                      # d_i - low >= 0, exact zeros kept
        lo, hi = np.zeros(nz), gap.copy()
        tie = np.sum(shifted == 0.0, axis=1) > 1                        # a repeated d: mu = low exactly
        hi[tie] = 0.0
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            with np.errstate(divide="ignore"):
                secular = 1.0 + np.sum(b2 / (shifted - mid[:, None]), axis=1)
            below = secular < 0                                          # the root lies above mid
            lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
        mu = low + 0.5 * (lo + hi)
        better = mu < best
        best[better] = mu[better]
        with np.errstate(divide="ignore", invalid="ignore"):
            v = B[rows, group][None, :] / (db - mu[:, None])
        at_mu = ~np.isfinite(v).all(axis=1)              # mu = d_i to rounding: the limit direction e_i
        v[at_mu] = np.where(np.isfinite(v[at_mu]), 0.0, 1.0)
        for j in np.flatnonzero(tie):                    # two latents at one d: b's orthogonal pair
            first, second = np.flatnonzero(shifted[j] == 0.0)[:2]
            v[j] = 0.0
            v[j, first], v[j, second] = B[rows[second], group], -B[rows[first], group]
        vectors[better] = 0.0
        vectors[np.ix_(np.flatnonzero(better), rows)] = v[better]
    j = int(np.argmin(best))
    w = vectors[j] / np.linalg.norm(vectors[j])
    radius = _CLUSTER * float(np.linalg.norm(A, 2))
    multiplicity = int(np.sum(np.abs(a - a[j]) <= radius))
    return float(np.sqrt(max(best[j], 0.0))) / scale, complex(a[j]), multiplicity, w


def _number(lam: complex) -> str:
    return f"{lam.real:.6g}" if lam.imag == 0 else f"{lam.real:.6g}{lam.imag:+.6g}j"


def time_scales(system: System) -> tuple[float, float]:
    """Typical rate ``omega`` (rad/s) and spread of the plant's linearisations over its X0 box at ``u = 0``.

    ``omega`` is the median over :data:`_SCALE_SAMPLES` box states of the spectral radius of
    ``df/dx``; the spread is the ratio of the 90 % to the 10 % quantile of all their nonzero
    ``|eig(df/dx)|``. A plant without a time scale (``df/dx`` nilpotent everywhere) gets 1 and 1.
    """
    n, nx = _SCALE_SAMPLES, system.nx
    x = system.sample_box(n, 0)
    jac = np.asarray(system.f_jac.map(n)(x.T, np.zeros((system.nu, n)))[0])
    jac = jac.reshape(nx, n, nx).transpose(1, 0, 2)
    jac = jac[np.all(np.isfinite(jac), axis=(1, 2))]
    mags = np.abs(np.linalg.eigvals(jac)) if len(jac) else np.zeros((0, nx))
    omega = float(np.median(mags.max(axis=1))) if len(mags) else 0.0
    if not omega > 0:
        return 1.0, 1.0
    nonzero = mags[mags > 1e-9 * omega]
    return omega, float(np.quantile(nonzero, 0.9) / np.quantile(nonzero, 0.1))


def _blocks(nz: int, ny: int) -> np.ndarray:
    """The output that drives each latent: ``ny`` contiguous blocks, the first ``nz % ny`` one longer."""
    sizes = [nz // ny + (j < nz % ny) for j in range(ny)]
    return np.repeat(np.arange(ny), sizes)


@dataclass(frozen=True, eq=False)
class Design:
    """A validated latent pair: ``A`` (nz, nz) Hurwitz and ``B`` (nz, ny) with ``(A, B)`` controllable.

    Controllability is the PBH test: ``[A - lam I, B]`` has full row rank at every eigenvalue
    ``lam`` of ``A``, judged by its smallest singular value relative to ``|[A, B]|_2``
    (:attr:`controllability_margin` >= :data:`MIN_MARGIN`). It costs one SVD of an
    (nz, nz + ny) matrix per eigenvalue (about 0.2 s at nz = 129, 7 s at nz = 387, 25 s at nz = 516);
    for a diagonal ``A`` with every latent driven by one output at most (:meth:`from_poles`,
    :meth:`default`) the blocks' secular equations give the same margin in ``O(nz^2)``.

    Parameters
    ----------
    A : array_like, shape (nz, nz)
    B : array_like, shape (nz, ny)

    Attributes
    ----------
    nz, ny : int
    kappa : float
        Condition number of the eigenvector matrix of ``A`` (1 for a diagonal ``A``).
    lam : float
        Decay rate ``-max Re eig(A)`` (> 0).
    controllability_margin : float
        ``min over eigenvalues lam of A`` of ``s_min([A - lam I, B]) / |[A, B]|_2``, in (0, 1]:
        the relative size of the smallest perturbation of ``(A, B)`` at ``lam`` that makes the pair
        uncontrollable (an upper bound on the distance to uncontrollability). Unchanged when
        ``A`` and ``B`` are scaled together.
    """

    A: np.ndarray
    B: np.ndarray
    controllability_margin: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        A = np.asarray(self.A, dtype=float)
        B = np.asarray(self.B, dtype=float)
        if B.ndim == 1:
            B = B[:, None]
        if A.ndim != 2 or A.shape[0] != A.shape[1] or A.shape[0] == 0:
            raise error("A", "a non-empty square matrix (nz, nz)", Text(f"shape {A.shape}"))
        if B.ndim != 2 or B.shape[0] != A.shape[0]:
            raise error("B", f"shape (nz, ny) = ({A.shape[0]}, ny)", Text(f"shape {B.shape}"))
        finite_array(A, "A")
        finite_array(B, "B")
        eig = np.linalg.eigvals(A)
        if np.max(eig.real) >= 0:
            raise error("A", "a Hurwitz matrix (all eigenvalues with negative real part)",
                        Text(f"max Re eig(A) = {np.max(eig.real):.6g}"))
        margin, lam, multiplicity, w = _pbh(A, B)
        if not margin >= MIN_MARGIN:
            if multiplicity > B.shape[1]:
                fix = (f"lam has {multiplicity} independent eigenvectors and B {B.shape[1]} column(s): "
                       f"give A distinct eigenvalues (or B {multiplicity} independent columns).")
            else:
                latents = np.flatnonzero(np.abs(w) >= 0.5 * np.abs(w).max())[:8].tolist()
                fix = (f"B does not reach the mode of lam: its left eigenvector w lies on latents {latents} "
                       "(0-based) and w^T B ~ 0; give B nonzero rows there or move that eigenvalue of A.")
            raise error("(A, B)", f"a controllable pair (PBH: s_min([A - lam I, B]) >= {MIN_MARGIN:g} |[A, B]| "
                        "at every eigenvalue lam of A)",
                        Text(f"{margin:.3g} |[A, B]| at lam = {_number(lam)}"), fix)
        object.__setattr__(self, "A", _frozen(A))
        object.__setattr__(self, "B", _frozen(B))
        object.__setattr__(self, "controllability_margin", margin)

    @classmethod
    def paper(cls, system: System) -> Design:
        """The HyperKKL paper's pair: ``nz = ny (2 nx + 1)``, ``A = -diag(1..nz)``, ``B = ones((nz, ny))``.

        The benchmark protocol (``docs/protocol.md``) and the shipped models of the paper's four
        systems use it; training picks it for plants with ``paper_design`` set.
        """
        if not isinstance(system, System):
            raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
        nz = system.ny * (2 * system.nx + 1)
        return cls(-np.diag(np.arange(1.0, nz + 1.0)), np.ones((nz, system.ny)))

    @classmethod
    def from_poles(cls, poles: Sequence[float], ny: int) -> Design:
        """Unit-gain first-order filters of the outputs: ``zdot_i = -p_i (z_i - y_j(i))``.

        So ``A = -diag(poles)`` and ``B[i, j(i)] = p_i``; latent ``i`` belongs to output ``j(i)`` in
        ``ny`` contiguous blocks (sizes ``nz // ny``, the first ``nz % ny`` one longer), and each
        latent settles at its output for a constant ``y`` (``z`` has the units and size of ``y``).

        Parameters
        ----------
        poles : sequence of float, shape (nz,)
            Positive rates ``p_i``, in latent order (block by block).
        ny : int
            Outputs, ``1 <= ny <= nz``.

        Returns
        -------
        Design
        """
        rates = finite_array(poles, "poles")
        ny = positive_int(ny, "ny")
        if rates.ndim != 1 or len(rates) < ny:
            raise error("poles", f"a sequence of at least ny = {ny} rates", Text(f"shape {rates.shape}"))
        if np.any(rates <= 0):
            raise error("poles", "positive rates (the poles are -rates)", rates.tolist())
        B = np.zeros((len(rates), ny))
        B[np.arange(len(rates)), _blocks(len(rates), ny)] = rates
        return cls(-np.diag(rates), B)

    @classmethod
    def default(cls, system: System, *, nz: int | None = None, poles: Sequence[float] | None = None) -> Design:
        """Per-output blocks of real poles spread over the plant's own time scales.

        With ``omega`` the median spectral radius of ``df/dx(x, 0)`` over the X0 box and ``s`` the
        spread of its ``|eig|`` (90 % over 10 % quantile) clipped to [:data:`MIN_SPREAD`,
        :data:`MAX_SPREAD`], the ``nz`` rates are ``omega * s^e_i``, ``e_i = (i - nz//2 + 1/2) / nz``:
        log-spaced over less than ``[omega / sqrt(s), omega sqrt(s)]``, with ``omega`` halfway
        between two of them (a linear plant's own rate is never a pole). They are dealt to the
        ``ny`` blocks in turn, so every block spans the range and no two latents share a pole;
        see :meth:`from_poles` for the filters. The stiffness ``max/min rate`` stays below ``s``
        at every size (the paper's ``-diag(1..nz)`` reaches 65 at nx = 32).

        Parameters
        ----------
        system : System
        nz : int, optional
            Latent dimension, at least ``ny``; default ``ny (2 nx + 1)``.
        poles : sequence of float, optional
            Positive rates instead of the plant's: ``nz`` of them (per latent, block by block), or
            ``nz // ny`` (the same rates in every block, ``nz`` a multiple of ``ny``).

        Returns
        -------
        Design
        """
        if not isinstance(system, System):
            raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
        ny = system.ny
        nz = ny * (2 * system.nx + 1) if nz is None else positive_int(nz, "nz")
        if nz < ny:
            raise error("nz", f"at least ny = {ny} (one latent block per output)", nz)
        if poles is None:
            omega, spread = time_scales(system)
            s = float(np.clip(spread, MIN_SPREAD, MAX_SPREAD))
            rates = omega * s ** ((np.arange(nz) - nz // 2 + 0.5) / nz)
            return cls.from_poles(np.concatenate([rates[j::ny] for j in range(ny)]), ny)
        rates = finite_array(poles, "poles")
        if rates.shape == (nz // ny,) and nz % ny == 0:
            rates = np.tile(rates, ny)
        if rates.shape != (nz,):
            raise error("poles", f"{nz} rates (one per latent) or {nz // ny} (one per latent of a block, "
                        f"the same in each of the {ny} blocks)", Text(f"shape {rates.shape}"))
        return cls.from_poles(rates, ny)

    @property
    def nz(self) -> int:
        return self.A.shape[0]

    @property
    def ny(self) -> int:
        return self.B.shape[1]

    @property
    def lam(self) -> float:
        return float(-np.max(np.linalg.eigvals(self.A).real))

    @property
    def kappa(self) -> float:
        _, vecs = np.linalg.eig(self.A)
        return float(np.linalg.cond(vecs))

    def latent_equilibrium(self, y: object) -> np.ndarray:
        """The latent equilibrium ``z = -A^{-1} B y`` for constant outputs, row-wise.

        Parameters
        ----------
        y : array_like, shape (M, ny)

        Returns
        -------
        numpy.ndarray, shape (M, nz)
        """
        y = np.asarray(y, dtype=float)
        if y.ndim != 2 or y.shape[1] != self.ny:
            raise ValueError(f"y: expected shape (M, {self.ny}), received {y.shape}.")
        return -np.linalg.solve(self.A, self.B @ y.T).T

    def forgetting_time(self, z_gap: float, tol: float = 1e-6) -> float:
        """Time after which ``kappa * exp(-lam t) * z_gap <= tol`` (the decay of a wrong initial latent)."""
        if z_gap <= 0:
            return 0.0
        return max(0.0, float(np.log(self.kappa * z_gap / tol) / self.lam))

    def latent_bound(self, y_max: float) -> float:
        """Bound on ``|T(x)|`` when ``|y| <= y_max`` along the past: ``kappa |B| y_max / lam``."""
        return self.kappa * float(np.linalg.norm(self.B, 2)) * float(y_max) / self.lam

    def __repr__(self) -> str:
        return f"Design(nz={self.nz}, ny={self.ny}, lam={self.lam:.3g}, kappa={self.kappa:.3g})"
