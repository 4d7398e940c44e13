"""The generalisation benchmark of docs/protocol.md "Generalisation": inputs and noise an observer was not fit on.

A *case* is an input family, its parameter ranges (a regime) and a noise level. The benchmark's
four families keep their docs/protocol.md cells (:class:`~kklcasadi.evaluation.protocol.Protocol`
with the case's noise level: at 0.1 they are the protocol's own ``id`` and ``ood`` cells); the
held-out families (a swept sine, random steps, a saturated PD controller around a stepping set
point, :data:`kklcasadi.plant.signals.HELD_OUT_RANGES`) are :class:`FamilyCell` s. Every cell goes
through the trial cache, and every estimator sees the same trials.

Each case is classified against the model's card (:func:`fit_families`): ``fit`` (the family, with
ranges inside those the model was fit on), ``ood`` (a fitted family outside its fitted ranges) or
``held out`` (a family the model was not fit on). :func:`run` scores the observer, the EKF (its
``Q`` and ``R`` matched to the case's noise) and optionally the particle filter on every case, with
the observer's domain monitor per sample; :func:`markdown` and :func:`to_json` report it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional, Sequence

import casadi as ca
import numpy as np
from tqdm.auto import tqdm

from .. import metrics
from ..estimators.ekf import EKF
from ..estimators.pf import ParticleFilter
from ..observer.kkl import KKLObserver
from ..plant import signals as sig
from ..plant.simulate import TrajectoryBatch, simulate_batch
from ..plant.systems import System
from ..validation import Text, error, one_of, positive_int
from .compiled import CompiledEstimator, Compiler, _c_name, ekf_estimator
from .protocol import Protocol
from .trialcache import TrialCache

__all__ = ["Case", "FamilyCell", "Settings", "CaseResult", "Report", "cases", "fit_families", "category",
           "run", "markdown", "to_json", "monitor_summary", "MonitoredObserver", "NOISE_LEVELS", "FAMILY_STREAMS",
           "CATEGORIES", "BAD_RATIO", "FLAG_SHARE", "PF_SUBSTEPS"]

#: Noise levels of the benchmark: process and measurement noise std (docs/protocol.md: 0.1).
NOISE_LEVELS = (0.05, 0.1, 0.2)
#: The random stream of each held-out family: its trials draw from ``[seed, stream]`` (docs/protocol.md).
FAMILY_STREAMS = {"chirp": 101, "random": 102, "feedback": 103}
#: How a case relates to what the model was fit on.
CATEGORIES = ("fit", "ood", "held out", "unknown")
#: A trial is bad when the observer's SMAPE exceeds this multiple of the EKF's on that trial.
BAD_RATIO = 1.5
#: A trial is flagged when at least this share of its samples after ``t_settle`` is out of domain.
FLAG_SHARE = 0.5
#: RK4 steps per interval of the particle filter (one step diverges on FitzHugh-Nagumo's stiff corners).
PF_SUBSTEPS = {"fhn": 4, "rossler": 4}


@dataclass(frozen=True)
class Settings:
    """What every case shares: trials, horizon, sample period, seed, integrator, settle time."""

    n_trials: int = 100
    T: float = 50.0
    dt: float = 0.05
    seed: int = 2026
    method: str = "cvodes"
    t_settle: float = 5.0

    def __post_init__(self) -> None:
        positive_int(self.n_trials, "n_trials")


@dataclass(frozen=True)
class Case:
    """An input family in one regime at one noise level.

    Attributes
    ----------
    family : str
        One of :data:`kklcasadi.plant.signals.FAMILIES`.
    regime : {"id", "ood", "held_out"}
        ``id``/``ood``: the docs/protocol.md ranges (``zero``: ``id`` only); ``held_out``: the
        held-out families' ranges.
    noise : float
        Process and measurement noise std.
    """

    family: str
    regime: str
    noise: float

    def __post_init__(self) -> None:
        one_of(self.family, "family", sig.FAMILIES)
        allowed = ("held_out",) if self.family in sig.HELD_OUT_RANGES else ("id",) if self.family == "zero" \
            else ("id", "ood")
        one_of(self.regime, f"regime of family {self.family!r}", allowed)
        if not (isinstance(self.noise, (int, float)) and math.isfinite(self.noise) and self.noise >= 0):
            raise error("noise", "a noise std >= 0", self.noise)

    @property
    def ranges(self) -> dict:
        """The family's parameter ranges in this regime (``{}`` for zero)."""
        return sig.family_ranges(self.family, self.regime)

    def cell(self, settings: Settings) -> Any:
        """The case's trials as a trial-cache cell (a protocol cell for the benchmark's families)."""
        if self.family in sig.HELD_OUT_RANGES:
            return FamilyCell(self.family, settings, self.noise)
        protocol = Protocol(n_trials=settings.n_trials, T=settings.T, dt=settings.dt, process_std=self.noise,
                            measurement_std=self.noise, seed=settings.seed, regime=self.regime,
                            method=settings.method, t_settle=settings.t_settle)
        return protocol.cell(self.family)

    @property
    def label(self) -> str:
        return f"{self.family} {self.regime} {self.noise:g}"


