"""Where a rig lives, read from its logs: the envelope of a plant's training runs (``kklcasadi train --like``).

An :class:`Envelope` holds what a rig's logs say about it: the logged inputs on the model's grid,
the states along the logs (the EKF's estimates), the range of the logged outputs and inputs, and the
rig's noise (measurement std from the outputs' high-frequency residual, process std per state by the
likelihood of the EKF's innovations: :func:`kklcasadi.estimators.noise.rig_envelope` builds it). Its
card entry (:meth:`Envelope.to_card`) names every file (with its SHA-256) and what was estimated from
them; :func:`output_ranges` is the range of a plant's outputs over a state box (its X0 box by default).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..validation import Text, error, finite_array
from .systems import System

__all__ = ["Envelope", "output_ranges", "LIKE_TIME_FACTORS", "LIKE_AMPLITUDE_FACTORS", "OUTPUT_MARGIN"]

#: Samples of the X0 box at which :func:`output_ranges` evaluates ``h``.
_RANGE_SAMPLES = 4096

#: Range of the factor a ``like`` run's input segment is resampled by in time (log-uniform): 0.8 plays it
#: 25 % slower, 1.25 25 % faster.
LIKE_TIME_FACTORS = (0.8, 1.25)
#: Range of the factor it is rescaled by about zero (log-uniform; then clipped to the input range).
LIKE_AMPLITUDE_FACTORS = (0.8, 1.25)
#: A run is cut where an output leaves the logged range widened by this share of its width on each side.
OUTPUT_MARGIN = 0.1


def output_ranges(system: System, box: object = None) -> np.ndarray:
    """The range of each output ``h(x)`` over a state box, (ny, 2): a Latin hypercube of the box and its corners.

    Parameters
    ----------
    system : System
    box : array_like, shape (nx, 2), optional
        ``[lo, hi]`` per state (e.g. a model's training domain); default the X0 box (then the points
        are ``system.sample_box(4096, 0)``'s).
    """
    from scipy.stats import qmc

    box = system.x0_box if box is None else finite_array(box, "box", (system.nx, 2))
    unit = qmc.LatinHypercube(d=system.nx, seed=0).random(_RANGE_SAMPLES)
    points = [box.mean(axis=1) + (2.0 * unit - 1.0) * (0.5 * (box[:, 1] - box[:, 0]))]
    if system.nx <= 12:                                   # the 2^nx corners, where a monotone output peaks
        points.append(np.array(list(itertools.product(*box))))
    y = system.h_batch(np.vstack(points))
    return np.column_stack([y.min(axis=0), y.max(axis=0)])


def _readonly(value: object, shape: tuple, arg: str) -> np.ndarray:
    arr = np.array(value, dtype=float)
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise error(arg, f"finite values of shape {shape}", Text(f"shape {arr.shape}"))
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Envelope:
    """The envelope of a rig's training runs, read from its logs (see the module).

    Attributes
    ----------
    dt : float
        The grid of the arrays below (the model's sample time).
    inputs : tuple of numpy.ndarray, each (N_i, nu)
        The logged inputs per log on the grid (mean over each interval of a faster log); empty where
        the logs name no input columns (the rig ran at ``u = 0``).
    states : tuple of numpy.ndarray, each (N_i, nx)
        The rig's states along each log: the EKF's estimates with the estimated noise.
    y_range : numpy.ndarray, shape (ny, 2)
        The logged outputs' range (angles unwrapped and on the plant's branch).
    u_range : numpy.ndarray, shape (nu, 2), or None
        The logged inputs' range (None without input columns).
    measurement_std : float
        The measurement std the runs and the EKF take (the outputs' largest estimate, floored at
        :data:`kklcasadi.estimators.ekf.NOISE_FLOOR`).
    process_std : numpy.ndarray, shape (nx,)
        The process std per state.
    sources : tuple of dict
        One per log: ``path``, ``sha256``, ``rows``, the columns read, the grid's span.
    noise : dict
        How the noise was estimated (per-output measurement stds, the likelihood fit's record).
    settle : float
        Seconds at the start of each log where the EKF's states are its transient from the prior (no run
        starts there).
    """

    dt: float
    inputs: tuple
    states: tuple
    y_range: np.ndarray
    u_range: Optional[np.ndarray]
    measurement_std: float
    process_std: np.ndarray
    sources: tuple
    noise: dict = field(default_factory=dict)
    settle: float = 0.0

    def __post_init__(self) -> None:
        if not (isinstance(self.states, tuple) and self.states):
            raise error("states", "a non-empty tuple of (N_i, nx) arrays, one per log",
                        Text(type(self.states).__name__))
        nx = np.shape(self.states[0])[1]
        states = tuple(_readonly(s, (np.shape(s)[0], nx), f"states[{i}]") for i, s in enumerate(self.states))
        object.__setattr__(self, "states", states)
        if self.inputs:
            if len(self.inputs) != len(states):
                raise error("inputs", f"{len(states)} arrays (one per log) or none", Text(f"{len(self.inputs)}"))
            nu = np.shape(self.inputs[0])[1]
            object.__setattr__(self, "inputs", tuple(_readonly(u, (len(s), nu), f"inputs[{i}]")
                                                     for i, (u, s) in enumerate(zip(self.inputs, states))))
        y_range = np.array(self.y_range, dtype=float)
        object.__setattr__(self, "y_range", _readonly(y_range, (y_range.shape[0], 2), "y_range"))
        if self.u_range is not None:
            u_range = np.array(self.u_range, dtype=float)
            object.__setattr__(self, "u_range", _readonly(u_range, (u_range.shape[0], 2), "u_range"))
        object.__setattr__(self, "process_std", _readonly(self.process_std, (nx,), "process_std"))
        if not (self.dt > 0 and self.measurement_std >= 0 and self.settle >= 0):
            raise error("dt, measurement_std, settle", "dt > 0, a std >= 0 and seconds >= 0",
                        (self.dt, self.measurement_std, self.settle))

    @property
    def nx(self) -> int:
        return self.states[0].shape[1]

    @property
    def samples(self) -> int:
        """Grid samples over all logs."""
        return sum(len(s) for s in self.states)

    def to_card(self) -> dict:
        """The card's record: the files and what was read and estimated from them (no arrays)."""
        return {"sources": [dict(s) for s in self.sources], "dt": self.dt, "samples": self.samples,
                "y_range": self.y_range.tolist(),
                "u_range": None if self.u_range is None else self.u_range.tolist(),
                "measurement_std": self.measurement_std, "process_std": self.process_std.tolist(),
                "noise": dict(self.noise), "settle_s": self.settle,
                "like": {"time_factors": list(LIKE_TIME_FACTORS), "amplitude_factors": list(LIKE_AMPLITUDE_FACTORS)},
                "output_margin": OUTPUT_MARGIN}
