"""The validation score of a design search: trials of input families the configuration does not fit on, with their
own seed, and the observer's mean SMAPE over the EKF's on them."""

from __future__ import annotations

from dataclasses import dataclass, is_dataclass
from typing import Any, Optional, Sequence

import numpy as np

from ... import metrics
from ...estimators.ekf import EKF
from ...observer.kkl import KKLObserver
from ...plant import signals as sig
from ...plant.simulate import TrajectoryBatch, simulate_batch
from ...plant.systems import System
from ...validation import Text, error, positive_int
from ..compiled import Compiler, ekf_estimator, observer_estimator
from ..trialcache import TrialCache
from .space import field_names

__all__ = ["VALIDATION_SEED", "VALIDATION_FAMILIES", "ValidationCell", "validation_cells", "fitted_families",
           "Validation", "score"]

#: Seed of the validation trials (the protocol's scored trials use 2026; training runs their own).
VALIDATION_SEED = 7

#: The validation families: ``(label, signal kind, regime, parameter ranges)``. ``chirp`` and
#: ``random`` are families no default configuration fits on; the ``ood`` ranges of docs/protocol.md
#: are ranges none fits on. The families a configuration fits on are left out
#: (:func:`fitted_families`).
VALIDATION_FAMILIES: tuple = (
    ("chirp", "chirp", "", {"amplitude": (0.1, 1.0), "omega0": (0.2, 1.0), "omega1": (2.0, 5.0)}),
    ("random", "random", "", {"amplitude": (0.1, 1.0), "hold": (0.5, 3.0)}),
    ("constant-ood", "constant", "ood", sig.RANGES["ood"]["constant"]),
    ("sinusoid-ood", "sinusoid", "ood", sig.RANGES["ood"]["sinusoid"]),
    ("square-ood", "square", "ood", sig.RANGES["ood"]["square"]),
)


@dataclass(frozen=True)
class ValidationCell:
    """Validation trials of one input family: initial states from a Latin hypercube over the X0 box,
    the family's parameters drawn per trial, process and measurement noise, all from ``seed``.

    A cell of :class:`~kklcasadi.evaluation.trialcache.TrialCache` (``describe``, ``label``,
    ``shape``, ``simulate``).
    """

    name: str
    kind: str
    ranges: tuple
    n_trials: int = 20
    T: float = 50.0
    dt: float = 0.05
    process_std: float = 0.1
    measurement_std: float = 0.1
    seed: int = VALIDATION_SEED
    index: int = 0

    @property
    def label(self) -> str:
        return f"tune-{self.name}-{self.seed}"

    def describe(self) -> dict:
        return {"validation": {"name": self.name, "kind": self.kind, "ranges": [list(r) for r in self.ranges],
                               "n_trials": self.n_trials, "T": self.T, "dt": self.dt,
                               "process_std": self.process_std, "measurement_std": self.measurement_std,
                               "seed": self.seed, "index": self.index}}

    def shape(self) -> tuple[int, int]:
        return self.n_trials, round(self.T / self.dt)

    def signals(self, nu: int) -> list[sig.Signal]:
        """The per-trial inputs (seeded by ``(seed, index)``)."""
        rng = np.random.default_rng([self.seed, 100 + self.index])
        out = []
        for _ in range(self.n_trials):
            draw = {name: (rng.uniform(lo, hi, size=nu) if name in ("amplitude", "value") else rng.uniform(lo, hi))
                    for name, lo, hi in self.ranges}
            if self.kind in ("sinusoid", "square", "chirp"):
                draw["phase"] = rng.uniform(0.0, 2.0 * np.pi)
            if self.kind == "chirp":
                draw["duration"] = self.T
            if self.kind == "random":
                draw.update(seed=int(rng.integers(2 ** 31)), horizon=self.T)
            out.append(sig.make(self.kind, **draw))
        return out

    def simulate(self, system: System) -> TrajectoryBatch:
        x0 = system.sample_box(self.n_trials, np.random.default_rng([self.seed, 100 + self.index, 1]))
        seeds = np.random.SeedSequence([self.seed, 100 + self.index]).spawn(self.n_trials)
        inputs = [sig.in_box(u, system.u_box) for u in self.signals(system.nu)]
        return simulate_batch(system, x0, inputs, self.T, self.dt, process_std=self.process_std,
                              measurement_std=self.measurement_std, seed=seeds)