@dataclass(frozen=True)
class FamilyCell:
    """The trials of a held-out family at one noise level (a :class:`~kklcasadi.evaluation.trialcache.Cell`).

    Initial states: the protocol's Latin hypercube over X0 (``seed``); inputs: drawn in trial order
    from ``default_rng([seed, FAMILY_STREAMS[family]])``; noise: trial ``i`` from
    ``SeedSequence([seed, FAMILY_STREAMS[family]]).spawn(n_trials)[i]``, at std ``noise`` on the
    process and the measurement. ``feedback`` runs closed loop, its set points relative to
    :func:`output_range`.
    """

    family: str
    settings: Settings
    noise: float

    @property
    def label(self) -> str:
        return f"{self.family}-held_out-{self.noise:g}"

    def describe(self) -> dict:
        s = self.settings
        return {"generalisation": {"family": self.family, "ranges": {k: list(v) for k, v in self.ranges.items()},
                                   "stream": FAMILY_STREAMS[self.family], "noise": self.noise,
                                   "n_trials": s.n_trials, "T": s.T, "dt": s.dt, "seed": s.seed, "method": s.method}}

    @property
    def ranges(self) -> dict:
        return sig.family_ranges(self.family, "held_out")

    def shape(self) -> tuple[int, int]:
        return self.settings.n_trials, round(self.settings.T / self.settings.dt)

    def inputs(self, system: System) -> list:
        """The per-trial inputs (signals, or output-feedback laws for ``feedback``)."""
        s = self.settings
        rng = np.random.default_rng([s.seed, FAMILY_STREAMS[self.family]])
        span = output_range(system) if self.family == "feedback" else None
        return [sig.draw(self.family, rng, self.ranges, nu=system.nu, horizon=s.T, output_range=span)
                for _ in range(s.n_trials)]

    def simulate(self, system: System) -> TrajectoryBatch:
        s = self.settings
        x0 = system.sample_box(s.n_trials, s.seed)
        seeds = np.random.SeedSequence([s.seed, FAMILY_STREAMS[self.family]]).spawn(s.n_trials)
        return simulate_batch(system, x0, self.inputs(system), s.T, s.dt, process_std=self.noise,
                              measurement_std=self.noise, seed=seeds, method=s.method)


def output_range(system: System) -> tuple[np.ndarray, np.ndarray]:
    """The low and high ends of ``h`` over the X0 box (1024 Latin-hypercube points, seed 0), (ny,) each."""
    y = system.h_batch(system.sample_box(1024, 0))
    return y.min(axis=0), y.max(axis=0)


def cases(families: Sequence[str] = sig.FAMILIES, noises: Sequence[float] = NOISE_LEVELS,
          regimes: Sequence[str] = ("id", "ood", "held_out")) -> list[Case]:
    """The grid: every family in each of its regimes among ``regimes``, at every noise level."""
    out = []
    for family in families:
        for regime in regimes:
            if (regime == "held_out") == (family in sig.HELD_OUT_RANGES) and not (family == "zero" and regime == "ood"):
                out.extend(Case(family, regime, float(noise)) for noise in noises)
    return out


# ---------------------------------------------------------------------- what a model was fit on
def fit_families(observer: KKLObserver) -> Optional[dict]:
    """The input families (with their parameter ranges) the observer's maps were fit on.

    The card's ``fit_families`` where it records them; else, for a card whose training record
    holds the operational runs (``training.rollouts``: ``kinds`` drawn from ``regime``), those
    families in that regime; else None.

    Returns
    -------
    dict or None
        ``{family: {parameter: (lo, hi)}}``.
    """
    recorded = observer.model.spec.fit_families
    if recorded is not None:
        return {k: {p: tuple(b) for p, b in v.items()} for k, v in recorded.items()}
    rollouts = observer.model.card.get("training", {}).get("rollouts")
    if isinstance(rollouts, Mapping) and "kinds" in rollouts and "regime" in rollouts:
        return {kind: sig.family_ranges(kind, rollouts["regime"]) for kind in rollouts["kinds"]}
    return None


def category(case: Case, fitted: Optional[Mapping[str, Mapping[str, Sequence[float]]]]) -> str:
    """``fit``, ``ood``, ``held out`` or ``unknown`` (no record): the case against ``fitted``."""
    if fitted is None:
        return "unknown"
    if case.family not in fitted:
        return "held out"
    inside = all(name in fitted[case.family] and fitted[case.family][name][0] <= lo
                 and hi <= fitted[case.family][name][1] for name, (lo, hi) in case.ranges.items())
    return "fit" if inside else "ood"
