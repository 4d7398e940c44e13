"""The covariance head of a ``bank`` decoder (torch-free): how far off each estimate may be, sample by sample.

A small MLP (array prefix ``covariance``) reads the decoder's own features ``f = [z_k; y_k; u_k]`` and
returns ``q``, ``nx (nx + 1) / 2`` numbers that fill a lower-triangular factor ``L``: its diagonal
``exp(q_0), ..., exp(q_{nx-1})``, then the entries below it row by row (``L_10, L_20, L_21, ...``). In
the units of the decoder's network outputs ``v`` (their scale ``d = decoder/out_std``)

    Sigma_v = D L L^T D,                       D = diag(d)
    Sigma_x = S G J Sigma_v J G S,             J = diag(dxhat_i / dv_i),  S = diag(covariance/scale)

``J`` is 1 for a state decoded as ``v_i`` and ``s_i cosh(v_i) = sqrt(s_i^2 + xhat_i^2)`` for one decoded as
``xhat_i = s_i sinh(v_i)`` (the delta method through the output map, written in the estimate the step has
already). The delta method holds while ``sigma_i = sqrt(Sigma_v,ii)`` is small; where it is not (the start of
a run, when a state decoded through ``sinh`` may be off by orders of magnitude) the image of ``v``'s interval
``v_i +- k sigma_i`` is far wider than ``J`` says: ``G`` is the gain that makes ``xhat_i +- k sqrt(Sigma_x,ii)`` as
wide as that image, ``s_i (sinh(v_i + k sigma_i) - sinh(v_i - k sigma_i)) = 2 k J_i sigma_i g_i``, so
``g_i = sinh(k sigma_i) / (k sigma_i)`` (>= 1, 1 + (k sigma_i)^2 / 6 for a small ``sigma_i``), with ``k``
:data:`INTERVAL` = 2 (the 2-sigma interval the coverage is scored on); ``g_i = 1`` for a state decoded as
``v_i``. ``S`` is the calibration: one factor per state, chosen on validation runs so that the normalised errors
have unit variance there (:func:`kklcasadi.train.covariance.calibrate`). The head is fit by the Gaussian negative
log-likelihood of the truth after the decoder's mean (:mod:`kklcasadi.train.covariance`). Angle states are not
supported (their error lives on the circle).

:func:`covariance_numpy` is the reference; :func:`covariance_expression` the same map in CasADi (what
the observer's step and its C code compute).
"""

from __future__ import annotations

from typing import Any, Mapping

import casadi as ca
import numpy as np

from ...nets import builders as casadi_nets
from ...nets.numpy_mlp import mlp_numpy
from ...nets.specs import MLPSpec
from ...validation import error

__all__ = ["COVARIANCE", "SCALE", "INTERVAL", "n_entries", "array_shapes", "factor", "covariance_numpy",
           "covariance_expression", "output_jacobian", "interval_gain"]

#: Array prefix of the head's MLP (and the card's ``architecture.covariance`` entry).
COVARIANCE = "covariance"
#: Array of the per-state calibration factors (nx,).
SCALE = "covariance/scale"
#: The half-width, in standard deviations of ``v``, of the interval whose image through ``s sinh(v)`` sets the
#: variance of a state decoded that way (:func:`interval_gain`).
INTERVAL = 2.0


def n_entries(nx: int) -> int:
    """The head's outputs for ``nx`` states: ``nx (nx + 1) / 2`` (the factor's diagonal, then below it)."""
    return nx * (nx + 1) // 2


def array_shapes(spec: MLPSpec, nx: int) -> dict[str, tuple[int, ...]]:
    """The head's arrays: its MLP's (prefix :data:`COVARIANCE`) and :data:`SCALE` (nx,)."""
    if spec.n_out != n_entries(nx):
        raise error("architecture.covariance.sizes", f"a last size of nx (nx + 1) / 2 = {n_entries(nx)} (the "
                    "covariance factor's entries)", list(spec.sizes))
    return {**spec.array_shapes(COVARIANCE), SCALE: (nx,)}


def _lower(nx: int) -> list[tuple[int, int]]:
    """The strictly lower entries of an nx x nx matrix, row by row."""
    return [(i, j) for i in range(nx) for j in range(i)]


def factor(q: np.ndarray, nx: int) -> np.ndarray:
    """The lower-triangular factor ``L`` (..., nx, nx) of the head's outputs ``q`` (..., nx (nx + 1) / 2)."""
    L = np.zeros((*q.shape[:-1], nx, nx))
    idx = np.arange(nx)
    L[..., idx, idx] = np.exp(q[..., :nx])
    for k, (i, j) in enumerate(_lower(nx)):
        L[..., i, j] = q[..., nx + k]
    return L