def fitted_families(config: Any) -> set[tuple[str, str]]:
    """The ``(kind, regime)`` pairs a configuration fits on: every ``kinds`` field of its dataclass
    tree, with the ``regime`` beside it (``"train"`` where there is none; ``train`` is ``id``, and
    ``wide``, the hull of the ``id`` and ``ood`` ranges, both)."""
    found: set[tuple[str, str]] = set()
    if not is_dataclass(config):
        return found
    names = field_names(config)
    if "kinds" in names:
        regime = getattr(config, "regime", "train")
        regimes = {"train": ("id",), "wide": ("id", "ood")}.get(regime, (regime,))
        found |= {(kind, r) for kind in config.kinds for r in regimes}
    for name in names:
        found |= fitted_families(getattr(config, name))
    return found


def validation_cells(config: Any, *, n_trials: int = 20, seed: int = VALIDATION_SEED, T: float = 50.0,
                     dt: float = 0.05) -> list[ValidationCell]:
    """The validation cells of a configuration: :data:`VALIDATION_FAMILIES` less those it fits on.

    A family in the ``ood`` regime is left out where the configuration fits on that kind in the
    ``ood`` regime; ``chirp`` and ``random`` where it fits on them at all. (When
    ``kklcasadi.evaluation.generalisation`` lands, its held-out cells belong here.)
    """
    fitted = fitted_families(config)
    fitted_kinds = {kind for kind, _ in fitted}
    cells = []
    for index, (name, kind, regime, ranges) in enumerate(VALIDATION_FAMILIES):
        if (kind, regime) in fitted or (not regime and kind in fitted_kinds):
            continue
        cells.append(ValidationCell(name, kind, tuple((p, *r) for p, r in ranges.items()), positive_int(
            n_trials, "n_trials"), T, dt, seed=seed, index=index))
    if not cells:
        raise error("config", "a configuration that leaves some validation family out of its fitting data",
                    Text(f"fits on {sorted(fitted)}"), "Add a family to VALIDATION_FAMILIES that it does not fit on.")
    return cells


@dataclass(frozen=True, eq=False)
class Validation:
    """The validation trials of a study and the EKF's SMAPE on them (per cell, mean over trials)."""

    system: System
    cells: tuple
    ekf: dict
    trials: TrialCache
    compiler: Optional[Compiler]

    @classmethod
    def build(cls, system: System, cells: Sequence[ValidationCell], *, trials: Optional[TrialCache] = None,
              compiler: Optional[Compiler] = None) -> Validation:
        """Simulate (or read) the cells and score the EKF (docs/protocol.md settings) on them.

        ``compiler``: how the EKF and the observers are compiled (default ``Compiler()``, gcc).
        """
        trials = TrialCache(None) if trials is None else trials
        compiler = Compiler() if compiler is None else compiler
        ekf = ekf_estimator(EKF(system, cells[0].dt), compiler=compiler, n_threads=1)
        scores = {cell.name: _mean_smape(ekf, trials.trials(system, cell)) for cell in cells}
        return cls(system, tuple(cells), scores, trials, compiler)

    def describe(self) -> dict:
        """What the score is and what it is measured on (for the study and the card)."""
        return {"score": "mean over the cells of the observer's mean SMAPE over the EKF's on the same trials",
                "cells": [cell.describe()["validation"] for cell in self.cells], "ekf_smape": self.ekf}


def _mean_smape(estimator: Any, batch: TrajectoryBatch) -> float:
    ok = batch.ok
    xhat = np.asarray(estimator(batch.t, batch.y[ok], batch.u[ok]), dtype=float)
    return float(np.mean(metrics.smape(batch.x[ok], xhat)))


def score(observer: KKLObserver, validation: Validation) -> tuple[float, dict]:
    """The validation score of an observer and its per-cell SMAPE.

    Returns
    -------
    value : float
        Mean over the cells of ``SMAPE(observer) / SMAPE(EKF)`` (lower is better; 1 is the EKF).
    cells : dict
        ``{cell name: observer mean SMAPE %}``.
    """
    estimator = observer_estimator(observer, compiler=validation.compiler, n_threads=1)
    cells = {cell.name: _mean_smape(estimator, validation.trials.trials(validation.system, cell))
             for cell in validation.cells}
    return float(np.mean([cells[name] / validation.ekf[name] for name in cells])), cells
