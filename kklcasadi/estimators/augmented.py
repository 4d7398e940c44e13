"""Filters that estimate the uncertain parameters with the state (issue 46.4): the augmented EKF and the
particle filter over states and parameters.

Both run on :func:`kklcasadi.plant.augment.augmented`, the plant with its parameters ``p`` (and,
optionally, a constant input disturbance ``d``: ``u + d``, the offset-free construction) as extra
states that do not move. The augmented EKF lets them drift as random walks (``p`` increments of std
``param_walk * width(p) * sqrt(dt)`` per sample, ``width`` the parameter box's); it starts at the
nominal values with the box's uniform variance. The particle filter draws its particles' parameters
from the box (its prior) and keeps them constant between resamplings; after each resampling it
moves them by Liu and West's kernel shrinkage (``p <- a p + (1 - a) mean(p) + h std(p) n``,
``a = sqrt(1 - h^2)``: the cloud's mean and variance are kept, and the copies a resampling makes
part again), where the states' roughening (a jitter proportional to the cloud's range) would
widen a parameter cloud that one sample barely constrains at every resampling.

The estimate of either (``simulate``) is the augmented state; :meth:`AugmentedEKF.__call__` (the
protocol's estimator) and the step estimator of ``estimator()`` (:class:`PlantStates`, what a control
loop such as :func:`kklcasadi.estimators.nmpc.closed_loop` takes) return the plant's states, and
:meth:`split` separates the parts.
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np

from ..model.variants.ekfblock import register_filter
from ..plant.augment import augmented
from ..plant.systems import System
from ..validation import Text, error, nonnegative_number, positive_number, state_stds
from .ekf import EKF, noise_covariances
from .pf import ParticleFilter

__all__ = ["AugmentedEKF", "ParameterPF", "PlantStates", "PARAM_WALKS", "SHRINKAGE"]

#: The grid of the random walk's rate (a fraction of the box width per square-root second) that
#: :meth:`AugmentedEKF.fit` searches with the noise scales.
PARAM_WALKS = (0.001, 0.003, 0.01, 0.03, 0.1)
#: Liu and West's ``h`` of :class:`ParameterPF` (a discount of about 0.99).
SHRINKAGE = 0.1


class _Split:
    """The parts of an augmented estimate ``[x; p; d]`` (mixin of the two filters)."""

    plant: System
    nx: int

    def split(self, xhat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x (..., nx), p (..., n_params), d (..., nu or 0))`` of an augmented estimate (..., nx + n_params + nd)."""
        n_p = self.plant.n_params
        xhat = np.asarray(xhat)
        return xhat[..., :self.nx], xhat[..., self.nx:self.nx + n_p], xhat[..., self.nx + n_p:]

    def __call__(self, t: object, y: object, u: object) -> np.ndarray:
        """The protocol's estimator: ``(t (N,), y (M, N, ny), u (M, N, nu)) -> xhat (M, N, nx)``, the plant's states."""
        return self.split(self.simulate(t, y, u).xhat)[0]   # type: ignore[attr-defined]

    def estimator(self) -> PlantStates:
        """The filter one sample at a time: ``xhat = est.make_step(y, u)`` gives the plant's states (nx,); the
        parameters and the disturbance of the same step are ``est.params`` and ``est.disturbance``
        (a :class:`PlantStates` around the augmented filter's own step estimator)."""
        return PlantStates(super().estimator(), self)   # type: ignore[misc]


