"""The covariance head of a ``bank`` decoder (torch): fit by the Gaussian likelihood of the truth, then calibrated.

* :func:`fit_covariance` -- after the decoder's mean is fit, a small MLP on the decoder's features learns the
  factor of the errors' covariance (:mod:`kklcasadi.model.variants.covariance`) by minimising the Gaussian
  negative log-likelihood of the true states' errors, ``0.5 |L^-1 r|^2 + sum log L_ii`` with
  ``r = (v_true - v) / d`` the decoder's error in the units of its outputs.
* :func:`calibrate` -- one factor per state, on validation runs the head was not fit on, so that each
  state's normalised error has unit variance there (the head fit on the decoder's own fitting runs sees
  errors a little smaller than on new ones).
* :func:`calibrate_inflation` -- the constants of the head's inflation by the measurement residual
  (:mod:`kklcasadi.model.variants.inflation`): ``c`` the residual statistic's mean on in-distribution
  validation runs, and the time constant, among candidates, that keeps the 2-sigma coverage nearest its Gaussian
  value on those runs and on validation runs at a higher noise level.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import torch

from .. import consistency as cs
from ..model.variants.covariance import COVARIANCE, SCALE, covariance_numpy, n_entries
from ..model.variants.inflation import Inflation, inflation_numpy, residual_statistic
from ..nets.specs import MLPSpec
from ..plant.systems import System
from ..validation import Text, error
from .config import LoopConfig
from .decoder import fold_whitening, whitening
from .loop import ArrayDataset, FitResult, fit, torch_dtype
from .nets import MLP

__all__ = ["CovarianceConfig", "CovarianceFit", "fit_covariance", "calibrate", "gaussian_nll", "output_errors",
           "ValidationRuns", "calibrate_inflation"]

Tensor = torch.Tensor


@dataclass(frozen=True)
class CovarianceConfig:
    """The covariance head's network and its fit.

    Attributes
    ----------
    hidden : tuple of int
        Hidden widths of the head's MLP (small: it runs at every step beside the decoder).
    activation : str
    loop : LoopConfig
    dtype : {"float32", "float64"}
        Training precision; the arrays are float64 either way.
    """

    hidden: tuple[int, ...] = (16,)
    activation: str = "tanh"
    loop: LoopConfig = field(default_factory=lambda: LoopConfig(epochs=20, batch_size=512, lr=3e-3,
                                                                  schedule="cosine", val_fraction=0.05))
    dtype: str = "float32"

    def __post_init__(self) -> None:
        if not self.hidden or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in self.hidden):
            raise error("hidden", "a non-empty tuple of positive widths", self.hidden)
        torch_dtype(self.dtype)


@dataclass(frozen=True, eq=False)
class CovarianceFit:
    """Result of :func:`fit_covariance`: the head's arrays (``covariance/*``, scale 1), its card entry and the fit."""

    arrays: dict
    arch: dict
    fit: FitResult


def _factor(q: Tensor, nx: int) -> Tensor:
    """The lower-triangular factor (..., nx, nx) of the head's outputs (the layout of
    :func:`kklcasadi.model.variants.covariance.factor`: the diagonal's logarithms, then below it row by row)."""
    L = torch.diag_embed(torch.exp(q[..., :nx]))
    lower = [(i, j) for i in range(nx) for j in range(i)]
    if lower:
        off = torch.zeros_like(L)
        off[..., [i for i, _ in lower], [j for _, j in lower]] = q[..., nx:]
        L = L + off
    return L


def gaussian_nll(q: Tensor, r: Tensor) -> Tensor:
    """Mean negative log-likelihood (less ``nx/2 log 2 pi``) of errors ``r`` (B, nx) under ``N(0, L L^T)``,
    ``L`` from the head's outputs ``q`` (B, nx (nx + 1) / 2)."""
    nx = r.shape[-1]
    L = _factor(q, nx)
    white = torch.linalg.solve_triangular(L, r[..., None], upper=False)[..., 0]
    return (0.5 * (white ** 2).sum(-1) + q[..., :nx].sum(-1)).mean()


