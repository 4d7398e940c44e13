"""The exact sample-interval map of a linear latent under a first-order hold of ``y``.

Over ``[t_k, t_k+1]`` the latent ``zdot = A z + By y + Bu u + c`` sees ``y`` interpolated linearly
between ``y_k`` and ``y_k+1`` and ``u`` held at ``u_k`` (docs/design.md, "Between samples"). With
``d = (y_k+1 - y_k) / dt`` the augmented state ``(z, y, d[, u][, 1])``, ``ydot = d`` and the rest
constant, is linear and time-invariant; the first block row of its matrix exponential
``[Ad, Py, Pd, Pu, pc]`` gives ``z_k+1 = Ad z_k + (Py - Pd / dt) y_k + (Pd / dt) y_k+1 + Pu u_k + pc``.
The input and constant columns are in the augmented matrix only where they are given, so a latent
without them gets the exponential of the smaller matrix.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.linalg import expm

from ..validation import error

__all__ = ["FOHMatrices", "foh_matrices"]


@dataclass(frozen=True, eq=False)
class FOHMatrices:
    """Exact one-step map ``z_k+1 = Ad z_k + Gy y_k + Gy_next y_k+1 + Gu u_k + g``.

    Attributes
    ----------
    Ad : numpy.ndarray, shape (nz, nz)
    Gy, Gy_next : numpy.ndarray, shape (nz, ny)
    Gu : numpy.ndarray, shape (nz, nu)
        Empty (nz, 0) when the latent has no input term.
    g : numpy.ndarray, shape (nz,)
        Zeros when the latent has no constant term.
    """

    Ad: np.ndarray
    Gy: np.ndarray
    Gy_next: np.ndarray
    Gu: np.ndarray
    g: np.ndarray


def foh_matrices(A: np.ndarray, By: np.ndarray, dt: float, *, Bu: Optional[np.ndarray] = None,
                 c: Optional[np.ndarray] = None) -> FOHMatrices:
    """Exact discretisation of ``zdot = A z + By y + Bu u + c`` over one sample period.

    Parameters
    ----------
    A : numpy.ndarray, shape (nz, nz)
    By : numpy.ndarray, shape (nz, ny)
    dt : float
        Sample period (> 0).
    Bu : numpy.ndarray, shape (nz, nu), optional
        Input term (``u`` held over the interval).
    c : numpy.ndarray, shape (nz,), optional
        Constant drive.

    Returns
    -------
    FOHMatrices
    """
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise error("dt", "a finite number > 0", dt)
    nz, ny = By.shape
    nu = 0 if Bu is None else Bu.shape[1]
    n = nz + 2 * ny + nu + (c is not None)
    M = np.zeros((n, n))
    M[:nz, :nz] = A
    M[:nz, nz:nz + ny] = By
    M[nz:nz + ny, nz + ny:nz + 2 * ny] = np.eye(ny)
    if Bu is not None:
        M[:nz, nz + 2 * ny:nz + 2 * ny + nu] = Bu
    if c is not None:
        M[:nz, -1] = c
    E = expm(M * dt)[:nz]
    Py, Pd = E[:, nz:nz + ny], E[:, nz + ny:nz + 2 * ny]
    return FOHMatrices(E[:, :nz], Py - Pd / dt, Pd / dt, E[:, nz + 2 * ny:nz + 2 * ny + nu],
                       E[:, -1] if c is not None else np.zeros(nz))