def output_jacobian(xhat: Any, asinh_scale: np.ndarray, lib: Any = np) -> Any:
    """``dxhat_i / dv_i`` per state (..., nx): 1, or ``s_i cosh(v_i) = sqrt(s_i^2 + xhat_i^2)`` where
    ``asinh_scale_i = s_i > 0`` (``xhat_i = s_i sinh(v_i)``)."""
    scale = np.asarray(asinh_scale, dtype=float)
    if lib is np:
        return np.where(scale > 0, np.sqrt(scale ** 2 + np.asarray(xhat)[..., :scale.size] ** 2), 1.0)
    return ca.vertcat(*[ca.sqrt(float(s) ** 2 + xhat[i] ** 2) if s > 0 else ca.DM(1.0) for i, s in enumerate(scale)])


def interval_gain(sigma_v: Any, asinh_scale: np.ndarray, lib: Any = np) -> Any:
    """``g_i = sinh(k sigma_i) / (k sigma_i)`` (``k`` :data:`INTERVAL`) per state (..., nx) where ``asinh_scale_i >
    0``, 1 elsewhere: the gain on the delta method's standard deviation that makes ``+- k`` of them as wide as the
    image of ``v_i +- k sigma_i`` through ``s_i sinh(v)`` (module docstring); ``sigma_v`` (..., nx) the standard
    deviations of the decoder's outputs ``v``."""
    scale = np.asarray(asinh_scale, dtype=float)
    if lib is np:
        ks = INTERVAL * np.asarray(sigma_v, dtype=float)
        return np.where(scale > 0, np.sinh(ks) / ks, 1.0)
    return ca.vertcat(*[ca.sinh(INTERVAL * sigma_v[i]) / (INTERVAL * sigma_v[i]) if s > 0 else ca.DM(1.0)
                        for i, s in enumerate(scale)])


def covariance_numpy(spec: MLPSpec, arrays: Mapping[str, Any], features: np.ndarray, xhat: np.ndarray,
                     out_std: np.ndarray, asinh_scale: np.ndarray) -> np.ndarray:
    """The covariance of the estimates (numpy, float64).

    Parameters
    ----------
    spec : MLPSpec
        The head's network (``architecture.covariance``).
    arrays : Mapping[str, array_like]
        The head's arrays (:func:`array_shapes`).
    features : numpy.ndarray, shape (..., d)
        The decoder's features ``[z; y; u]``.
    xhat : numpy.ndarray, shape (..., nx)
        The estimates there.
    out_std : numpy.ndarray, shape (nx,)
        ``decoder/out_std``.
    asinh_scale : numpy.ndarray, shape (nx,)
        ``decoder/asinh_scale``.

    Returns
    -------
    numpy.ndarray, shape (..., nx, nx)
    """
    nx = out_std.size
    L = factor(mlp_numpy(spec, arrays, COVARIANCE, features), nx)
    gain = interval_gain(out_std * np.sqrt(np.sum(L ** 2, axis=-1)), asinh_scale)
    d = np.asarray(arrays[SCALE], dtype=float) * output_jacobian(xhat, asinh_scale) * gain * out_std
    DL = d[..., :, None] * L
    return DL @ np.swapaxes(DL, -1, -2)


def covariance_expression(spec: MLPSpec, arrays: Mapping[str, Any], features: ca.MX, xhat: ca.MX,
                          out_std: np.ndarray, asinh_scale: np.ndarray, name: str = "covariance_mlp") -> ca.MX:
    """:func:`covariance_numpy` at CasADi symbols: ``features`` (d, 1), ``xhat`` (nx, 1) -> ``P`` (nx, nx)."""
    nx = out_std.size
    q = casadi_nets.mlp_function(spec, arrays, COVARIANCE, name)(features)
    lower = {(i, j): nx + k for k, (i, j) in enumerate(_lower(nx))}
    L = [[ca.exp(q[i]) if j == i else q[lower[i, j]] for j in range(i + 1)] for i in range(nx)]
    d = ca.DM(np.asarray(arrays[SCALE], dtype=float) * out_std) * output_jacobian(xhat, asinh_scale, ca)
    if np.any(np.asarray(asinh_scale) > 0):         # the states decoded as s sinh(v): the interval's gain
        sigma = ca.vertcat(*[float(out_std[i]) * ca.sqrt(sum(entry ** 2 for entry in L[i])) for i in range(nx)])
        d = d * interval_gain(sigma, asinh_scale, ca)
    rows = [ca.horzcat(*[d[i] * L[i][j] if j <= i else ca.MX(0) for j in range(nx)]) for i in range(nx)]
    DL = ca.vertcat(*rows)
    return ca.mtimes(DL, DL.T)
