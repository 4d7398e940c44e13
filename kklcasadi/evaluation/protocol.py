"""The benchmark protocol of docs/protocol.md: trials per (system, input regime) cell and their scoring.

Every method sees the same trials: initial states from a seeded Latin hypercube over X0, input
parameters and noise draws from seeds derived from ``(seed, regime index, trial)``. Noise-free and
noisy runs share the initial states, inputs and (unit) noise draws, scaled by the noise levels.

The trials of a cell are deterministic, so :func:`evaluate` takes them from a
:class:`~kklcasadi.evaluation.trialcache.TrialCache` (in memory, shared by the methods of one run,
and on disk, shared by every run). An estimator is any callable ``(t, y, u) -> xhat``
(:data:`BatchEstimator`); the fast ones (:func:`kklcasadi.evaluation.compiled.observer_estimator`,
:func:`kklcasadi.evaluation.compiled.ekf_estimator`) run compiled trajectories mapped over the trials.
"""

from __future__ import annotations

import time
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field, fields, replace
from typing import Callable, ContextManager, Iterator, Optional, Sequence, Union

import numpy as np
from tqdm.auto import tqdm

from .. import metrics
from ..plant import signals as sig
from ..plant.simulate import TrajectoryBatch, simulate_batch
from ..plant.systems import System
from .trialcache import TrialCache

__all__ = ["Protocol", "Cell", "CellResult", "evaluate", "evaluate_cells", "read_cells", "BatchEstimator", "Profile",
           "phase"]

#: An estimator of many trials at once: ``(t (N,), y (M, N, ny), u (M, N, nu)) -> xhat (M, N, nx)``.
BatchEstimator = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


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
        """The per-trial inputs of the ``kind`` column (seeded, identical for every method), in the plant's input
        units where it declares a ``u_box`` (:func:`kklcasadi.plant.signals.in_box`)."""
        if kind not in sig.BENCHMARK_KINDS:
            raise ValueError(f"unknown input regime {kind!r}; known: {', '.join(sig.BENCHMARK_KINDS)}")
        rng = np.random.default_rng([self.seed, sig.BENCHMARK_KINDS.index(kind)])
        return [sig.in_box(sig.sample(kind, rng, self.regime, nu=system.nu), system.u_box)
                for _ in range(self.n_trials)]

    def trials(self, system: System, kind: str) -> TrajectoryBatch:
        """Simulate the cell ``(system, kind)``: ``n_trials`` runs of ``T`` seconds."""
        x0 = system.sample_box(self.n_trials, self.seed)
        seeds = np.random.SeedSequence([self.seed, sig.BENCHMARK_KINDS.index(kind)]).spawn(self.n_trials)
        return simulate_batch(system, x0, self.signals(system, kind), self.T, self.dt, process_std=self.process_std,
                              measurement_std=self.measurement_std, seed=seeds, method=self.method)

    def cell(self, kind: str) -> Cell:
        """The cell of input regime ``kind`` (what a :class:`TrialCache` stores)."""
        if kind not in sig.BENCHMARK_KINDS:
            raise ValueError(f"unknown input regime {kind!r}; known: {', '.join(sig.BENCHMARK_KINDS)}")
        return Cell(self, kind)


@dataclass(frozen=True)
class Cell:
    """One cell of the protocol: its input regime under its settings."""

    protocol: Protocol
    kind: str

    @property
    def label(self) -> str:
        """``<kind>-<clean|noisy>``, for file names."""
        return f"{self.kind}-{'noisy' if self.protocol.noisy else 'clean'}"

    def describe(self) -> dict:
        """Every field of the protocol and the regime, as plain JSON values."""
        return {"protocol": {f.name: getattr(self.protocol, f.name) for f in fields(self.protocol)},
                "kind": self.kind}

    def shape(self) -> tuple[int, int]:
        """Trials and samples per trial."""
        return self.protocol.n_trials, round(self.protocol.T / self.protocol.dt)

    def simulate(self, system: System) -> TrajectoryBatch:
        """:meth:`Protocol.trials` of the cell."""
        return self.protocol.trials(system, self.kind)