class PlantStates:
    """The step estimator of an augmented filter, as the plant's states (a
    :class:`kklcasadi.estimate.StepEstimator`).

    ``make_step(y_k, u_k)`` returns the first ``nx`` components of the augmented filter's step (bitwise
    the plant's part of its ``simulate``), so that a loop written for the plant's estimators (the NMPC
    loop, the closed-loop example) takes it as it takes the EKF's.

    Parameters
    ----------
    inner : StepEstimator
        The augmented filter's own step estimator (``EKF.estimator()`` or ``ParticleFilter.estimator()``
        of the augmented plant).
    filt : AugmentedEKF or ParameterPF
        The filter (its :meth:`split`).

    Attributes
    ----------
    inner : StepEstimator
    augmented : ndarray (nx + n_params + nd,) or None
        The last augmented estimate, None before the first step.
    """

    def __init__(self, inner: Any, filt: _Split) -> None:
        if not callable(getattr(inner, "make_step", None)):
            raise error("inner", "a step estimator with make_step(y, u)", Text(type(inner).__name__), kind=TypeError)
        self.inner, self._split = inner, filt.split
        self.nx = filt.nx
        self.augmented: Optional[np.ndarray] = None

    @property
    def k(self) -> int:
        """Samples taken since the start or the last :meth:`reset`."""
        return int(self.inner.k)

    def reset(self) -> None:
        """Forget the past: the next :meth:`make_step` starts again from the prior."""
        self.inner.reset()
        self.augmented = None

    def make_step(self, y: object, u: object) -> np.ndarray:
        """Feed ``y_k`` and ``u_k`` (the input held from ``t_k``); return the plant's states ``xhat_k`` (nx,)."""
        self.augmented = np.asarray(self.inner.make_step(y, u), dtype=float)
        return self._split(self.augmented)[0].copy()

    def _part(self, i: int) -> Optional[np.ndarray]:
        return None if self.augmented is None else self._split(self.augmented)[i].copy()

    @property
    def params(self) -> Optional[np.ndarray]:
        """The parameters' estimate (n_params,) of the last step, None before the first."""
        return self._part(1)

    @property
    def disturbance(self) -> Optional[np.ndarray]:
        """The input disturbance's estimate (nu,) of the last step (empty without one), None before the first."""
        return self._part(2)

    @property
    def cov(self) -> Optional[np.ndarray]:
        """The plant states' block (nx, nx) of the augmented filter's covariance (the EKF's ``P``), None before
        the first step; absent (AttributeError) where the inner estimator reports none (the particle filter)."""
        cov = self.inner.cov
        return None if cov is None else np.asarray(cov)[:self.nx, :self.nx].copy()

    @property
    def stats(self) -> dict:
        """The inner estimator's stats with ``var`` cut to the plant's states and ``var_augmented`` beside it."""
        stats = dict(self.inner.stats)
        var = stats.get("var")
        stats["var_augmented"] = var
        stats["var"] = None if var is None else np.asarray(var)[:self.nx].copy()
        return stats


# estimator() gives the plant-state step estimator (PlantStates), not the inner filter's own: a deliberate
# override in both filters (the type: ignore[misc] on their class lines)
class AugmentedEKF(_Split, EKF):  # type: ignore[misc]
    """EKF of the plant with its parameters (and an input disturbance) as random-walk states.

    Parameters
    ----------
    system : System
        A plant with parameters (or any plant with ``input_disturbance``).
    dt : float
    process_std : float or sequence (nx,)
        The plant states' process-noise std (as :meth:`kklcasadi.EKF.for_noise`).
    measurement_std : float
    param_walk : float
        The parameters' random walk: increments of std ``param_walk * width * sqrt(dt)`` per sample.
    input_disturbance : bool
        Also estimate a constant input disturbance ``d`` (prior box ``disturbance_box``, default
        ``[-1, 1]``), a random walk of ``disturbance_walk * width * sqrt(dt)``.
    disturbance_box : array_like (nu, 2), optional
    disturbance_walk : float
    q_scale, r_scale : float
        Factors of the plant states' process-noise std and of the measurement std (as :class:`TunedEKF`).
    substeps : int or "auto"
        RK4 steps per sample (as :class:`kklcasadi.EKF`'s; "auto" on the augmented plant).

    Attributes
    ----------
    plant : System
        The plant (``system``); :attr:`system` is the augmented one the filter runs.
    nx : int
        The plant's states.
    tuning : Tuning or None
        The grid search of :meth:`fit`.
    """

    def __init__(self, system: System, dt: float, *, process_std: float | Sequence[float] = 0.1,
                 measurement_std: float = 0.1, param_walk: float = 0.01, input_disturbance: bool = False,
                 disturbance_box: Any = None, disturbance_walk: float = 0.01, q_scale: float = 1.0,
                 r_scale: float = 1.0, substeps: int | str = "auto") -> None:
        aug = augmented(system, input_disturbance=input_disturbance, disturbance_box=disturbance_box)
        self.plant, self.nx = system, system.nx
        self.param_walk = nonnegative_number(param_walk, "param_walk")
        self.disturbance_walk = nonnegative_number(disturbance_walk, "disturbance_walk")
        self.q_scale = positive_number(q_scale, "q_scale")
        self.r_scale = positive_number(r_scale, "r_scale")
        self.tuning = None
        n_p, n_d = system.n_params, aug.nx - system.nx - system.n_params
        width = aug.x0_box[:, 1] - aug.x0_box[:, 0]
        dt = positive_number(dt, "dt")
        Q, R = noise_covariances(system, dt, process_std=state_stds(process_std, system.nx) * self.q_scale,
                                 measurement_std=positive_number(measurement_std, "measurement_std") * self.r_scale)
        walk = np.concatenate([np.full(n_p, self.param_walk), np.full(n_d, self.disturbance_walk)])
        walk_var = (walk * width[system.nx:]) ** 2 * dt
        x0 = aug.x0_box.mean(axis=1)
        if n_p:
            x0[system.nx:system.nx + n_p] = system.param_nominal
        super().__init__(aug, dt, Q=np.diag(np.concatenate([np.diag(Q), np.maximum(walk_var, 1e-18)])), R=R, x0=x0,
                         substeps=substeps)

    @classmethod
    def fit(cls, system: System, dt: float, tuning: Any, *, q_scales: Sequence[float] = (1.0, 4.0, 16.0),
            r_scales: Sequence[float] = (1.0, 2.0), param_walks: Sequence[float] = PARAM_WALKS,
            run: Any = None, **options: Any) -> AugmentedEKF:
        """The augmented EKF whose noise scales and walk rate score best on ``tuning`` (mean SMAPE of the plant's
        states; :func:`kklcasadi.estimators.tuned.grid_search`).

        Parameters
        ----------
        tuning : TrajectoryBatch or tuple ``(t, x, y, u)``
            Tuning trials (their own seed; never the scored trials).
        q_scales, r_scales, param_walks : sequence of float
            The grid (default 3 x 2 x 5 = 30 filters).
        **options
            The other arguments of :class:`AugmentedEKF`.
        """
        from .tuned import grid_search

        def build(q_scale: float, r_scale: float, param_walk: float) -> AugmentedEKF:
            return cls(system, dt, q_scale=q_scale, r_scale=r_scale, param_walk=param_walk, **options)

        result = grid_search(build, {"q_scale": q_scales, "r_scale": r_scales, "param_walk": param_walks}, tuning,
                             nx=system.nx, angles=system.angle_states, run=run)
        best = build(**result.best)
        best.tuning = result
        return best


