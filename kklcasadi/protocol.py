"""The benchmark protocol of docs/protocol.md: trials per (system, input regime) cell and their scoring.

Every method sees the same trials: initial states from a seeded Latin hypercube over X0, input
parameters and noise draws from seeds derived from ``(seed, regime index, trial)``. Noise-free and
noisy runs share the initial states, inputs and (unit) noise draws, scaled by the noise levels.

The trials of a cell are deterministic, so :func:`evaluate` can take them from an in-memory dict
(shared by the methods of one run) and from a :class:`~kklcasadi.trialcache.TrialCache` on disk
(shared by every run). An estimator is any callable ``(t, y, u) -> xhat``; the fast ones
(:func:`kklcasadi.compiled.observer_estimator`, :func:`kklcasadi.compiled.ekf_estimator`) run
compiled trajectories mapped over the trials.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable, Optional, Sequence, Union

import numpy as np
from tqdm.auto import tqdm

from . import metrics
from . import signals as sig
from .simulate import TrajectoryBatch, simulate_batch
from .systems import System

if TYPE_CHECKING:
    from .trialcache import TrialCache

__all__ = ["Protocol", "CellResult", "evaluate", "cell_trials", "Estimator"]

#: An estimator maps measured trials to estimates: ``(t (N,), y (M, N, ny), u (M, N, nu)) -> xhat (M, N, nx)``.
Estimator = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Protocol:
    """Settings of the benchmark (defaults: docs/protocol.md, noise on).

    Use :meth:`noise_free` for the column comparable with the paper's table.
    """

    n_trials: int = 100
    T: float = 50.0
    dt: float = 0.05
    process_std: float = 0.1
    measurement_std: float = 0.1
    seed: int = 2026
    regime: str = "id"
    method: str = "cvodes"
    t_settle: float = 5.0

    def __post_init__(self) -> None:
        if not isinstance(self.n_trials, int) or self.n_trials < 1:
            raise ValueError(f"n_trials must be a positive integer, got {self.n_trials!r}")
        if self.regime not in sig.REGIMES:
            raise ValueError(f"unknown regime {self.regime!r}; known regimes: {', '.join(sig.REGIMES)}")

    @property
    def noisy(self) -> bool:
        return self.process_std > 0 or self.measurement_std > 0

    def noise_free(self) -> Protocol:
        """The same protocol without process or measurement noise."""
        return replace(self, process_std=0.0, measurement_std=0.0)

    def signals(self, system: System, kind: str) -> list[sig.Signal]:
        """The per-trial inputs of the ``kind`` column (seeded, identical for every method)."""
        if kind not in sig.BENCHMARK_KINDS:
            raise ValueError(f"unknown input regime {kind!r}; known: {', '.join(sig.BENCHMARK_KINDS)}")
        rng = np.random.default_rng([self.seed, sig.BENCHMARK_KINDS.index(kind)])
        return [sig.sample(kind, rng, self.regime, nu=system.nu) for _ in range(self.n_trials)]

    def trials(self, system: System, kind: str) -> TrajectoryBatch:
        """Simulate the cell ``(system, kind)``: ``n_trials`` runs of ``T`` seconds."""
        x0 = system.sample_box(self.n_trials, self.seed)
        seeds = np.random.SeedSequence([self.seed, sig.BENCHMARK_KINDS.index(kind)]).spawn(self.n_trials)
        return simulate_batch(system, x0, self.signals(system, kind), self.T, self.dt, process_std=self.process_std,
                              measurement_std=self.measurement_std, seed=seeds, method=self.method)


@dataclass(frozen=True, eq=False)
class CellResult:
    """Scores of one method on one cell: per-trial SMAPE (%) and RMSE after ``t_settle``."""

    system: str
    kind: str
    noisy: bool
    smape: np.ndarray
    rmse_after: np.ndarray

    @property
    def summary(self) -> metrics.Summary:
        return metrics.summarize(self.smape)


def cell_trials(system: System, protocol: Protocol, kind: str, *, trials: Optional[dict] = None,
                trial_cache: Optional[TrialCache] = None) -> TrajectoryBatch:
    """The trials of the cell ``(system, kind)``: from ``trials``, else ``trial_cache``, else simulated.

    Parameters
    ----------
    system : System
    protocol : Protocol
    kind : str
        Input regime (:data:`kklcasadi.signals.BENCHMARK_KINDS`).
    trials : dict, optional
        In-memory cache ``{kind: TrajectoryBatch}`` of this protocol (filled on a miss).
    trial_cache : TrialCache, optional
        On-disk cache (read, or written on a miss).

    Returns
    -------
    TrajectoryBatch
        Bitwise :meth:`Protocol.trials` ``(system, kind)``.
    """
    batch = trials.get(kind) if trials is not None else None
    if batch is None:
        batch = protocol.trials(system, kind) if trial_cache is None else trial_cache.trials(system, protocol, kind)
        if trials is not None:
            trials[kind] = batch
    return batch


def evaluate(estimator: Estimator, system: System, protocol: Protocol = Protocol(),
             kinds: Sequence[str] = sig.BENCHMARK_KINDS, *, trials: Optional[dict] = None,
             trial_cache: Optional[TrialCache] = None, progress: Union[bool, str] = False) -> list[CellResult]:
    """Score ``estimator`` on every input regime of ``system`` under ``protocol``.

    Parameters
    ----------
    estimator : callable ``(t, y, u) -> xhat``
        ``t`` (N,), ``y`` (M, N, ny), ``u`` (M, N, nu) -> ``xhat`` (M, N, nx); e.g. a
        :class:`kklcasadi.compiled.TrajectoryEstimator`.
    system : System
    protocol : Protocol
    kinds : sequence of str
        Input regimes to score.
    trials : dict, optional
        Cache ``{kind: TrajectoryBatch}`` reused across estimators (filled when given empty).
    trial_cache : TrialCache, optional
        On-disk cache of the cells' trials (see :func:`cell_trials`).
    progress : bool or str
        Show a progress bar over the cells; a str labels it.

    Returns
    -------
    list of CellResult
        One per kind, in order; trials that failed in the simulation (``ok`` False) are left out.
    """
    results = []
    label = progress if isinstance(progress, str) else system.name
    for kind in tqdm(kinds, desc=label, unit="cell", disable=not progress):
        batch = cell_trials(system, protocol, kind, trials=trials, trial_cache=trial_cache)
        ok = batch.ok
        xhat = np.asarray(estimator(batch.t, batch.y[ok], batch.u[ok]), dtype=float)
        if xhat.shape != batch.x[ok].shape:
            raise ValueError(f"estimator returned shape {xhat.shape}, expected {batch.x[ok].shape}")
        results.append(CellResult(system.name, kind, protocol.noisy, metrics.smape(batch.x[ok], xhat),
                                  metrics.rmse_after(batch.t, batch.x[ok], xhat, protocol.t_settle)))
    return results
