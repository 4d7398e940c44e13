"""The MHE primed by a KKL observer: the learned observer runs alongside the exact-model MHE
(:class:`kklcasadi.estimators.mhe.MHE`); its estimate at ``k - n`` is the arrival prior, with a covariance
from the observer's typical error at that time (calibrated on simulated runs, :func:`kkl_error_profile`),
and its estimate at ``k`` initialises the newest node. A short horizon then suffices; a failed solve
returns the KKL estimate (counted in the stats).
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np

from ..estimate import Estimate
from ..validation import nonnegative_number
from .mhe import MHE, MHEEstimator, MHEStats

__all__ = ["KKLPrimedMHE", "kkl_error_profile"]


class KKLPrimedMHE:
    """The MHE with its arrival prior and warm start from a KKL observer.

    At sample ``k`` the prior of the window's first node ``k - n`` is the KKL estimate there,
    with covariance ``diag(error_std[k - n]^2)``, or, with ``error_std=None``, the observer's own
    covariance of that estimate (its covariance head, :attr:`KKLObserver.covariance`: sample by
    sample and trial by trial); the newest node starts at the KKL estimate at ``k``, and a failed
    solve returns the KKL estimate (counted in the stats).

    Parameters
    ----------
    observer : KKLObserver
        The learned observer (its ``simulate`` runs alongside; its system and ``dt`` are used).
    error_std : array_like, shape (N, nx) or (nx,), or None
        Typical error of the observer at each sample time (:func:`kkl_error_profile`), or one
        level for all times; None: the observer's covariance head (a model with
        ``architecture.covariance``).
    horizon : int
        Short window length (default 5).
    **mhe_options
        Keyword options of :class:`MHE` (``process_std``, ``measurement_std``, ``substeps``,
        ``noise_floor``, ``max_iter``, ``ipopt``).

    Attributes
    ----------
    observer : KKLObserver
    mhe : MHE
    error_std : numpy.ndarray
    last_stats : MHEStats or None
        Statistics of the last :meth:`__call__`.
    """

    def __init__(self, observer: Any, error_std: Any, horizon: int = 5, **mhe_options: Any) -> None:
        from ..observer.kkl import KKLObserver

        if not isinstance(observer, KKLObserver):
            raise TypeError(f"observer: expected a KKLObserver (kc.load_observer), received "
                            f"{type(observer).__name__}.")
        self.observer = observer
        self.mhe = MHE(observer.system, observer.dt, horizon, **mhe_options)
        self.last_stats: Optional[MHEStats] = None
        if error_std is None:
            if observer.covariance is None:
                raise ValueError(f"error_std: expected the observer's errors' std, or None for a model with a "
                                 f"covariance head, received None for {observer!r}, which has none. Pass "
                                 "kkl_error_profile(observer, protocol), or fit a head "
                                 "(benchmarks/covariance_heads.py).")
            self.error_std = None
            return
        std = np.asarray(error_std, dtype=float)
        if std.ndim not in (1, 2) or std.shape[-1] != observer.nx or not np.all(std > 0):
            raise ValueError(f"error_std: expected positive values of shape (N, {observer.nx}) or "
                             f"({observer.nx},), received shape {std.shape}"
                             f"{'' if std.size == 0 or np.all(std > 0) else ' with values <= 0'}.")
        self.error_std: Optional[np.ndarray] = std

    def __repr__(self) -> str:
        return (f"KKLPrimedMHE(method={self.observer.method!r}, system="
                f"{self.observer.system.name!r}, horizon={self.mhe.horizon})")

    def _std(self, n_samples: int) -> np.ndarray:
        if self.error_std.ndim == 1:
            return np.repeat(self.error_std[None], n_samples, axis=0)
        if self.error_std.shape[0] < n_samples:
            tail = np.repeat(self.error_std[-1:], n_samples - self.error_std.shape[0], axis=0)
            return np.vstack([self.error_std, tail])
        return self.error_std[:n_samples]

    def simulate(self, t: Any, y: Any, u: Any) -> Estimate:
        """Run the observer, then the MHE primed by it (shapes as :meth:`MHE.simulate`)."""
        est = self.observer.simulate(t, y, u)
        if self.error_std is None:
            return self.mhe.simulate(t, y, u, guide=est.xhat, guide_cov=est.cov)
        return self.mhe.simulate(t, y, u, guide=est.xhat, guide_std=self._std(np.size(t)))

    def estimator(self) -> MHEEstimator:
        """The primed MHE one sample at a time: the observer's step estimator guides an :class:`MHEEstimator`
        (its estimates equal :meth:`simulate`'s to the rounding of the observer's step, one sample at a time)."""
        return MHEEstimator(self.mhe, self.observer.estimator(), self.error_std)

    def __call__(self, t: Any, y: Any, u: Any) -> np.ndarray:
        """The protocol estimator; statistics in :attr:`last_stats`."""
        run = self.simulate(t, y, u)
        self.last_stats = run.stats
        return run.xhat


def kkl_error_profile(observer: Any, protocol: Any, kinds: Sequence[str] = ("zero", "constant",
                      "sinusoid", "square"), *, floor: float = 0.05) -> np.ndarray:
    """The observer's RMS error at each sample time over simulated protocol runs (calibration).

    Use a protocol with another seed than the benchmark's, so that the calibration runs are not
    the scored ones.

    Parameters
    ----------
    observer : KKLObserver
    protocol : kklcasadi.evaluation.protocol.Protocol
        Trials to calibrate on (its noise levels, horizon and seed).
    kinds : sequence of str
        Input regimes pooled.
    floor : float
        Lower bound of the returned standard deviations, as a fraction of the X0 box half-width
        (keeps the prior from being overconfident where the sample error is small by chance).

    Returns
    -------
    numpy.ndarray, shape (N, nx)
        RMS over trials of ``x - xhat`` per state and sample.
    """
    system = observer.system
    errors = []
    for kind in kinds:
        batch = protocol.trials(system, kind)
        ok = batch.ok
        xhat = observer.simulate(batch.t, batch.y[ok], batch.u[ok]).xhat
        errors.append(batch.x[ok] - xhat)
    err = np.concatenate(errors, axis=0)
    half = 0.5 * (system.x0_box[:, 1] - system.x0_box[:, 0])
    return np.maximum(np.sqrt(np.mean(err ** 2, axis=0)), nonnegative_number(floor, "floor") * half)