def output_errors(x: np.ndarray, xhat: np.ndarray, out_std: np.ndarray, asinh_scale: np.ndarray) -> np.ndarray:
    """The estimates' errors in the units of the decoder's outputs, ``(v(x) - v(xhat)) / out_std`` (..., nx), with
    ``v(x) = asinh(x / s)`` for a state with an ``asinh`` scale ``s > 0`` and ``x`` otherwise (what
    :func:`fit_covariance` fits; the estimate's ``v`` is recovered from ``xhat`` exactly up to rounding)."""
    s = np.asarray(asinh_scale, dtype=float)
    safe = np.where(s > 0, s, 1.0)

    def v(a: np.ndarray) -> np.ndarray:
        return np.where(s > 0, np.arcsinh(np.asarray(a, dtype=float) / safe), a)

    return (v(x) - v(xhat)) / np.asarray(out_std, dtype=float)


def fit_covariance(features: np.ndarray, error_v: np.ndarray, config: CovarianceConfig, *, seed: int = 0,
                   progress: bool = False) -> CovarianceFit:
    """Fit the covariance head on the decoder's features and its errors.

    Parameters
    ----------
    features : numpy.ndarray, shape (S, d)
        The decoder's features ``[z; y; u]`` of the samples.
    error_v : numpy.ndarray, shape (S, nx)
        The decoder's errors there in the units of its outputs, ``(v_true - v) / decoder/out_std``.
    config : CovarianceConfig
    seed : int
    progress : bool

    Returns
    -------
    CovarianceFit
        The head's arrays with :data:`kklcasadi.model.variants.covariance.SCALE` 1 (calibrate it with
        :func:`calibrate`).
    """
    features = np.asarray(features, dtype=float)
    r = np.asarray(error_v, dtype=float)
    if features.ndim != 2 or r.ndim != 2 or len(features) != len(r) or not np.all(np.isfinite(r)):
        raise error("error_v", f"finite errors of shape (S = {len(features)}, nx)", Text(f"shape {r.shape}"))
    nx = r.shape[1]
    sizes = (features.shape[1], *config.hidden, n_entries(nx))
    dtype = torch_dtype(config.dtype)
    torch.manual_seed(seed)
    mlp = MLP(sizes, config.activation)
    mean, white = whitening(features)
    start = np.zeros(sizes[-1])
    start[:nx] = np.log(np.std(r, axis=0) + 1e-12)                 # the errors' scale, uncorrelated, at the start
    mlp.set_normalisation(np.zeros(sizes[0]), np.ones(sizes[0]), start, np.ones(sizes[-1]))
    with torch.no_grad():                          # start at that constant covariance, whatever the features
        mlp.layers[-1].weight.zero_()
        mlp.layers[-1].bias.zero_()
    mlp = mlp.to(dtype)
    data = ArrayDataset({"f": (features - mean) @ white.T, "r": r}, dtype=dtype)

    def loss_fn(batch: Mapping[str, Tensor], epoch: int) -> tuple[Tensor, dict[str, float]]:
        loss = gaussian_nll(mlp(batch["f"]), batch["r"])
        return loss, {"nll": loss.item()}

    result = fit(list(mlp.parameters()), loss_fn, data, config.loop, name="covariance head", seed=seed,
                 progress=progress)
    arrays = fold_whitening(mlp.to(torch.float64).to_arrays(COVARIANCE), mean, white, prefix=COVARIANCE)
    arrays[SCALE] = np.ones(nx)
    return CovarianceFit(arrays, mlp.spec.to_card(), result)


