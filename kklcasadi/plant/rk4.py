"""The one RK4 of the package: a symbolic classical Runge-Kutta step over one sample interval.

Used by the EKF's discretisation and by the observers' latent step (first-order hold of ``y``
between samples: the right-hand side receives the fraction ``s`` in [0, 1] of the interval).
:func:`stable_substeps` is how many RK4 steps per interval a plant needs to be stable over its box.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping, TypeVar

import numpy as np

from ..validation import positive_int, positive_number
from .signals import UNIT_LEVEL

__all__ = ["rk4_step", "stable_substeps", "substeps_for", "RK4_STEP_LIMIT"]

#: The largest ``h |lambda|`` (RK4 step times the Jacobian's largest eigenvalue modulus) that
#: :func:`stable_substeps` allows: inside classical RK4's stability limits on the negative real axis
#: (2.785) and the imaginary axis (2.828), with a margin.
RK4_STEP_LIMIT = 2.0

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


def stable_substeps(system: Any, dt: float, *, samples: int = 256, seed: int = 0) -> int:
    """RK4 steps per sample interval for ``system`` to be stable everywhere in its box.

    The Jacobian ``df/dx`` is evaluated at ``samples`` states drawn uniformly in the X0 box (and at
    the box's corners where there are at most 256), with inputs drawn in the plant's ``u_box`` (the
    benchmark's ``[-2, 2]`` without one); the answer is the least ``n >= 1`` with
    ``(dt / n) max |lambda| <= RK4_STEP_LIMIT``. A stiff plant (FitzHugh-Nagumo's fast variable at
    the box's edges: ``dt |lambda| = 8.9`` at dt = 0.05) gets several steps, where one RK4 step
    amplifies its fast mode instead of damping it; the paper's other plants get 1.

    Parameters
    ----------
    system : System
        ``x0_box`` (nx, 2), ``u_box`` (nu, 2) or None, ``f_jac``.
    dt : float
        Sample interval.
    samples : int
        Random states (seeded by ``seed``: the answer is a function of the plant and ``dt``).

    Returns
    -------
    int
    """
    dt, samples = positive_number(dt, "dt"), positive_int(samples, "samples")
    box = np.asarray(system.x0_box, dtype=float)
    nx, nu = box.shape[0], int(system.nu)
    rng = np.random.default_rng(seed)
    x = rng.uniform(box[:, 0], box[:, 1], (samples, nx))
    if nx <= 8:
        corners = np.array(np.meshgrid(*box, indexing="ij")).reshape(nx, -1).T
        x = np.vstack([x, corners])
    u_box = np.tile([-UNIT_LEVEL, UNIT_LEVEL], (nu, 1)) if system.u_box is None else np.asarray(system.u_box)
    u = rng.uniform(u_box[:, 0], u_box[:, 1], (x.shape[0], nu))
    jac = np.asarray(system.f_jac.map(x.shape[0])(x.T, u.T)[0])       # (nx, nx * n): the Jacobians side by side
    blocks = jac.reshape(nx, x.shape[0], nx).transpose(1, 0, 2)
    finite = np.all(np.isfinite(blocks), axis=(1, 2))
    rho = float(np.max(np.abs(np.linalg.eigvals(blocks[finite])), initial=0.0))
    return max(1, math.ceil(dt * rho / RK4_STEP_LIMIT))


def substeps_for(system: Any, dt: float, chosen: Mapping[str, int]) -> int:
    """``chosen[system.name]`` where the table has the plant (the counts a benchmark chose for the paper's
    plants, e.g. :data:`kklcasadi.estimators.pf.SUBSTEPS`), else :func:`stable_substeps` (a plant of the user's:
    at least stable over its box)."""
    return int(chosen[system.name]) if system.name in chosen else stable_substeps(system, dt)
