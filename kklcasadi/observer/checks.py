"""The observer's checks: of the model against the plant, of the discretisation, of sampled data.

One-line errors that name the argument, what was expected and what was received (the trial and sample
of a bad value); the domain monitor's boxes. Used by :mod:`kklcasadi.observer.kkl`.
"""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from ..model.card import ModelSpec
from ..plant.systems import System, read_states

__all__ = ["DOMAIN_MARGIN", "DISCRETIZATIONS", "domain_bounds", "domain_rows", "box_rows", "check_exact_only",
           "check_system", "check_discretization", "check_time", "check_samples", "check_finite", "check_initial"]

#: Relative margin of the domain monitor: estimates up to this share of the trained range outside
#: it still count as in the domain (a transient grazing the edge is not flagged).
DOMAIN_MARGIN = 0.1
#: Discretisations of the latent ODE over one sample interval.
DISCRETIZATIONS = ("exact", "rk4")


def domain_bounds(domain: Any) -> tuple[np.ndarray, np.ndarray]:
    """``[x; z]`` lower and upper bounds of the domain monitor, widened by :data:`DOMAIN_MARGIN`."""
    lo = np.concatenate([domain.x_lo, domain.z_lo])
    hi = np.concatenate([domain.x_hi, domain.z_hi])
    margin = DOMAIN_MARGIN * np.maximum(hi - lo, 1e-9)
    return lo - margin, hi + margin


def domain_rows(system: System, size: int) -> Optional[np.ndarray]:
    """The rows of ``[x; z]`` (``size`` of them) the domain's box check tests: every one but a state the plant's
    equations do not read (:func:`~kklcasadi.plant.systems.read_states`: its estimate is not what the maps were
    trained to bound, such as the Qube's arm angle under ``y = alpha``); None where the plant reads every state."""
    read = read_states(system)
    return None if len(read) == system.nx else np.array([i for i in range(size) if i >= system.nx or i in read])


def box_rows(point: Any, bounds: tuple[np.ndarray, np.ndarray], rows: Optional[np.ndarray]) -> tuple[Any, Any, Any]:
    """``point`` (``[x; z]``: numbers (..., n) or a CasADi column) and the ``bounds`` on :func:`domain_rows`' ``rows``
    (None: all, as they are)."""
    lo, hi = bounds
    if rows is None:
        return point, lo, hi
    return (point[..., rows] if isinstance(point, np.ndarray) else point[rows.tolist()]), lo[rows], hi[rows]


def check_system(spec: ModelSpec, system: System, where: str) -> None:
    expected = spec.system
    if system.name != expected.name:
        raise ValueError(f"{where}: 'system.name': the model was trained for {expected.name!r}, "
                         f"received the system {system.name!r}. Pass the plant the model was "
                         "trained for, or load the model trained for this plant.")
    for key in ("nx", "nu", "ny"):
        if getattr(system, key) != getattr(expected, key):
            raise ValueError(f"{where}: 'system.{key}': the model expects {key} = "
                             f"{getattr(expected, key)}, the system {system.name!r} has {key} = "
                             f"{getattr(system, key)}. Pass the plant the model was trained for.")
    if expected.fingerprint is not None and system.fingerprint != expected.fingerprint:
        raise ValueError(f"{where}: 'system.fingerprint': the model was trained for a plant {expected.name!r} "
                         f"with other dynamics or another box (fingerprint {expected.fingerprint[:12]}..., the plant "
                         f"passed has {system.fingerprint[:12]}...). Pass the plant the model was trained for, "
                         "or train a model for this plant.")


def check_discretization(discretization: Optional[str], linear: bool, method: str) -> str:
    if discretization is None:
        return "exact" if linear else "rk4"
    if discretization not in DISCRETIZATIONS:
        raise ValueError(f"discretization: expected one of {list(DISCRETIZATIONS)} or None, "
                         f"received {discretization!r}.")
    if discretization == "exact" and not linear:
        raise ValueError(f"discretization: 'exact' needs linear latent dynamics; method {method!r}"
                         " has an input term that depends on z. Use 'rk4' (the default).")
    return discretization


