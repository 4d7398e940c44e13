"""Interoperability with python-control: the observer as a discrete-time ``NonlinearIOSystem``."""

from __future__ import annotations

from typing import TYPE_CHECKING

import control
import numpy as np

if TYPE_CHECKING:
    from .kkl import KKLObserver

__all__ = ["to_iosys"]


def to_iosys(observer: KKLObserver, name: str = "kkl_observer") -> control.NonlinearIOSystem:
    """The observer as a discrete-time :class:`control.NonlinearIOSystem` with ``dt = obs.dt``.

    Inputs ``[y[0], ..., y[ny-1], u[0], ..., u[nu-1]]`` (the sample ``y_k`` and the input ``u_k``
    held from ``t_k``), outputs ``xhat[0], ..., xhat[nx-1]``. The output at sample k depends on
    the input at sample k (the estimate uses ``y_k``), so the system state is what the observer
    knew before it: ``[z_k-1; vec(w_k-1); y_k-1; started]`` (``vec`` column-major; ``w`` is the
    observer's input memory, the window for windowed variants). With the default initial state 0
    (``started = 0``) the first sample initialises ``z_0 = 0`` and the memory from ``u_0``
    (``observer.memory_init(y_0, u_0)``), and :func:`control.input_output_response` reproduces
    :meth:`KKLObserver.simulate`.

    Parameters
    ----------
    observer : KKLObserver
    name : str
        The system's name.

    Returns
    -------
    control.NonlinearIOSystem
    """
    from .kkl import KKLObserver

    if not isinstance(observer, KKLObserver):
        raise TypeError(f"observer: expected a KKLObserver, received {type(observer).__name__}.")
    if not isinstance(name, str) or not name:
        raise ValueError(f"name: expected a non-empty string, received {name!r}.")
    nz, ny, nu = observer.nz, observer.ny, observer.nu
    rows, cols = observer.memory_shape
    n_window = rows * cols

    def advance(x: np.ndarray, inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(z_k, vec w_k, xhat_k)`` from the state before sample k and the inputs at k."""
        y, u = inputs[:ny], inputs[ny:]
        if x[-1] < 0.5:                                      # not started: first sample
            z, w = np.zeros(nz), np.asarray(observer.memory_init(y, u))
            xhat = observer.decode(z, w)
            return z, w.ravel(order="F"), np.asarray(xhat).ravel()
        w = x[nz:nz + n_window].reshape(rows, cols, order="F")
        y_prev = x[nz + n_window:nz + n_window + ny]
        z_next, w_next, xhat = observer.step(x[:nz], w, y_prev, y, u)
        return (np.asarray(z_next).ravel(), np.asarray(w_next).ravel(order="F"),
                np.asarray(xhat).ravel())

    def update(t: float, x: np.ndarray, inputs: np.ndarray, params: dict) -> np.ndarray:
        z, w, _ = advance(np.asarray(x, dtype=float), np.asarray(inputs, dtype=float))
        return np.concatenate([z, w, np.asarray(inputs, dtype=float)[:ny], [1.0]])

    def output(t: float, x: np.ndarray, inputs: np.ndarray, params: dict) -> np.ndarray:
        return advance(np.asarray(x, dtype=float), np.asarray(inputs, dtype=float))[2]

    states = ([f"z[{i}]" for i in range(nz)]
              + [f"w[{i},{j}]" for j in range(cols) for i in range(rows)]
              + [f"y_prev[{i}]" for i in range(ny)] + ["started"])
    return control.NonlinearIOSystem(
        update, output, name=name, dt=observer.dt, states=states,
        inputs=[f"y[{i}]" for i in range(ny)] + [f"u[{i}]" for i in range(nu)],
        outputs=[f"xhat[{i}]" for i in range(observer.nx)])
