"""The covariance head's inflation by the measurement residual (torch-free): the head does not see the noise level.

The covariance head (:mod:`kklcasadi.model.variants.covariance`) is fit and calibrated at the noise level of its
fitting runs; where the measurements are noisier than that, the estimates are further off than it says (twice the
noise: 2-sigma coverage near 68 % instead of 95 %). The observer sees the noise level in its own residual: with
``P_k`` the head's covariance of the estimate ``xhat_k`` and ``y_k`` the measurement the estimate was decoded with,

    nu_k  = y_k - h(xhat_k)                            (the residual, ny)
    S_k   = H_k P_k H_k^T + diag(R)                    (H_k = dh/dx at xhat_k; R the card's measurement variances)
    r_k   = nu_k^T S_k^-1 nu_k / ny
    m_0   = 1,   m_k = (1 - a) m_{k-1} + a r_k / c     (k >= 1; a = 1 - exp(-dt / time_constant))
    P'_k  = max(1, m_k) P_k

``m`` is one more state the observer's step carries (the CasADi step's sixth input and fifth output, the C
``name_step``'s ``arg[5]`` and ``res[4]``); ``c`` is the mean of ``r`` on in-distribution validation runs, so that
``m`` stays near 1 there and the calibrated head is left as it is, and grows with the residual's variance where
the noise is larger. ``R`` is the fitting runs' measurement noise variance (the residual's scale under the
head's calibration); ``c`` and the time constant are chosen on validation runs
(``benchmarks/covariance_heads.py``). The estimates do not depend on ``m``: they are bitwise those of the step
without it. It is not a correction for a wrong model: a plant whose parameters differ from the model's is
tracked in ``y`` while the unmeasured states drift, and the residual does not see that.

:func:`inflation_numpy` is the reference; :func:`inflation_function` the same recursion in CasADi (what the
observer's step and its C code compute).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import casadi as ca
import numpy as np

from ...nets.specs import field_error
from ...plant.systems import System
from ...validation import is_number

__all__ = ["INFLATION", "Inflation", "residual_statistic", "inflation_numpy", "inflation_function", "fold"]

#: The card's entry (``architecture.inflation``).
INFLATION = "inflation"
_KEYS = ("R", "c", "time_constant")


def _positive(value: Any) -> bool:
    return is_number(value) and math.isfinite(value) and value > 0


@dataclass(frozen=True)
class Inflation:
    """The inflation's constants (``architecture.inflation``).

    Attributes
    ----------
    R : tuple of float
        The measurement noise variance per output (ny), > 0.
    c : float
        The mean of the residual statistic ``r`` on in-distribution validation runs, > 0.
    time_constant : float
        Of the statistic's exponential average, in seconds, > 0.
    """

    R: tuple[float, ...]
    c: float
    time_constant: float

    @classmethod
    def from_card(cls, entry: Any, where: str, ny: int) -> Inflation:
        """The constants of a card's ``architecture.inflation`` (``{"R": [ny numbers > 0], "c": number > 0,
        "time_constant": number > 0}``), checked; a bad one raises the package's one-line error naming it."""
        name = f"architecture.{INFLATION}"
        if not isinstance(entry, Mapping) or set(entry) != set(_KEYS):
            received = sorted(entry) if isinstance(entry, Mapping) else entry
            raise field_error(where, name, f"an object with exactly the keys {list(_KEYS)}", received,
                              "docs/model-format.md (benchmarks/covariance_heads.py writes it).")
        R = entry["R"]
        if not (isinstance(R, list) and len(R) == ny and all(_positive(v) for v in R)):
            raise field_error(where, f"{name}.R", f"a list of ny = {ny} finite variances > 0", R,
                              "The measurement noise variance per output of the head's fitting runs.")
        for key in ("c", "time_constant"):
            if not _positive(entry[key]):
                raise field_error(where, f"{name}.{key}", "a finite number > 0", entry[key],
                                  "Chosen on validation runs by benchmarks/covariance_heads.py.")
        return cls(tuple(float(v) for v in R), float(entry["c"]), float(entry["time_constant"]))

    def to_card(self) -> dict:
        return {"R": list(self.R), "c": self.c, "time_constant": self.time_constant}

    def weight(self, dt: float) -> float:
        """The exponential average's weight of a new sample, ``a = 1 - exp(-dt / time_constant)``."""
        return -math.expm1(-dt / self.time_constant)