def check_exact_only(exact_only: bool, argument: str, received: str, path: Any) -> bool:
    """Refuse the RK4 step (``argument`` ``"discretization"``) or the integrator (``"integrator"``) of the model at
    ``path`` whose latent runs only by its exact step (``exact_only``: the augmented EKF block, a discrete step with
    no continuous-time field); returns ``exact_only``."""
    if exact_only and (argument != "discretization" or received != "exact"):
        expected = "'exact' (or None)" if argument == "discretization" else "a model whose latent has a field"
        raise ValueError(f"{argument}: expected {expected} for {path}, whose latent holds the augmented EKF's block "
                         f"(a discrete step with no continuous-time field), received {received!r}. Use the exact "
                         "step (step, simulate).")
    return exact_only


def check_time(t: Any, dt: float) -> np.ndarray:
    given = np.asarray(t)
    eps = np.finfo(given.dtype).eps if np.issubdtype(given.dtype, np.floating) else np.finfo(float).eps
    t = given.astype(float)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"t: expected sample times of shape (N,), N >= 1, received shape "
                         f"{t.shape}.")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"t: expected finite sample times, received a NaN/inf at sample "
                         f"{int(np.argmin(np.isfinite(t)))}.")
    steps = np.diff(t)
    # the spacing of stored times is exact to the rounding of their dtype (float32 times: ~1e-6 s at t = 50 s)
    tolerance = max(1e-9 * dt, 1e-12 * max(1.0, abs(t[-1])), 2 * eps * max(1.0, float(np.max(np.abs(t)))))
    if steps.size and not np.all(np.abs(steps - dt) <= tolerance):
        k = int(np.argmax(np.abs(steps - dt)))
        raise ValueError(f"t: expected samples spaced by the observer's dt = {dt}, received "
                         f"t[{k + 1}] - t[{k}] = {steps[k]}. Resample the data at dt.")
    return t


def check_samples(values: Any, argument: str, n: int, dim: int) -> tuple[np.ndarray, bool]:
    """Return ``values`` as (M, N, dim) and whether it was given with a trial axis."""
    array = np.asarray(values, dtype=float)
    if array.ndim == 1 and dim == 1:
        array = array[:, None]
    if array.ndim == 2 and array.shape == (n, dim):
        return array[None], False
    if array.ndim == 3 and array.shape[1:] == (n, dim) and array.shape[0] >= 1:
        return array, True
    raise ValueError(f"{argument}: expected shape (N, {dim}) or (M, N, {dim}) with N = {n} "
                     f"samples (the length of t), received {np.shape(values)}.")


def check_finite(values: np.ndarray, argument: str, t: np.ndarray, batched: bool) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        trial, k, _ = (int(i) for i in np.argwhere(bad)[0])
        at = f"trial {trial}, sample {k}" if batched else f"sample {k}"
        raise ValueError(f"{argument}: expected finite values, received "
                         f"{values[trial, k].tolist()} at {at} (t = {t[k]:.6g}). Remove or "
                         "repair the bad samples before running the observer.")


def check_initial(z0: Any, m: int, nz: int, batched: bool) -> np.ndarray:
    """The initial latent states as columns (nz, M); 0 by default."""
    if z0 is None:
        return np.zeros((nz, m))
    array = np.asarray(z0, dtype=float)
    if array.shape == (nz,):
        array = np.repeat(array[None], m, axis=0)
    elif not (batched and array.shape == (m, nz)):
        expected = f"({nz},) or (M, {nz}) = ({m}, {nz})" if batched else f"({nz},)"
        raise ValueError(f"z0: expected shape {expected}, received {array.shape}.")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"z0: expected finite values, received {array.tolist()}.")
    return np.ascontiguousarray(array.T)
