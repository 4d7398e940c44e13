"""The one numpy evaluation of an MLP of a model file (float64), the reference beside its CasADi twin
(:func:`kklcasadi.nets.builders.mlp_function`) and its torch network (:class:`kklcasadi.train.nets.MLP`)."""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from .specs import MLPSpec

__all__ = ["mlp_numpy"]

_ACTIVATIONS = {"tanh": np.tanh, "relu": lambda a: np.maximum(a, 0.0),
                "softplus": lambda a: np.maximum(a, 0.0) + np.log1p(np.exp(-np.abs(a))), "identity": lambda a: a}


def mlp_numpy(spec: MLPSpec, arrays: Mapping[str, Any], prefix: str, v: np.ndarray) -> np.ndarray:
    """The MLP ``prefix/*`` of ``arrays`` at ``v``, normalisation folded in as the card stores it.

    Parameters
    ----------
    spec : MLPSpec
    arrays : Mapping[str, array_like]
        ``prefix/in_mean``, ``in_std``, ``W0``, ``b0``, ..., ``out_std``, ``out_mean`` (and ``Wskip``
        with the skip path).
    prefix : str
    v : numpy.ndarray, shape (..., n_in)

    Returns
    -------
    numpy.ndarray, shape (..., n_out)
    """
    f = _ACTIVATIONS[spec.activation]
    v = (v - np.asarray(arrays[f"{prefix}/in_mean"])) / np.asarray(arrays[f"{prefix}/in_std"])
    h = v
    n = len(spec.layer_shapes)
    for i in range(n):
        h = h @ np.asarray(arrays[f"{prefix}/W{i}"]).T + np.asarray(arrays[f"{prefix}/b{i}"])
        if i < n - 1:
            h = f(h)
    if spec.skip:
        h = h + v @ np.asarray(arrays[f"{prefix}/Wskip"]).T
    return h * np.asarray(arrays[f"{prefix}/out_std"]) + np.asarray(arrays[f"{prefix}/out_mean"])