@dataclass(frozen=True, eq=False)
class CellResult:
    """Scores of one estimator on one cell: per-trial SMAPE (%) and RMSE after ``t_settle``.

    Attributes
    ----------
    system, kind : str
    noisy : bool
    smape, rmse_after : numpy.ndarray, shape (M,)
    seconds : float or None
        Wall time of the estimator over the whole cell, where it was timed.
    n_samples : int or None
        Trials x samples estimated, where timed.
    failed : int
        Failed solves whose estimate was the fallback (MHE); 0 for the others.
    solve_ms : float or None
        Mean wall time of one solver call (MHE), ms.
    escaped : int
        Trials of the cell whose state escaped (the simulation failed or blew up): not scored, and
        counted here (``smape`` and ``rmse_after`` hold the others).
    """

    system: str
    kind: str
    noisy: bool
    smape: np.ndarray
    rmse_after: np.ndarray
    seconds: Optional[float] = None
    n_samples: Optional[int] = None
    failed: int = 0
    solve_ms: Optional[float] = None
    escaped: int = 0

    @property
    def summary(self) -> metrics.Summary:
        return metrics.summarize(self.smape)

    @property
    def n_trials(self) -> int:
        """Trials of the cell, scored and escaped."""
        return len(self.smape) + self.escaped


@dataclass
class Profile:
    """Where a run's time goes: wall and CPU seconds per phase (``compile``, ``simulate``, ``read``,
    ``estimate``, ``score``).

    Phases nest (:meth:`phase`): the time of an inner phase is not counted again in the one around
    it. CPU time is this process's (all its threads); time measured elsewhere (the C compiler's
    processes) is counted with :meth:`add`.
    """

    wall: dict = field(default_factory=dict)
    cpu: dict = field(default_factory=dict)
    _stack: list = field(default_factory=list, repr=False)

    def add(self, name: str, wall: float, cpu: float) -> None:
        """Count ``wall`` and ``cpu`` seconds, measured outside any phase of this thread, for ``name``."""
        self.wall[name] = self.wall.get(name, 0.0) + wall
        self.cpu[name] = self.cpu.get(name, 0.0) + cpu

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        """Time the ``with`` block as the phase ``name``."""
        inner = [0.0, 0.0]
        self._stack.append(inner)
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            self._stack.pop()
            self.add(name, wall - inner[0], cpu - inner[1])
            if self._stack:
                self._stack[-1][0] += wall
                self._stack[-1][1] += cpu

    def table(self, wall: Optional[float] = None, cpu: Optional[float] = None) -> str:
        """A markdown table of the phases, with the run's total ``wall`` and ``cpu`` when given."""
        lines = ["| phase | wall (s) | CPU (s) | CPU / wall |", "|---|---|---|---|"]
        rows = list(self.wall.items()) + ([("total", wall)] if wall is not None and cpu is not None else [])
        for name, w in rows:
            c = cpu if name == "total" else self.cpu[name]
            lines.append(f"| {name} | {w:.1f} | {c:.1f} | {c / w if w > 0 else 0.0:.2f} |")
        return "\n".join(lines)


def phase(profile: Optional[Profile], name: str) -> ContextManager[None]:
    """``profile.phase(name)``, or a context that does nothing where ``profile`` is None."""
    return nullcontext() if profile is None else profile.phase(name)


def read_cells(system: System, cells: Sequence[Cell], trials: TrialCache, *,
               profile: Optional[Profile] = None) -> list[TrajectoryBatch]:
    """The trials of ``cells`` from ``trials`` (memory, disk, else simulated and stored).

    ``profile`` gets the phase ``read`` for a cell found on disk (or in memory), ``simulate`` for
    one simulated.
    """
    batches = []
    for cell in cells:
        stored = trials.directory is not None and trials.path(system, cell).exists()
        with phase(profile, "read" if stored else "simulate"):
            batches.append(trials.trials(system, cell))
    return batches


