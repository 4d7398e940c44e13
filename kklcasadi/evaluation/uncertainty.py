"""The estimators' own covariances on the protocol's cells, scored the same way (issue 49).

A learned observer with a covariance head (:attr:`kklcasadi.observer.kkl.KKLObserver.covariance`), the EKF and the
particle filter each report, with every estimate, how far off it may be. :func:`score_uncertainty` runs them on the
same trials and scores each covariance against the errors with :func:`kklcasadi.consistency.consistency`: mean NEES
against Bar-Shalom's 95 % band of the trials' count, the share of sample times whose trial-averaged NEES lies in it,
1- and 2-sigma coverage per state and the log-likelihood of the truth, beside the SMAPE. Every estimator is scored
with its variances (the diagonal of its covariance: the EKF and the particle filter report no more), so NEES and
likelihood ignore correlations for all alike. :func:`score_cases` does the same on the generalisation cases (the
EKF tuned to each case's noise), :func:`uncertainty_row` scores estimates already run (the robustness benchmark's,
``kklcasadi robustness --consistency``), :func:`uncertainty_table` writes the markdown table.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Optional, Sequence

import numpy as np

from .. import metrics
from ..consistency import SIGMA_LEVELS, Consistency, consistency
from ..plant.simulate import TrajectoryBatch
from ..plant.systems import System
from ..validation import Text, error
from .compiled import CompiledRecord, Compiler
from .generalisation import Case, Settings, case_ekf
from .protocol import Cell, read_cells
from .trialcache import TrialCache

if TYPE_CHECKING:
    from ..observer.kkl import KKLObserver

__all__ = ["UncertainEstimator", "UncertaintyRow", "observer_uncertainty", "RecordedObserver", "filter_uncertainty",
           "score_uncertainty", "score_cases", "uncertainty_row", "uncertainty_table", "uncertainty_record"]

#: The compiler of :func:`observer_uncertainty` by default (the evaluation's cache and flags).
_COMPILER = Compiler()
#: ``(t (N,), y (M, N, ny), u (M, N, nu)) -> (xhat (M, N, nx), var (M, N, nx))``: estimates and their variances.
UncertainEstimator = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class UncertaintyRow:
    """One estimator on one cell: its mean SMAPE (%) and the consistency of its covariance."""

    label: str
    system: str
    cell: str
    smape: float
    consistency: Consistency
    escaped: int = 0


def observer_uncertainty(observer: KKLObserver, *, compiler: Optional[Compiler] = _COMPILER,
                         n_threads: Optional[int] = None) -> UncertainEstimator:
    """An observer with a covariance head as an :data:`UncertainEstimator` (compiled, bitwise its ``simulate``)."""
    return RecordedObserver(observer, compiler=compiler, n_threads=n_threads).uncertain


class RecordedObserver:
    """An observer with a covariance head, both a protocol estimator (``(t, y, u) -> xhat``) and an
    :data:`UncertainEstimator` (:meth:`uncertain`), which keeps each call's results by its inputs: the SMAPE and
    the consistency of one cell come from one run (``kklcasadi evaluate --consistency``).

    Attributes
    ----------
    record : CompiledRecord
        The compiled trajectories (what :func:`kklcasadi.evaluation.compiled.precompile` takes).
    """

    def __init__(self, observer: KKLObserver, *, compiler: Optional[Compiler] = _COMPILER,
                 n_threads: Optional[int] = None) -> None:
        if observer.covariance is None:
            raise ValueError(f"observer: expected a model with a covariance head (architecture.covariance), received "
                             f"{observer!r} without one. Fit one with benchmarks/covariance_heads.py.")
        self.record = CompiledRecord(observer, compiler=compiler, n_threads=n_threads)
        self._kept: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def _run(self, t: np.ndarray, y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xhat, _, cov = self.record.record(t, y, u)
        return xhat, np.diagonal(cov, axis1=-2, axis2=-1)

    def uncertain(self, t: np.ndarray, y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(xhat, var)`` of M trials, computed once per distinct ``(t, y, u)``."""
        key = hashlib.sha256(b"".join(np.ascontiguousarray(a, dtype=float).tobytes() + str(np.shape(a)).encode()
                                      for a in (t, y, u))).digest()
        if key not in self._kept:
            self._kept[key] = self._run(t, y, u)
        return self._kept[key]

    def __call__(self, t: np.ndarray, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.uncertain(t, y, u)[0]


def filter_uncertainty(estimator: Any) -> UncertainEstimator:
    """An EKF or a particle filter (anything whose ``simulate(t, y, u)`` gives ``xhat`` and ``var``)."""

    def estimate(t: np.ndarray, y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        est = estimator.simulate(t, y, u)
        return np.asarray(est.xhat), np.asarray(est.var)

    return estimate


def score_uncertainty(estimators: Sequence[tuple[str, UncertainEstimator]], system: System, cells: Sequence[Cell],
                      *, trials: Optional[TrialCache] = None) -> list[UncertaintyRow]:
    """Run every estimator on every cell's trials (those that did not escape) and score its covariance.

    Parameters
    ----------
    estimators : sequence of (str, UncertainEstimator)
        Row labels and estimators.
    system : System
    cells : sequence of Cell
    trials : TrialCache, optional
        Where the cells' trials come from (default: simulated for this call).

    Returns
    -------
    list of UncertaintyRow
        Estimator by estimator, cell by cell; the whole horizon is scored (``t_settle`` 0), as the SMAPE.
    """
    batches = read_cells(system, cells, TrialCache(None) if trials is None else trials)
    return [_row(label, estimator, system, cell.label, batch) for label, estimator in estimators
            for cell, batch in zip(cells, batches)]


def score_cases(observers: Sequence[tuple[str, KKLObserver]], case_list: Sequence[Case], settings: Settings, *,
                trials: Optional[TrialCache] = None, compiler: Optional[Compiler] = _COMPILER,
                n_threads: Optional[int] = None) -> list[UncertaintyRow]:
    """The generalisation cases (:mod:`kklcasadi.evaluation.generalisation`): each observer's covariance head and
    the EKF's own covariance (the EKF tuned to the case's noise, :func:`~kklcasadi.evaluation.generalisation.case_ekf`,
    as the benchmark runs it), case by case on the same trials; rows labelled with the case (``family regime
    noise``)."""
    if not observers:
        raise error("observers", "at least one (label, observer) with a covariance head", Text("none"))
    plant = observers[0][1].system
    trials = TrialCache(None) if trials is None else trials
    runners = [(label, observer_uncertainty(obs, compiler=compiler, n_threads=n_threads)) for label, obs in observers]
    rows = []
    for case in case_list:
        batch = trials.trials(plant, case.cell(settings))
        ekf = filter_uncertainty(case_ekf(plant, case.noise, settings.dt))
        rows += [_row(label, estimator, plant, case.label, batch) for label, estimator in [*runners, ("EKF", ekf)]]
    return rows


def _row(label: str, estimator: UncertainEstimator, system: System, cell: str,
         batch: TrajectoryBatch) -> UncertaintyRow:
    """One estimator on one batch of trials (those that did not escape)."""
    ok = batch.ok
    xhat, var = estimator(batch.t, batch.y[ok], batch.u[ok])
    return uncertainty_row(label, system, cell, batch.t, batch.x[ok], xhat, var, escaped=int((~ok).sum()))


def uncertainty_row(label: str, system: System, cell: str, t: np.ndarray, x: np.ndarray, xhat: np.ndarray,
                    var: np.ndarray, *, smape: Optional[np.ndarray] = None, escaped: int = 0) -> UncertaintyRow:
    """Score one estimator's estimates and variances on the trials of one cell (the whole horizon).

    Parameters
    ----------
    label, cell : str
        The row's estimator and cell (or case).
    system : System
    t : numpy.ndarray, shape (N,)
    x, xhat, var : numpy.ndarray, shape (M, N, nx)
        The true states, the estimates and their variances.
    smape : numpy.ndarray, shape (M,), optional
        The trials' SMAPE as the caller scored them (default :func:`kklcasadi.metrics.smape` of ``x``, ``xhat``).
    escaped : int
        Trials left out because the plant escaped.
    """
    value = metrics.smape(x, xhat) if smape is None else smape
    return UncertaintyRow(label, system.name, cell, float(np.mean(value)),
                          consistency(x, xhat, var, t=t, angles=system.angle_states), escaped)


def uncertainty_table(rows: Sequence[UncertaintyRow]) -> str:
    """Markdown: per estimator and cell the SMAPE, the mean NEES with its band, the share of times in the band,
    1- and 2-sigma coverage per state (%) and the mean log-likelihood of the truth."""
    levels = " / ".join(f"{k:g}" for k in SIGMA_LEVELS)
    head = ["system", "cell", "estimator", "SMAPE %", "mean NEES (95 % band)", "times in band %",
            f"coverage {levels} sigma, per state %", "log-lik."]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        c = r.consistency
        cover = "; ".join(" / ".join(f"{100 * c.coverage[j][i]:.1f}" for j in range(len(SIGMA_LEVELS)))
                          for i in range(c.nx))
        lines.append(f"| {r.system} | {r.cell} | {r.label} | {r.smape:.2f} | {c.nees:.3g} ({c.nees_band[0]:.3g}-"
                     f"{c.nees_band[1]:.3g}) | {100 * c.in_band:.1f} | {cover} | {c.log_likelihood:.3g} |")
    return "\n".join(lines)


def uncertainty_record(rows: Sequence[UncertaintyRow]) -> list[dict]:
    """The rows as JSON-able records."""
    return [{"label": r.label, "system": r.system, "cell": r.cell, "smape": r.smape, "escaped": r.escaped,
             **r.consistency.to_json()} for r in rows]
