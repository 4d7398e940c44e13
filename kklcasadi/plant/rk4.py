"""The one RK4 of the package: a symbolic classical Runge-Kutta step over one sample interval.

Used by the EKF's discretisation and by the observers' latent step (first-order hold of ``y``
between samples: the right-hand side receives the fraction ``s`` in [0, 1] of the interval).
"""

from __future__ import annotations

from typing import Callable, TypeVar

__all__ = ["rk4_step"]

S = TypeVar("S")


def rk4_step(rhs: Callable[[float, S], S], x: S, h: object, substeps: int = 1) -> S:
    """Advance ``x`` over one interval of length ``h`` with ``substeps`` classical RK4 steps.

    Parameters
    ----------
    rhs : callable ``rhs(s, x) -> xdot``
        Right-hand side; ``s`` is the fraction of the interval elapsed (0 at its start, 1 at its
        end), so a first-order hold of a measurement is ``y_k + s (y_k+1 - y_k)``.
    x : casadi.SX, casadi.MX or numpy.ndarray
        State at the start of the interval.
    h : float or symbolic scalar
        Interval length.
    substeps : int
        Number of equal RK4 steps inside the interval.

    Returns
    -------
    Same type as ``x``: the state at the end of the interval.
    """
    if not isinstance(substeps, int) or substeps < 1:
        kind = ValueError if isinstance(substeps, int) else TypeError
        raise kind(f"substeps: expected a positive int, received {substeps!r}.")
    ds = 1.0 / substeps
    step = h * ds
    for i in range(substeps):
        s0 = i * ds
        k1 = rhs(s0, x)
        k2 = rhs(s0 + ds / 2, x + step / 2 * k1)
        k3 = rhs(s0 + ds / 2, x + step / 2 * k2)
        k4 = rhs(s0 + ds, x + step * k3)
        x = x + step / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x
