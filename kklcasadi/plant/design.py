"""The latent design ``(A, B)`` of a KKL observer: ``zdot = A z + B y``."""

from __future__ import annotations

from dataclasses import dataclass

import control
import numpy as np

from ..validation import Text, error, finite_array
from .systems import System

__all__ = ["Design"]


def _frozen(arr: np.ndarray) -> np.ndarray:
    out = np.array(arr, dtype=float, copy=True)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class Design:
    """A validated latent pair: ``A`` (nz, nz) Hurwitz and ``B`` (nz, ny) with ``(A, B)`` controllable.

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
    """

    A: np.ndarray
    B: np.ndarray

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
        rank = np.linalg.matrix_rank(control.ctrb(A, B))
        if rank < A.shape[0]:
            raise error("(A, B)", f"a controllable pair (controllability matrix of rank nz = {A.shape[0]})",
                        Text(f"rank {rank}"), "Give A distinct eigenvalues or change B.")
        object.__setattr__(self, "A", _frozen(A))
        object.__setattr__(self, "B", _frozen(B))

    @classmethod
    def default(cls, system: System) -> Design:
        """The paper's choice: ``nz = ny (2 nx + 1)``, ``A = -diag(1..nz)``, ``B = ones((nz, ny))``."""
        if not isinstance(system, System):
            raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
        nz = system.ny * (2 * system.nx + 1)
        return cls(-np.diag(np.arange(1.0, nz + 1.0)), np.ones((nz, system.ny)))

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