def evaluate_cells(estimator: BatchEstimator, system: System, cells: Sequence[Cell], *,
                   trials: Optional[TrialCache] = None, profile: Optional[Profile] = None) -> list[CellResult]:
    """Score ``estimator`` on several cells with one call: their trials concatenated along the trials.

    For estimators that do the work of trials with the same inputs once (the noise-free and noisy
    cells of one regime share their inputs; :class:`kklcasadi.evaluation.compiled.CompiledEstimator`);
    the scores are those of :func:`evaluate` cell by cell for estimators whose trials are independent.

    Parameters
    ----------
    estimator : callable ``(t, y, u) -> xhat``
    system : System
    cells : sequence of Cell
        Cells with the same sample times (horizon and ``dt``).
    trials : TrialCache, optional
        See :func:`evaluate`.
    profile : Profile, optional
        Records the phases ``simulate`` or ``read`` (the trials), ``estimate`` and ``score``.

    Returns
    -------
    list of CellResult
        One per cell, in order.
    """
    batches = read_cells(system, cells, TrialCache(None) if trials is None else trials, profile=profile)
    t = batches[0].t
    for cell, batch in zip(cells, batches):
        if not np.array_equal(batch.t, t):
            raise ValueError(f"cells: expected the same sample times, received {cell.label} with {batch.t.size} "
                             f"samples (dt {cell.protocol.dt}) beside {t.size}.")
    oks = [batch.ok for batch in batches]
    with phase(profile, "estimate"):
        y = np.concatenate([batch.y[ok] for batch, ok in zip(batches, oks)])
        u = np.concatenate([batch.u[ok] for batch, ok in zip(batches, oks)])
        xhat = (np.asarray(estimator(t, y, u), dtype=float) if y.shape[0] else np.zeros((0, t.size, system.nx)))
    expected = (y.shape[0], t.size, system.nx)
    if xhat.shape != expected:
        raise ValueError(f"estimator returned shape {xhat.shape}, expected {expected}")
    results, start = [], 0
    with phase(profile, "score"):
        for cell, batch, ok in zip(cells, batches, oks):
            part, start = xhat[start:start + int(ok.sum())], start + int(ok.sum())
            x = batch.x[ok]
            escaped = int((~ok).sum())
            if not ok.any():
                results.append(CellResult(system.name, cell.kind, cell.protocol.noisy, np.zeros(0), np.zeros(0),
                                          escaped=escaped))
                continue
            results.append(CellResult(system.name, cell.kind, cell.protocol.noisy, metrics.smape(x, part),
                                      metrics.rmse_after(t, x, part, cell.protocol.t_settle), escaped=escaped))
    return results


def evaluate(estimator: BatchEstimator, system: System, protocol: Protocol = Protocol(),
             kinds: Sequence[str] = sig.BENCHMARK_KINDS, *, trials: Optional[TrialCache] = None,
             progress: Union[bool, str] = False) -> list[CellResult]:
    """Score ``estimator`` on every input regime of ``system`` under ``protocol``.

    Parameters
    ----------
    estimator : callable ``(t, y, u) -> xhat``
        ``t`` (N,), ``y`` (M, N, ny), ``u`` (M, N, nu) -> ``xhat`` (M, N, nx); e.g. a
        :class:`kklcasadi.evaluation.compiled.CompiledEstimator`.
    system : System
    protocol : Protocol
    kinds : sequence of str
        Input regimes to score.
    trials : TrialCache, optional
        Where the cells' trials come from (memory, then disk, else simulated and kept); pass one
        to share them across estimators and runs. Default: simulated for this call.
    progress : bool or str
        Show a progress bar over the cells; a str labels it.

    Returns
    -------
    list of CellResult
        One per kind, in order; trials whose state escaped in the simulation (``ok`` False) are not
        scored and counted in ``escaped``.
    """
    trials = TrialCache(None) if trials is None else trials
    label = progress if isinstance(progress, str) else system.name
    return [evaluate_cells(estimator, system, [protocol.cell(kind)], trials=trials)[0]
            for kind in tqdm(kinds, desc=label, unit="cell", disable=not progress)]
