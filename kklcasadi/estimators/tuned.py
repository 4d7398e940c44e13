"""The EKF an engineer has tuned: Q and R scales chosen on tuning trials (issue 46.4).

Where the model is off or the noise is not Gaussian, the EKF with the simulator's ``Q`` and ``R``
(:meth:`kklcasadi.EKF.for_noise`) is not the best EKF: inflating ``Q`` lets it follow a plant its
model does not describe, inflating ``R`` makes it trust heavy-tailed measurements less. A fair
baseline for a learned observer is therefore the EKF whose scales are chosen as an engineer would:
on a grid, by the error on simulated **tuning** trials whose true states are known (never on the
trials it is scored on). :func:`grid_search` is the search, shared with the augmented EKF.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..metrics import smape
from ..plant.systems import System
from ..validation import Text, error, positive_number, state_stds
from .ekf import EKF, noise_covariances

__all__ = ["TunedEKF", "Tuning", "grid_search", "Q_SCALES", "R_SCALES"]

#: The grid of the process-noise std's factor (Q scales as its square): from the simulator's noise up
#: to the large values that let the filter follow a plant its model does not describe.
Q_SCALES = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
#: The grid of the measurement-noise std's factor (R scales as its square).
R_SCALES = (0.25, 0.5, 1.0, 2.0, 4.0)


@dataclass(frozen=True)
class Tuning:
    """The result of a grid search: every point's score and the one chosen.

    Attributes
    ----------
    names : tuple of str
        The tuned arguments, in the grid's order.
    points : tuple of tuple
        Every point of the grid (one value per name).
    scores : tuple of float
        The mean SMAPE (%) on the tuning trials of each point (inf where the filter failed).
    n_trials : int
        The tuning trials scored.
    """

    names: tuple[str, ...]
    points: tuple[tuple[float, ...], ...]
    scores: tuple[float, ...]
    n_trials: int

    @property
    def best(self) -> dict[str, float]:
        """The chosen point (lowest score; the first of equals in grid order)."""
        return dict(zip(self.names, self.points[int(np.argmin(self.scores))]))

    @property
    def best_score(self) -> float:
        return float(min(self.scores))

    def to_json(self) -> dict[str, Any]:
        return {"names": list(self.names), "points": [list(p) for p in self.points],
                "scores": [None if not np.isfinite(s) else s for s in self.scores], "n_trials": self.n_trials,
                "best": self.best}


def _trials(tuning: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(t, x, y, u)`` of a :class:`kklcasadi.TrajectoryBatch` (its ``ok`` trials) or a 4-tuple."""
    if hasattr(tuning, "ok"):
        keep = np.asarray(tuning.ok, dtype=bool)
        return tuning.t, tuning.x[keep], tuning.y[keep], tuning.u[keep]
    if isinstance(tuning, tuple) and len(tuning) == 4:
        return tuple(np.asarray(a, dtype=float) for a in tuning)   # type: ignore[return-value]
    raise error("tuning", "a kklcasadi.TrajectoryBatch or a tuple (t, x (M,N,nx), y (M,N,ny), u (M,N,nu))",
                Text(type(tuning).__name__), kind=TypeError)


def grid_search(build: Callable[..., Any], grid: Mapping[str, Sequence[float]], tuning: Any, *,
                nx: int | None = None, angles: Sequence[int] = (),
                run: Callable[[Any, np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None) -> Tuning:
    """Score ``build(**point)`` at every point of ``grid`` on the tuning trials; the lowest mean SMAPE wins.

    Parameters
    ----------
    build : callable
        ``build(**point) -> estimator``.
    grid : mapping of name to values
        The grid's axes; every combination is tried.
    tuning : TrajectoryBatch or tuple ``(t, x, y, u)``
        Tuning trials with their true states (their own seed; never the scored trials).
    nx : int, optional
        Score the first ``nx`` components of the estimate (an augmented filter's plant states);
        default all.
    angles : sequence of int
        Angle states (wrapped in the SMAPE).
    run : callable, optional
        ``run(estimator, t, y, u) -> xhat (M, N, n)``; default ``estimator.simulate(t, y, u).xhat``.
    """
    t, x, y, u = _trials(tuning)
    if len(x) == 0:
        raise error("tuning", "at least one trial that did not escape", Text("0 trials"))
    names = tuple(grid)
    points = tuple(itertools.product(*(tuple(float(v) for v in grid[n]) for n in names)))
    scores = []
    for point in points:
        estimator = build(**dict(zip(names, point)))
        xhat = estimator.simulate(t, y, u).xhat if run is None else run(estimator, t, y, u)
        values = smape(x, np.asarray(xhat)[..., :nx or x.shape[-1]], angles=angles)
        score = float(np.mean(values))
        scores.append(score if np.isfinite(score) else np.inf)
    return Tuning(names, points, tuple(scores), len(x))


class TunedEKF(EKF):
    """An EKF with ``Q = diag(q_scale process_std dt)^2`` and ``R = (r_scale measurement_std)^2 I``.

    :meth:`fit` chooses the scales on tuning trials; constructed directly it is
    :meth:`kklcasadi.EKF.for_noise` with the scales applied.

    Parameters
    ----------
    system : System
    dt : float
    process_std : float or sequence of float (nx,)
        The simulator's process-noise std (one, or one per state).
    measurement_std : float
        The simulator's measurement-noise std (scale).
    q_scale, r_scale : float
        Factors (> 0) of the two stds.
    **options
        ``x0``, ``P0``, ``substeps``, ``params`` of :class:`kklcasadi.EKF`.

    Attributes
    ----------
    q_scale, r_scale : float
    tuning : Tuning or None
        The grid search that chose the scales (:meth:`fit`), None when given.
    """

    def __init__(self, system: System, dt: float, *, process_std: float | Sequence[float], measurement_std: float,
                 q_scale: float = 1.0, r_scale: float = 1.0, **options: Any) -> None:
        self.q_scale = positive_number(q_scale, "q_scale")
        self.r_scale = positive_number(r_scale, "r_scale")
        self.tuning: Tuning | None = None
        Q, R = noise_covariances(system, dt, process_std=state_stds(process_std, system.nx) * self.q_scale,
                                 measurement_std=positive_number(measurement_std, "measurement_std") * self.r_scale)
        super().__init__(system, dt, Q=Q, R=R, **options)

    @classmethod
    def fit(cls, system: System, dt: float, tuning: Any, *, process_std: float | Sequence[float],
            measurement_std: float, q_scales: Sequence[float] = Q_SCALES, r_scales: Sequence[float] = R_SCALES,
            run: Callable | None = None, **options: Any) -> TunedEKF:
        """The EKF whose scales score best on ``tuning`` (see :func:`grid_search`).

        Parameters
        ----------
        tuning : TrajectoryBatch or tuple ``(t, x, y, u)``
            Tuning trials (their own seed).
        q_scales, r_scales : sequence of float
            The grid (default :data:`Q_SCALES` x :data:`R_SCALES`, 40 filters).
        run : callable, optional
            How to run a filter over the trials (see :func:`grid_search`).
        """
        def build(q_scale: float, r_scale: float) -> TunedEKF:
            return cls(system, dt, process_std=process_std, measurement_std=measurement_std, q_scale=q_scale,
                       r_scale=r_scale, **options)

        result = grid_search(build, {"q_scale": q_scales, "r_scale": r_scales}, tuning, angles=system.angle_states,
                             run=run)
        best = build(**result.best)
        best.tuning = result
        return best
