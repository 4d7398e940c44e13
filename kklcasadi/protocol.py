"""The benchmark protocol of PROTOCOL.md: trials per (system, input regime) cell and their scoring.

Every method sees the same trials: initial states from a seeded Latin hypercube over X0, input
parameters and noise draws from seeds derived from ``(seed, regime index, trial)``. Noise-free and
noisy runs share the initial states, inputs and (unit) noise draws, scaled by the noise levels.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np

from . import metrics
from . import signals as sig
from .simulate import TrajectoryBatch, simulate_batch
from .systems import System

__all__ = ["Protocol", "CellResult", "evaluate", "Estimator"]

#: An estimator maps measured trials to estimates: ``(t (N,), y (M, N, ny), u (M, N, nu)) -> xhat (M, N, nx)``.
Estimator = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Protocol:
    """Settings of the benchmark (defaults: PROTOCOL.md, noise on).

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


def evaluate(estimator: Estimator, system: System, protocol: Protocol = Protocol(),
             kinds: Sequence[str] = sig.BENCHMARK_KINDS, *, trials: dict | None = None) -> list[CellResult]:
    """Score ``estimator`` on every input regime of ``system`` under ``protocol``.

    Parameters
    ----------
    estimator : callable ``(t, y, u) -> xhat``
        ``y`` (M, N, ny), ``u`` (M, N, nu) -> ``xhat`` (M, N, nx).
    trials : dict, optional
        Cache ``{kind: TrajectoryBatch}`` reused across estimators (filled when given empty).
    """
    results = []
    for kind in kinds:
        batch = trials.get(kind) if trials is not None else None
        if batch is None:
            batch = protocol.trials(system, kind)
            if trials is not None:
                trials[kind] = batch
        ok = batch.ok
        xhat = np.asarray(estimator(batch.t, batch.y[ok], batch.u[ok]), dtype=float)
        if xhat.shape != batch.x[ok].shape:
            raise ValueError(f"estimator returned shape {xhat.shape}, expected {batch.x[ok].shape}")
        results.append(CellResult(system.name, kind, protocol.noisy, metrics.smape(batch.x[ok], xhat),
                                  metrics.rmse_after(batch.t, batch.x[ok], xhat, protocol.t_settle)))
    return results