class ParameterPF(_Split, ParticleFilter):  # type: ignore[misc]
    """The bootstrap particle filter over states and parameters, the parameter box as the prior.

    Parameters
    ----------
    system : System
        A plant with parameters.
    dt : float
    process_std : float or sequence (nx,)
        The plant states' process noise (the parameters get none: they move only by roughening).
    input_disturbance : bool
        Also a constant input disturbance ``d`` with a uniform prior on ``disturbance_box``.
    disturbance_box : array_like (nu, 2), optional
    shrinkage : float
        Liu and West's ``h`` (0 < h < 1) of the parameters' move after a resampling (0.1: a discount of
        about 0.99).
    **options
        The other arguments of :class:`kklcasadi.estimators.ParticleFilter` (``n_particles``,
        ``measurement_std``, ``noise_model``, ``roughening``, ``seed``, ...); the prior is uniform on the
        augmented box.
    """

    def __init__(self, system: System, dt: float, *, process_std: float | Sequence[float] = 0.1,
                 input_disturbance: bool = False, disturbance_box: Any = None, shrinkage: float = SHRINKAGE,
                 **options: Any) -> None:
        aug = augmented(system, input_disturbance=input_disturbance, disturbance_box=disturbance_box)
        self.plant, self.nx = system, system.nx
        self.shrinkage = positive_number(shrinkage, "shrinkage")
        if self.shrinkage >= 1:
            raise error("shrinkage", "Liu and West's h, 0 < h < 1", shrinkage)
        stds = np.zeros(aug.nx)
        stds[:system.nx] = state_stds(process_std, system.nx)
        super().__init__(aug, dt, process_std=stds, **options)

    def roughen(self, X: np.ndarray, rng: np.random.Generator) -> None:
        """The states' roughening (:meth:`ParticleFilter.roughen` on the plant's states), then the
        parameters' kernel shrinkage (module docstring); draws ``(n_particles, nx_augmented)`` normals."""
        n, nx = X.shape[0], self.nx
        draws = rng.standard_normal(X.shape)
        if self.roughening > 0:
            X[:, :nx] += self.roughening * np.ptp(X[:, :nx], axis=0) * n ** (-1.0 / nx) * draws[:, :nx]
        theta = X[:, nx:]
        a = np.sqrt(1.0 - self.shrinkage ** 2)
        theta[:] = a * theta + (1.0 - a) * theta.mean(axis=0) + self.shrinkage * theta.std(axis=0) * draws[:, nx:]


register_filter(AugmentedEKF)        # the bank latent's augmented EKF block runs this filter's step