def calibrate(arrays: Mapping[str, np.ndarray], arch: Mapping[str, object], features: np.ndarray, xhat: np.ndarray,
              errors: np.ndarray, out_std: np.ndarray, asinh_scale: np.ndarray) -> np.ndarray:
    """The per-state calibration factors ``s_i = sqrt(mean(e_i^2 / P_ii))`` on validation samples.

    Parameters
    ----------
    arrays, arch
        The head's arrays (its :data:`SCALE` is ignored) and card entry.
    features : numpy.ndarray, shape (S, d)
    xhat : numpy.ndarray, shape (S, nx)
        The estimates at the samples.
    errors : numpy.ndarray, shape (S, nx)
        The estimates' errors ``x - xhat`` there.
    out_std, asinh_scale : numpy.ndarray, shape (nx,)
        ``decoder/out_std`` and ``decoder/asinh_scale``.

    Returns
    -------
    numpy.ndarray, shape (nx,)
    """
    nx = out_std.size
    unit = {**arrays, SCALE: np.ones(nx)}
    spec = MLPSpec.from_card(arch, "architecture", COVARIANCE)
    P = covariance_numpy(spec, unit, features, xhat, out_std, asinh_scale)
    ratio = np.asarray(errors, dtype=float) ** 2 / np.diagonal(P, axis1=-2, axis2=-1)
    if not np.all(np.isfinite(ratio)):
        raise error("errors", "finite errors and variances at every validation sample",
                    Text(f"{int(np.sum(~np.isfinite(ratio)))} non-finite"))
    return np.sqrt(ratio.mean(axis=0))


@dataclass(frozen=True, eq=False)
class ValidationRuns:
    """Runs of an observer with a covariance head: times ``t`` (N,), true states ``x`` (M, N, nx), measurements ``y``
    (M, N, ny), estimates ``xhat`` (M, N, nx) and the head's covariances ``P`` (M, N, nx, nx), not inflated."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    xhat: np.ndarray
    P: np.ndarray


def calibrate_inflation(system: System, dt: float, R: Sequence[float], nominal: ValidationRuns,
                        noisy: Sequence[ValidationRuns], time_constants: Sequence[float] = (1.0, 2.5, 5.0)
                        ) -> tuple[Inflation, list[dict]]:
    """The constants of the covariance head's inflation (:mod:`kklcasadi.model.variants.inflation`), on
    validation runs.

    ``c`` is the mean of the residual statistic ``r`` over the samples of ``nominal`` (runs at the head's own noise
    level, in distribution), so that the inflation's state averages 1 there. The time constant is the candidate
    whose worst 2-sigma coverage, over the states and over ``nominal`` and each of ``noisy`` (runs at other noise
    levels), is nearest :data:`kklcasadi.consistency.GAUSSIAN_COVERAGE` (ties: the first candidate).

    Parameters
    ----------
    system : System
    dt : float
        The sample period.
    R : sequence of float
        The measurement noise variance per output of the head's fitting runs.
    nominal : ValidationRuns
    noisy : sequence of ValidationRuns
    time_constants : sequence of float
        The candidates, in seconds.

    Returns
    -------
    Inflation
    list of dict
        Per candidate: ``time_constant``, ``worst`` (its worst distance, in coverage) and, per run set (``nominal``,
        then ``noisy[0]``, ...), the mean inflation and the 2-sigma coverage per state.
    """
    R = [float(v) for v in R]
    flat = nominal.xhat.reshape(-1, system.nx).T                                  # (nx, samples)
    hx = np.asarray(system.h.map(flat.shape[1])(flat)).T
    H = np.asarray(system.h_jac.map(flat.shape[1])(flat)).reshape(system.ny, -1, system.nx).transpose(1, 0, 2)
    r = residual_statistic(nominal.y.reshape(-1, system.ny), hx, H, nominal.P.reshape(-1, system.nx, system.nx), R)
    c = float(np.mean(r))
    target = cs.GAUSSIAN_COVERAGE[cs.SIGMA_LEVELS.index(2.0)]
    table = []
    for tau in time_constants:
        inflation = Inflation(tuple(R), c, float(tau))
        row: dict = {"time_constant": float(tau), "sets": []}
        worst = 0.0
        for runs in (nominal, *noisy):
            lam = inflation_numpy(inflation, system, dt, runs.y, runs.xhat, runs.P)
            score = cs.consistency(runs.x, runs.xhat, lam[..., None, None] * runs.P, t=runs.t)
            cover = list(score.coverage[cs.SIGMA_LEVELS.index(2.0)])
            worst = max(worst, max(abs(v - target) for v in cover))
            row["sets"].append({"mean_inflation": float(np.mean(lam)), "coverage_2sigma": cover,
                                "nees": score.nees})
        row["worst"] = worst
        table.append(row)
    best = min(table, key=lambda row: row["worst"])
    return Inflation(tuple(R), c, best["time_constant"]), table
