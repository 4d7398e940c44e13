"""Accuracy metrics of docs/protocol.md: SMAPE (the table's number), RMSE, RMSE after a settle time.

States that are angles (``System.angle_states``) are compared modulo ``2 pi`` when passed as
``angles=``: their error is :func:`wrap_angle` of the difference. Without ``angles`` every metric
computes exactly what it always did.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .validation import index_tuple

__all__ = ["smape", "rmse", "rmse_after", "wrap_angle", "Summary", "summarize"]


def wrap_angle(a: object) -> np.ndarray | float:
    """Angles mapped to ``(-pi, pi]``: ``pi - ((pi - a) mod 2 pi)``.

    Parameters
    ----------
    a : array_like, any shape
        Angles in radians.

    Returns
    -------
    float or numpy.ndarray, the shape of ``a``
        ``pi`` stays ``pi`` and ``-pi`` becomes ``pi``.
    """
    with np.errstate(invalid="ignore"):                       # NaN and inf give NaN
        out = np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2.0 * np.pi)
    return float(out) if out.ndim == 0 else out


def _wrapped(a: np.ndarray, b: np.ndarray, angles: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(a, b, a - b)`` with the components ``angles`` of all three wrapped to (-pi, pi]."""
    index = list(angles)
    a, b = a.copy(), b.copy()
    difference = a - b
    difference[..., index] = wrap_angle(difference[..., index])
    a[..., index] = wrap_angle(a[..., index])
    b[..., index] = wrap_angle(b[..., index])
    return a, b, difference


def _pair(x_true: object, xhat: object) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(x_true, dtype=float)
    b = np.asarray(xhat, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"xhat: expected the same shape as x_true {a.shape}, received shape {b.shape}.")
    if a.ndim < 2:
        raise ValueError(f"x_true, xhat: expected trajectories of shape (N, nx) or (M, N, nx), "
                         f"received shape {a.shape}.")
    return a, b


def smape(x_true: object, xhat: object, *, per_state: bool = False, angles: object = ()) -> np.ndarray | float:
    """Symmetric mean absolute percentage error per trial, in percent (docs/protocol.md).

    ``100 / (N nx) * sum_k sum_i 2 |x_ik - xhat_ik| / (|x_ik| + |xhat_ik| + 1e-8)``

    Parameters
    ----------
    x_true, xhat : array_like, shape (N, nx) or (M, N, nx)
    per_state : bool
        Average over time only, giving one SMAPE per state component (their mean is the
        protocol's number): shows which state dominates it.
    angles : sequence of int
        State components that are angles: their numerator is the wrapped difference
        ``|wrap_angle(x - xhat)|`` and their denominator uses ``wrap_angle(x)`` and
        ``wrap_angle(xhat)``, so the term does not depend on the branch either is written in.

    Returns
    -------
    float or numpy.ndarray, shape (M,); with ``per_state``: shape (nx,) or (M, nx)
        NaN for a trial whose estimate is not finite.
    """
    a, b = _pair(x_true, xhat)
    angles = index_tuple(angles, "angles", a.shape[-1])
    if angles:
        a, b, difference = _wrapped(a, b, angles)
    else:
        difference = a - b
    terms = 2.0 * np.abs(difference) / (np.abs(a) + np.abs(b) + 1e-8)
    if per_state:
        return 100.0 * terms.mean(axis=-2)
    out = 100.0 * terms.mean(axis=(-2, -1))
    return float(out) if out.ndim == 0 else out


def rmse(x_true: object, xhat: object, *, angles: object = ()) -> np.ndarray | float:
    """Root-mean-square error per trial over all samples and states; shapes as :func:`smape`.

    ``angles`` (sequence of int): state components whose error is ``wrap_angle(x - xhat)``.
    """
    a, b = _pair(x_true, xhat)
    angles = index_tuple(angles, "angles", a.shape[-1])
    difference = _wrapped(a, b, angles)[2] if angles else a - b
    out = np.sqrt(np.mean(difference ** 2, axis=(-2, -1)))
    return float(out) if out.ndim == 0 else out


def rmse_after(t: object, x_true: object, xhat: object, t_settle: float = 5.0, *,
               angles: object = ()) -> np.ndarray | float:
    """RMSE over the samples with ``t >= t_settle`` (docs/protocol.md reports ``t_settle = 5`` s).

    Parameters
    ----------
    t : array_like, shape (N,)
    x_true, xhat : array_like, shape (N, nx) or (M, N, nx)
    angles : sequence of int
        State components compared modulo ``2 pi`` (see :func:`rmse`).
    """
    a, b = _pair(x_true, xhat)
    t = np.asarray(t, dtype=float)
    if t.shape != (a.shape[-2],):
        raise ValueError(f"t: expected shape (N,) = ({a.shape[-2]},), received shape {t.shape}.")
    keep = t >= t_settle
    if not keep.any():
        raise ValueError(f"t_settle: expected a time at or before the last sample t = {t[-1]}, received {t_settle!r}.")
    return rmse(a[..., keep, :], b[..., keep, :], angles=angles)


@dataclass(frozen=True)
class Summary:
    """Mean, median and interquartile range of per-trial values (docs/protocol.md reporting)."""

    mean: float
    median: float
    q25: float
    q75: float
    n: int
    n_failed: int

    @property
    def iqr(self) -> float:
        return self.q75 - self.q25

    def __str__(self) -> str:
        failed = f", {self.n_failed} failed" if self.n_failed else ""
        return f"{self.mean:.2f} (median {self.median:.2f}, IQR {self.q25:.2f}-{self.q75:.2f}, n={self.n}{failed})"


def summarize(values: object) -> Summary:
    """Summarise per-trial values; non-finite trials are counted as failed and excluded."""
    v = np.asarray(values, dtype=float).ravel()
    ok = np.isfinite(v)
    if not ok.any():
        raise ValueError(f"values: expected at least one finite value to summarise, "
                         f"received {v.size} values, none finite.")
    q25, med, q75 = np.percentile(v[ok], [25, 50, 75])
    return Summary(float(v[ok].mean()), float(med), float(q25), float(q75), int(ok.sum()), int((~ok).sum()))
