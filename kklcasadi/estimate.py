"""One result type for every estimator, and the one-sample-at-a-time protocol they share.

Every estimator of kklcasadi (the KKL observer, the EKF, the particle filter, the MHE and the
KKL-primed MHE) returns an :class:`Estimate` from ``simulate(t, y, u)``, with the fields that apply to
it and None for the others, and gives a :class:`StepEstimator` from ``estimator()``: ``make_step(y_k,
u_k) -> xhat_k`` per sample, as a control loop (:func:`kklcasadi.estimators.nmpc.closed_loop`) or a
live system feeds it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Protocol, runtime_checkable

import numpy as np

__all__ = ["Estimate", "StepEstimator", "check_sample"]


@dataclass(frozen=True, eq=False)
class Estimate:
    """An estimator run on sampled measurements: one trajectory ``(N, .)`` or M trials ``(M, N, .)``.

    Attributes
    ----------
    t : numpy.ndarray, shape (N,)
        Sample times.
    xhat : numpy.ndarray, shape (N, nx) or (M, N, nx)
        The state estimates ``xhat_k`` (from ``y_0..y_k``, ``u_0..u_k-1``).
    var : numpy.ndarray, shape like ``xhat``, or None
        The estimate's variance per state where the estimator knows it: the EKF's diagonal of ``P``,
        the particle filter's weighted variance, the diagonal of ``cov`` where that is given (an observer
        with a covariance head); None for the other observers and the MHEs.
    z : numpy.ndarray, shape (N, nz) or (M, N, nz), or None
        The KKL observer's latent states ``z_k`` (``z_0 = 0``); None for the others.
    in_domain : numpy.ndarray of bool, shape (N,) or (M, N), or None
        The KKL observer's domain monitor per sample (:meth:`kklcasadi.KKLObserver.in_domain`): whether
        ``(xhat_k, z_k)`` lies in the trained boxes and, where the model has a decoder-input monitor,
        whether the decoder's input lies within its threshold of the fitting data; None where the model
        records neither, and for the other estimators.
    stats : object or None
        What the estimator reports about its run: the MHEs' solver statistics
        (:class:`kklcasadi.estimators.mhe.MHEStats`), the particle filter's effective sample sizes
        (:class:`kklcasadi.estimators.pf.PFStats`); None for the observer and the EKF.
    cov : numpy.ndarray, shape (N, nx, nx) or (M, N, nx, nx), or None
        The covariance of each estimate's error ``x_k - xhat_k`` where the estimator gives it: the KKL
        observer's covariance head (:attr:`kklcasadi.KKLObserver.covariance`); None otherwise.
    """

    t: np.ndarray
    xhat: np.ndarray
    var: Optional[np.ndarray] = None
    z: Optional[np.ndarray] = None
    in_domain: Optional[np.ndarray] = None
    stats: Any = None
    cov: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        if self.var is None and self.cov is not None:
            object.__setattr__(self, "var", np.diagonal(self.cov, axis1=-2, axis2=-1))


@runtime_checkable
class StepEstimator(Protocol):
    """An estimator fed one sample at a time (``obs.estimator()``, ``ekf.estimator()``, ...).

    ``make_step(y_k, u_k)`` takes the measurement ``y_k`` (ny,) and the input ``u_k`` (nu,) held from
    ``t_k`` and returns the estimate ``xhat_k`` (nx,); the first call starts the estimator, and the
    sequence is the estimator's ``simulate`` sample by sample. ``reset()`` starts it again; ``k`` counts
    the samples taken, and ``stats`` says what the last step did (a dict with ``k`` at least).
    """

    k: int

    def make_step(self, y: Any, u: Any) -> np.ndarray: ...

    def reset(self) -> None: ...

    @property
    def stats(self) -> dict: ...


def check_sample(value: Any, argument: str, dim: int, k: int, *, finite: bool = True) -> np.ndarray:
    """One sample ``(dim,)`` of a step estimator's ``y`` or ``u``, finite unless ``finite=False`` (a guarded
    estimator takes a non-finite sample and holds it back; ``k``: the sample, named in the error)."""
    array = np.asarray(value, dtype=float)
    if array.shape not in ((dim,), (dim, 1)) and not (dim == 1 and array.shape == ()):
        raise ValueError(f"{argument}: expected shape ({dim},) at sample {k}, received "
                         f"{array.shape}.")
    array = array.reshape(dim)
    if finite and not np.all(np.isfinite(array)):
        raise ValueError(f"{argument}: expected finite values at sample {k}, received "
                         f"{array.tolist()}. Skip or repair the sample; the estimator state is "
                         "unchanged.")
    return array