def residual_statistic(y: np.ndarray, hx: np.ndarray, H: np.ndarray, P: np.ndarray, R: Any) -> np.ndarray:
    """``r = nu^T (H P H^T + diag(R))^-1 nu / ny`` with ``nu = y - h(xhat)`` (numpy; ``hx`` (..., ny) the values
    ``h(xhat)``, ``H`` (..., ny, nx) its Jacobians, ``P`` (..., nx, nx) the head's covariances) -> (...)."""
    nu = np.asarray(y, dtype=float) - hx
    S = H @ P @ np.swapaxes(H, -1, -2) + np.diag(np.asarray(R, dtype=float))
    return np.einsum("...i,...i->...", nu, np.linalg.solve(S, nu[..., None])[..., 0]) / nu.shape[-1]


def inflation_numpy(inflation: Inflation, system: System, dt: float, y: np.ndarray, xhat: np.ndarray,
                    P: np.ndarray) -> np.ndarray:
    """The factors ``max(1, m_k)`` of runs (the module docstring's recursion; the reference of
    :func:`inflation_function`).

    Parameters
    ----------
    inflation : Inflation
    system : System
        The plant (its ``h`` and ``h_jac``).
    dt : float
        The sample period.
    y : numpy.ndarray, shape (M, N, ny)
    xhat : numpy.ndarray, shape (M, N, nx)
    P : numpy.ndarray, shape (M, N, nx, nx)
        The head's covariances of the estimates.

    Returns
    -------
    numpy.ndarray, shape (M, N)
        1 at the first sample of each run.
    """
    M, N, nx = xhat.shape
    flat = np.asarray(xhat, dtype=float).reshape(-1, nx).T
    hx = np.asarray(system.h.map(M * N)(flat)).T.reshape(M, N, system.ny)
    H = np.asarray(system.h_jac.map(M * N)(flat)).reshape(system.ny, M * N, nx).transpose(1, 0, 2)
    r = residual_statistic(y, hx, H.reshape(M, N, system.ny, nx), P, inflation.R) / inflation.c
    a = inflation.weight(dt)
    m = np.ones((M, N))
    for k in range(1, N):
        m[:, k] = (1 - a) * m[:, k - 1] + a * r[:, k]
    return np.maximum(1.0, m)


def inflation_function(inflation: Inflation, system: System, dt: float) -> ca.Function:
    """``inflation(m, y, xhat, P) -> (m_next, P_inflated)``: one step of the recursion (module docstring) at the
    sample whose measurement is ``y`` (ny, 1), estimate ``xhat`` (nx, 1) and head covariance ``P`` (nx, nx); ``m``
    the state after the previous sample. Plain scalar expressions (the residual's small solve expanded), so that
    its C equals the CasADi VM."""
    nx, ny = system.nx, system.ny
    m, y, x = ca.SX.sym("m"), ca.SX.sym("y", ny), ca.SX.sym("xhat", nx)
    P = ca.SX.sym("P", nx, nx)
    nu = y - system.h(x)
    H = system.h_jac(x)
    S = ca.mtimes(ca.mtimes(H, P), H.T) + ca.diag(ca.DM(list(inflation.R)))
    r = ca.dot(nu, ca.solve(S, nu)) / ny
    a = inflation.weight(dt)
    m_next = (1 - a) * m + (a / inflation.c) * r
    return ca.Function("inflation", [m, y, x, P], [m_next, ca.fmax(1.0, m_next) * P],
                       ["m", "y", "xhat", "P"], ["m_next", "P_inflated"])


def fold(step: ca.Function, name: str, n: int) -> ca.Function:
    """An observer's ``step`` or ``step_covariance`` folded over ``n`` steps (``mapaccum``): ``z`` and ``w`` (its
    first two inputs and outputs) carried from step to step, and the inflation's state ``m`` (a sixth input and
    fifth output, where the step has them: :attr:`kklcasadi.KKLObserver.step_covariance`)."""
    if step.n_in() == 6:
        return step.mapaccum(name, n, [0, 1, 5], [0, 1, 4])
    return step.mapaccum(name, n, [0, 1], [0, 1])
