"""The input-window convention shared by training, evaluation, export and C.

The window ``w_k`` holds the last ``window`` input samples up to and including ``u_k``, oldest
first, shape (window, nu); before ``t = 0`` it is filled with ``u_0``.
"""

from __future__ import annotations

import numpy as np

from ..validation import positive_int

__all__ = ["input_windows"]


def input_windows(u: np.ndarray, window: int) -> np.ndarray:
    """All input windows of a sampled input, as a read-only view.

    Parameters
    ----------
    u : numpy.ndarray, shape (N, nu) or (M, N, nu)
    window : int
        Window length (number of samples), >= 1.

    Returns
    -------
    numpy.ndarray, shape (N, window, nu) or (M, N, window, nu)
        ``out[k] = [u_{k-window+1}, ..., u_k]`` (oldest first), with ``u_j = u_0`` for ``j < 0``.
    """
    window = positive_int(window, "window")
    u = np.asarray(u, dtype=float)
    if u.ndim not in (2, 3):
        raise ValueError(f"u: expected shape (N, nu) or (M, N, nu), received {u.shape}.")
    axis = u.ndim - 2
    first = np.take(u, [0], axis=axis)
    padded = np.concatenate([np.repeat(first, window - 1, axis=axis), u], axis=axis)
    view = np.lib.stride_tricks.sliding_window_view(padded, window, axis=axis)
    return np.moveaxis(view, -1, -2)
