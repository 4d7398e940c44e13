"""Whether an estimator's covariance is consistent with its errors: NEES, coverage, likelihood of the truth.

Every estimator that reports a covariance with its estimate (the EKF's ``P``, the particle filter's
weighted spread, a learned observer's covariance head) is scored the same way, on the trials its
SMAPE is scored on (docs/protocol.md, "Consistency"):

* the normalised estimation error squared of each sample, ``NEES_k = e_k^T P_k^-1 e_k`` with
  ``e_k = x_k - xhat_k``: chi-square with ``nx`` degrees of freedom where the estimate is Gaussian and
  ``P_k`` its true covariance, so its mean is ``nx``;
* Bar-Shalom's test of it: over ``M`` trials the average NEES of one sample time lies in the 95 %
  band of ``chi2(M nx) / M`` (:func:`nees_band`), and so does the mean over all samples;
* the share of true states inside the 1-sigma and 2-sigma intervals ``xhat_i +- k sqrt(P_ii)``, per
  state (68.3 % and 95.4 % for a Gaussian error of that variance);
* the mean log-likelihood of the truth under ``N(xhat_k, P_k)``, which rewards a covariance that is
  both calibrated and tight.

A covariance is given either full, ``(..., nx, nx)``, or as its diagonal, ``(..., nx)`` (the
variances alone: NEES and likelihood then ignore correlations). Angle states (``angles=``) have
their errors wrapped as in :mod:`kklcasadi.metrics`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.stats

from .metrics import wrap_angle
from .validation import Text, error, index_tuple

__all__ = ["nees", "coverage", "log_likelihood", "nees_band", "Consistency", "consistency", "full_covariance",
           "SIGMA_LEVELS", "GAUSSIAN_COVERAGE"]

#: The interval half-widths, in standard deviations, whose coverage :func:`consistency` reports.
SIGMA_LEVELS = (1.0, 2.0)
#: The coverage of ``+- k sigma`` for a Gaussian error, per level of :data:`SIGMA_LEVELS`.
GAUSSIAN_COVERAGE = tuple(float(scipy.stats.chi2.cdf(k ** 2, 1)) for k in SIGMA_LEVELS)


def _errors(x_true: object, xhat: object, angles: object) -> np.ndarray:
    a = np.asarray(x_true, dtype=float)
    b = np.asarray(xhat, dtype=float)
    if a.shape != b.shape or a.ndim < 1:
        raise error("xhat", f"the shape of x_true {a.shape}", Text(f"shape {b.shape}"))
    e = a - b
    index = list(index_tuple(angles, "angles", a.shape[-1]))
    if index:
        e[..., index] = wrap_angle(e[..., index])
    return e


def full_covariance(cov: object, shape: tuple[int, ...]) -> np.ndarray:
    """``cov`` as full matrices ``(..., nx, nx)`` for estimates of ``shape`` ``(..., nx)``.

    Parameters
    ----------
    cov : array_like, shape (..., nx, nx) or (..., nx)
        Covariances, or their diagonals (variances).
    shape : tuple of int
        The estimates' shape ``(..., nx)``.

    Raises
    ------
    ValueError
        A shape that is neither, a non-finite entry, or a covariance that is not positive definite
        (a variance <= 0).
    """
    p = np.asarray(cov, dtype=float)
    nx = shape[-1]
    if p.shape == tuple(shape):
        if not (np.all(np.isfinite(p)) and np.all(p > 0)):
            raise error("cov", "finite variances > 0", Text(f"min {np.nanmin(p):.3g}, non-finite "
                                                           f"{int(np.sum(~np.isfinite(p)))}"))
        out = np.zeros((*shape, nx))
        idx = np.arange(nx)
        out[..., idx, idx] = p
        return out
    if p.shape != (*shape, nx):
        raise error("cov", f"covariances of shape {(*shape, nx)} or variances of shape {tuple(shape)}",
                    Text(f"shape {p.shape}"))
    if not np.all(np.isfinite(p)):
        raise error("cov", "finite covariances", Text(f"{int(np.sum(~np.isfinite(p)))} non-finite entries"))
    return p


def _cholesky(p: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.cholesky(0.5 * (p + np.swapaxes(p, -1, -2)))
    except np.linalg.LinAlgError as exc:
        raise error("cov", "positive definite covariances", Text("one that is not")) from exc


def _whitened(x_true: object, xhat: object, cov: object, angles: object) -> tuple[np.ndarray, np.ndarray]:
    """``L^-1 e`` (..., nx) and ``log det P`` (...) with ``P = L L^T``."""
    e = _errors(x_true, xhat, angles)
    chol = _cholesky(full_covariance(cov, e.shape))
    white = np.linalg.solve(chol, e[..., None])[..., 0]
    return white, 2.0 * np.sum(np.log(np.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)


def nees(x_true: object, xhat: object, cov: object, *, angles: object = ()) -> np.ndarray:
    """Normalised estimation error squared of each sample, ``e^T P^-1 e``.

    Parameters
    ----------
    x_true, xhat : array_like, shape (..., nx)
    cov : array_like, shape (..., nx, nx) or (..., nx)
        The estimates' covariances, or their variances.
    angles : sequence of int
        Angle states, whose error is wrapped to (-pi, pi].

    Returns
    -------
    numpy.ndarray, shape (...)
    """
    white, _ = _whitened(x_true, xhat, cov, angles)
    return np.sum(white ** 2, axis=-1)


def log_likelihood(x_true: object, xhat: object, cov: object, *, angles: object = ()) -> np.ndarray:
    """Log-density of the truth under ``N(xhat, P)`` per sample (arguments as :func:`nees`).

    ``-0.5 (e^T P^-1 e + log det P + nx log 2 pi)``

    Returns
    -------
    numpy.ndarray, shape (...)
    """
    white, logdet = _whitened(x_true, xhat, cov, angles)
    nx = white.shape[-1]
    return -0.5 * (np.sum(white ** 2, axis=-1) + logdet + nx * np.log(2.0 * np.pi))


def coverage(x_true: object, xhat: object, var: object, k: float, *, angles: object = ()) -> np.ndarray:
    """Share of samples whose true state lies within ``k`` standard deviations, per state.

    Parameters
    ----------
    x_true, xhat : array_like, shape (..., nx)
    var : array_like, shape (..., nx) or (..., nx, nx)
        Variances, or covariances (their diagonals are read).
    k : float
        Half-width of the interval in standard deviations (> 0).
    angles : sequence of int

    Returns
    -------
    numpy.ndarray, shape (nx,)
        ``mean(|e_i| <= k sqrt(var_i))`` over all samples.
    """
    if not (np.isfinite(k) and k > 0):
        raise error("k", "a half-width > 0 in standard deviations", k)
    e = _errors(x_true, xhat, angles)
    p = np.asarray(var, dtype=float)
    if p.shape == (*e.shape, e.shape[-1]):
        p = np.diagonal(p, axis1=-2, axis2=-1)
    p = full_covariance(p, e.shape)
    p = np.diagonal(p, axis1=-2, axis2=-1)
    return np.mean(np.abs(e) <= k * np.sqrt(p), axis=tuple(range(e.ndim - 1)))


def nees_band(n: int, nx: int, level: float = 0.95) -> tuple[float, float]:
    """The two-sided ``level`` band of the mean of ``n`` independent ``chi2(nx)`` values.

    Bar-Shalom's test of a filter's consistency: over ``n`` Monte Carlo trials the average NEES of one
    sample time lies in ``[chi2.ppf((1 - level) / 2, n nx), chi2.ppf((1 + level) / 2, n nx)] / n``.

    Parameters
    ----------
    n : int
        Values averaged (trials), >= 1.
    nx : int
        Degrees of freedom of each (the state's size), >= 1.
    level : float
        In (0, 1).
    """
    for name, value in (("n", n), ("nx", nx)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise error(name, "a positive integer", value)
    if not 0 < level < 1:
        raise error("level", "a probability in (0, 1)", level)
    dof = n * nx
    lo, hi = scipy.stats.chi2.ppf([(1 - level) / 2, (1 + level) / 2], dof)
    return float(lo / n), float(hi / n)


@dataclass(frozen=True)
class Consistency:
    """How well an estimator's covariance describes its errors over ``M`` trials (see the module).

    Attributes
    ----------
    nees : float
        Mean NEES over every scored sample of every trial (``nx`` for a consistent estimator).
    nees_band : tuple of float
        The 95 % band of the average NEES of one sample time over the ``trials`` (:func:`nees_band`).
    in_band : float
        Share of the sample times whose average NEES over the trials lies in ``nees_band``.
    coverage : tuple of tuple of float
        Per level of :data:`SIGMA_LEVELS`, the share of samples inside ``+- k sigma`` per state.
    log_likelihood : float
        Mean log-density of the truth per sample.
    trials, samples, nx : int
        Trials, scored sample times per trial, and the state's size.
    """

    nees: float
    nees_band: tuple[float, float]
    in_band: float
    coverage: tuple[tuple[float, ...], ...]
    log_likelihood: float
    trials: int
    samples: int
    nx: int

    @property
    def nees_in_band(self) -> bool:
        """Whether the mean NEES lies in :attr:`nees_band`."""
        return self.nees_band[0] <= self.nees <= self.nees_band[1]

    def to_json(self) -> dict:
        """A JSON-able record (plain floats and lists)."""
        return {"nees": self.nees, "nees_band": list(self.nees_band), "in_band": self.in_band,
                "coverage": {f"{k:g}sigma": list(c) for k, c in zip(SIGMA_LEVELS, self.coverage)},
                "log_likelihood": self.log_likelihood, "trials": self.trials, "samples": self.samples, "nx": self.nx}


def consistency(x_true: object, xhat: object, cov: object, *, t: object = None, t_settle: float = 0.0,
                angles: object = ()) -> Consistency:
    """Score the covariances ``cov`` of estimates ``xhat`` of ``M`` trials against the truth.

    Parameters
    ----------
    x_true, xhat : array_like, shape (M, N, nx)
    cov : array_like, shape (M, N, nx, nx) or (M, N, nx)
        Covariances of the estimates, or their variances.
    t : array_like, shape (N,), optional
        Sample times; with ``t_settle`` > 0 only the samples at ``t >= t_settle`` are scored.
    t_settle : float
        See ``t``; 0 (default) scores the whole horizon, as the SMAPE does.
    angles : sequence of int
        Angle states.

    Returns
    -------
    Consistency
    """
    x = np.asarray(x_true, dtype=float)
    if x.ndim != 3:
        raise error("x_true", "trials of shape (M, N, nx)", Text(f"shape {x.shape}"))
    m, n, nx = x.shape
    keep = np.ones(n, dtype=bool)
    if t is not None:
        times = np.asarray(t, dtype=float)
        if times.shape != (n,):
            raise error("t", f"shape (N,) = ({n},)", Text(f"shape {times.shape}"))
        keep = times >= t_settle
        if not keep.any():
            raise error("t_settle", f"a time at or before the last sample {times[-1]}", t_settle)
    values = nees(x, xhat, cov, angles=angles)[:, keep]
    lo, hi = nees_band(m, nx)
    per_time = values.mean(axis=0)
    xh = np.asarray(xhat, dtype=float)[:, keep]
    p = np.asarray(cov, dtype=float)[:, keep]
    cover = tuple(tuple(float(c) for c in coverage(x[:, keep], xh, p, k, angles=angles)) for k in SIGMA_LEVELS)
    return Consistency(float(values.mean()), (lo, hi), float(np.mean((per_time >= lo) & (per_time <= hi))), cover,
                       float(np.mean(log_likelihood(x[:, keep], xh, p, angles=angles))), m, int(keep.sum()), nx)
