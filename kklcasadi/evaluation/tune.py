"""Observer design searches on Optuna (``kklcasadi tune``): the search space, the validation score,
the study, and the best trial as a model directory.

A study searches one method's training configuration (:func:`kklcasadi.train.default_config`)
against a validation score measured on trials that no training and no benchmark uses: input
families and parameter ranges the configuration does not fit on (:func:`validation_cells`),
simulated with their own seed, scored as the observer's mean SMAPE over the EKF's on the same
trials (:func:`score`). The engine is Optuna, with nothing of our own around it:

* the storage is an Optuna RDB storage: a SQLite file by default, a PostgreSQL URL to join one
  study from several machines (every ``kklcasadi tune`` started with the same ``--study`` and
  ``--storage`` is one more worker);
* a worker killed mid-trial stops beating its RDB heartbeat; after the grace period the next
  worker to start a trial marks it failed and Optuna's ``RetryHeartbeatStaleTrialCallback``
  queues it again with the same parameters, which that worker then runs;
* the study stops at ``n_trials`` complete trials (``MaxTrialsCallback``), so running ``tune``
  again resumes it, and a larger ``n_trials`` extends it;
* TPE samples the space (multivariate, constant liar for parallel workers).

The search space of every method is one entry of :data:`SPACES`: dimensions that name the
configuration's dataclass fields by dotted path (``"decoder.loop.epochs"``), so a renamed or new
field is one line there. Budget dimensions (:class:`Budget`) search up to a cap, default the
method's own default budget; the recipe's baseline is trained at the caps.

Optuna (``pip install 'kklcasadi[tune]'``) and torch are imported inside the functions that use
them.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
import time
import warnings
from dataclasses import dataclass, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import numpy as np

from .. import metrics
from ..estimators.ekf import EKF
from ..model import variants
from ..model.files import Search, load_model, save_model
from ..observer.kkl import KKLObserver, load_observer
from ..plant import signals as sig
from ..plant.simulate import TrajectoryBatch, simulate_batch
from ..plant.systems import System
from ..validation import Text, error, positive_int
from .compiled import Compiler, ekf_estimator, observer_estimator
from .trialcache import TrialCache

__all__ = ["Float", "Int", "Filters", "Layers", "MaybeRate", "Budget", "Space", "SPACES", "search_space",
           "ValidationCell", "validation_cells", "fitted_families", "Validation", "score", "TuneResult", "tune",
           "export_best", "summary_table", "search_plot", "storage_url", "VALIDATION_SEED", "VALIDATION_FAMILIES"]

PathLike = Union[str, os.PathLike]

#: Seed of the validation trials (the protocol's scored trials use 2026; training runs their own).
VALIDATION_SEED = 7
#: How often a killed trial is queued again (Optuna's ``RetryHeartbeatStaleTrialCallback(max_retry)``).
MAX_RETRY = 2
#: Directory names under the study's ``--out``.
TRIALS_DIR, BEST_DIR, BASELINE_DIR = "trials", "best", "baseline"


def _install_hint() -> str:
    return "pip install 'kklcasadi[tune]'"


def _optuna() -> Any:
    try:
        import optuna
    except ImportError:
        raise ModuleNotFoundError(f"kklcasadi tune needs optuna, which is not installed; install the tune extra: "
                                  f"{_install_hint()}", name="optuna") from None
    return optuna


# -- the search space -------------------------------------------------------------------------------


def _paths(paths: Union[str, Sequence[str]]) -> tuple[str, ...]:
    return (paths,) if isinstance(paths, str) else tuple(paths)


@dataclass(frozen=True)
class Float:
    """A real field (or several fields set to one value), uniform or log-uniform on ``[low, high]``."""

    name: str
    paths: Union[str, tuple]
    low: float
    high: float
    log: bool = False

    def suggest(self, trial: Any) -> float:
        return trial.suggest_float(self.name, self.low, self.high, log=self.log)

    def describe(self) -> dict:
        return {"name": self.name, "kind": "float", "paths": list(_paths(self.paths)), "low": self.low,
                "high": self.high, "log": self.log}


@dataclass(frozen=True)
class Int:
    """An integer field (or several), uniform or log-uniform on ``[low, high]``."""

    name: str
    paths: Union[str, tuple]
    low: int
    high: int
    log: bool = False

    def suggest(self, trial: Any) -> int:
        return trial.suggest_int(self.name, self.low, self.high, log=self.log)

    def describe(self) -> dict:
        return {"name": self.name, "kind": "int", "paths": list(_paths(self.paths)), "low": self.low,
                "high": self.high, "log": self.log}


@dataclass(frozen=True)
class Filters:
    """A tuple of filter rates (rad/s): ``count`` of them log-spaced from ``slow`` to ``slow * span``.

    Optuna parameters ``NAME_n``, then (``n >= 1``) ``NAME_slow`` and (``n >= 2``) ``NAME_span``.
    """

    name: str
    paths: Union[str, tuple]
    count: tuple
    slow: tuple
    span: tuple

    def suggest(self, trial: Any) -> tuple:
        n = trial.suggest_int(f"{self.name}_n", *self.count)
        if n == 0:
            return ()
        slow = trial.suggest_float(f"{self.name}_slow", *self.slow, log=True)
        if n == 1:
            return (slow,)
        span = trial.suggest_float(f"{self.name}_span", *self.span, log=True)
        return tuple(float(v) for v in np.geomspace(slow, slow * span, n))

    def describe(self) -> dict:
        return {"name": self.name, "kind": "filters", "paths": list(_paths(self.paths)), "count": list(self.count),
                "slow": list(self.slow), "span": list(self.span)}


@dataclass(frozen=True)
class Layers:
    """Hidden layer widths: ``depth`` layers of one ``width`` (``NAME_width`` log-uniform, ``NAME_depth``)."""

    name: str
    paths: Union[str, tuple]
    width: tuple
    depth: tuple

    def suggest(self, trial: Any) -> tuple:
        width = trial.suggest_int(f"{self.name}_width", *self.width, log=True)
        return (width,) * trial.suggest_int(f"{self.name}_depth", *self.depth)

    def describe(self) -> dict:
        return {"name": self.name, "kind": "layers", "paths": list(_paths(self.paths)), "width": list(self.width),
                "depth": list(self.depth)}


@dataclass(frozen=True)
class MaybeRate:
    """None or a rate log-uniform on ``[low, high]`` (``NAME_on``, then ``NAME_rate``)."""

    name: str
    paths: Union[str, tuple]
    low: float
    high: float

    def suggest(self, trial: Any) -> Optional[float]:
        if not trial.suggest_categorical(f"{self.name}_on", [True, False]):
            return None
        return trial.suggest_float(f"{self.name}_rate", self.low, self.high, log=True)

    def describe(self) -> dict:
        return {"name": self.name, "kind": "maybe_rate", "paths": list(_paths(self.paths)), "low": self.low,
                "high": self.high}


@dataclass(frozen=True)
class Budget:
    """A budget (runs, epochs): an integer from ``fraction`` of the cap up to the cap, log-uniform.

    The cap is the configuration's own value at the first path unless :func:`search_space` is given
    one; the baseline is trained at the cap.
    """

    name: str
    paths: Union[str, tuple]
    fraction: float = 0.5

    def resolve(self, cap: int) -> Int:
        cap = positive_int(cap, f"{self.name} budget")
        return Int(self.name, self.paths, max(1, math.ceil(self.fraction * cap)), cap, log=True)


#: The search space of every method that trains, by the dotted names of its configuration's fields.
#: ``bank``: the output and input filters (counts and rates), the clock, the decoder's width and
#: depth, the training noise, the learning rate and the budget (runs and epochs); the others: what
#: their configurations expose. The recipe's values lie inside every range.
SPACES: dict[str, tuple] = {
    "bank": (
        Filters("y_filters", "y_poles", count=(3, 12), slow=(0.05, 1.0), span=(5.0, 500.0)),
        Filters("u_filters", "u_poles", count=(0, 4), slow=(0.1, 1.0), span=(2.0, 100.0)),
        MaybeRate("clock", "clock", 0.05, 1.0),
        Layers("decoder", "decoder.hidden", width=(32, 384), depth=(1, 4)),
        Float("noise", ("measurement_std", "process_std"), 0.05, 0.2, log=True),
        Float("lr", "decoder.loop.lr", 3e-4, 3e-3, log=True),
        Budget("runs", "rollouts.n_traj"),
        Budget("epochs", "decoder.loop.epochs"),
    ),
    "autonomous": (
        Int("width", "width", 32, 256, log=True),
        Int("depth", "depth", 2, 4),
        Float("lr", ("encoder.lr", "decoder.lr"), 3e-4, 5e-3, log=True),
        Float("noise", "measurement_std", 0.0, 0.2),
        Budget("runs", "n_traj"),
        Budget("epochs", ("encoder.epochs", "decoder.epochs")),
    ),
    "curriculum": (
        Float("lr", "loop.lr", 3e-5, 1e-3, log=True),
        Float("nu_pde", "nu_pde", 0.01, 1.0, log=True),
        Budget("runs", "n_traj"),
        Budget("epochs", "loop.epochs"),
    ),
    **{method: (
        Int("hidden", "hidden", 16, 128, log=True),
        Int("proj", "proj", 4, 32, log=True),
        Layers("gain", "gain_hidden", width=(16, 128), depth=(1, 3)),
        Int("window", "data.window", 10, 100, log=True),
        Float("lr", "loop.lr", 3e-4, 3e-3, log=True),
        Budget("runs", "data.n_traj"),
        Budget("epochs", "loop.epochs"),
    ) for method in ("obs", "obs_stream")},
    **{method: (
        Int("hidden", "hidden", 16, 128, log=True),
        Int("rank", "rank", 1, 8),
        Layers("backbone", "backbone", width=(16, 128), depth=(1, 3)),
        Float("nu_pde", "nu_pde", 0.01, 1.0, log=True),
        Int("window", "data.window", 10, 100, log=True),
        Float("lr", "loop.lr", 3e-4, 3e-3, log=True),
        Budget("runs", "data.n_traj"),
        Budget("epochs", "loop.epochs"),
    ) for method in ("dyn", "dyn_stream")},
}


def _field_names(config: Any) -> list[str]:
    return [f.name for f in fields(config)] if is_dataclass(config) else []


def _get(config: Any, path: str) -> Any:
    value = config
    for i, part in enumerate(path.split(".")):
        if part not in _field_names(value):
            raise error("space", f"a field {part!r} of {type(value).__name__} for {path!r} (fields: "
                        f"{_field_names(value)})", Text(".".join(path.split(".")[:i + 1])),
                        "The configuration class changed: update kklcasadi.evaluation.tune.SPACES.")
        value = getattr(value, part)
    return value


def _set(config: Any, path: str, value: Any) -> Any:
    _get(config, path)
    head, _, rest = path.partition(".")
    return replace(config, **{head: _set(getattr(config, head), rest, value) if rest else value})


@dataclass(frozen=True)
class Space:
    """One method's search space over a base configuration.

    Attributes
    ----------
    method : str
    base : dataclass
        The configuration the dimensions change (the method's default, with the caller's changes).
    dims : tuple
        :class:`Float`, :class:`Int`, :class:`Filters`, :class:`Layers`, :class:`MaybeRate` (budget
        dimensions resolved to :class:`Int` with their caps).
    budget : tuple of str
        Names of the budget dimensions (set to their caps in :meth:`baseline`).
    """

    method: str
    base: Any
    dims: tuple
    budget: tuple

    def __post_init__(self) -> None:
        for dim in self.dims:
            for path in _paths(dim.paths):
                _get(self.base, path)

    def suggest(self, trial: Any) -> Any:
        """The configuration of an Optuna trial (or ``optuna.trial.FixedTrial(params)`` to replay one)."""
        config = self.base
        for dim in self.dims:
            value = dim.suggest(trial)
            for path in _paths(dim.paths):
                config = _set(config, path, value)
        return config

    def baseline(self) -> Any:
        """The base configuration with every budget at its cap: the recipe, at the study's budget."""
        config = self.base
        for dim in self.dims:
            if dim.name in self.budget:
                for path in _paths(dim.paths):
                    config = _set(config, path, dim.high)
        return config

    def describe(self) -> list[dict]:
        """One JSON entry per dimension (for the study and the card)."""
        return [{**dim.describe(), "budget": dim.name in self.budget} for dim in self.dims]


def search_space(method: str, config: Any = None, *, system: str = "", caps: Optional[dict] = None) -> Space:
    """The search space of ``method`` (:data:`SPACES`) over ``config``.

    Parameters
    ----------
    method : str
        A method with an entry in :data:`SPACES`.
    config : dataclass, optional
        The base configuration; default ``kklcasadi.train.default_config(system, method)``.
    system : str
        The plant's name, for the default configuration.
    caps : dict, optional
        Budget caps by dimension name (``{"runs": 500, "epochs": 15}``); default the configuration's
        own values.
    """
    if method not in SPACES:
        raise error("method", f"one of {sorted(SPACES)} (a method with a search space)", method)
    if config is None:
        from ..train import default_config

        config = default_config(system, method)
    caps = dict(caps or {})
    dims, budget = [], []
    for dim in SPACES[method]:
        if isinstance(dim, Budget):
            cap = caps.pop(dim.name, None)
            dim = dim.resolve(_get(config, _paths(dim.paths)[0]) if cap is None else cap)
            budget.append(dim.name)
        dims.append(dim)
    if caps:
        raise error("caps", f"budget names among {budget}", Text(f"unknown {sorted(caps)}"))
    return Space(method, config, tuple(dims), tuple(budget))


# -- the validation cells ---------------------------------------------------------------------------

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
        return simulate_batch(system, x0, self.signals(system.nu), self.T, self.dt, process_std=self.process_std,
                              measurement_std=self.measurement_std, seed=seeds)


def fitted_families(config: Any) -> set[tuple[str, str]]:
    """The ``(kind, regime)`` pairs a configuration fits on: every ``kinds`` field of its dataclass
    tree, with the ``regime`` beside it (``"train"`` where there is none; ``train`` is ``id``, and
    ``wide``, the hull of the ``id`` and ``ood`` ranges, both)."""
    found: set[tuple[str, str]] = set()
    if not is_dataclass(config):
        return found
    names = _field_names(config)
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


# -- the study ----------------------------------------------------------------------------------------


def storage_url(storage: Optional[str], out: Path) -> str:
    """The storage URL: ``storage`` as given, else the SQLite file ``out/study.db``."""
    return storage if storage else f"sqlite:///{(out / 'study.db').resolve()}"


def _public_url(url: str) -> str:
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


def _driver_url(url: str) -> str:
    """A bare ``postgresql://`` URL with the driver the tune extra installs (psycopg 3), which SQLAlchemy
    before 2.1 does not take by default."""
    return "postgresql+psycopg://" + url[len("postgresql://"):] if url.startswith("postgresql://") else url


def _storage(url: str, heartbeat: int) -> Any:
    optuna = _optuna()
    url = _driver_url(url)
    engine = {"connect_args": {"timeout": 60}} if url.startswith("sqlite") else {"pool_pre_ping": True}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RDBStorage(
            url, engine_kwargs=engine, heartbeat_interval=heartbeat, grace_period=3 * heartbeat,
            heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY))


@dataclass(frozen=True, eq=False)
class TuneResult:
    """What :func:`tune` did: the study, where the best model, the summary and the plot were written,
    and how many trials this worker ran."""

    study: Any
    best_dir: Optional[Path]
    summary: Path
    plot: Path
    ran: int


def _train(system: System, method: str, config: Any, out: Path, *, base: Optional[Path], seed: int,
           threads: int) -> float:
    from ..train import train_observer

    t0 = time.perf_counter()
    train_observer(system, method, out, config=config, base=base, seed=seed, progress=False, threads=threads,
                   overwrite=True)
    return time.perf_counter() - t0


def _study_record(system: System, method: str, space: Space, validation: Validation, seed: int) -> dict:
    return {"system": system.name, "fingerprint": system.fingerprint, "method": method, "seed": seed,
            "space": space.describe(), "objective": validation.describe()}


def tune(system: System, method: str, out_dir: PathLike, *, n_trials: int, study: Optional[str] = None,
         storage: Optional[str] = None, config: Any = None, caps: Optional[dict] = None,
         base: Optional[PathLike] = None, seed: int = 0, threads: int = 1, val_trials: int = 20,
         heartbeat: int = 30, baseline: bool = False, copy_from: Optional[str] = None,
         sampler_seed: Optional[int] = None, progress: bool = True) -> TuneResult:
    """Run one worker of an Optuna study of ``method``'s design on ``system``.

    Parameters
    ----------
    system : System
    method : str
        A method with a search space (:data:`SPACES`).
    out_dir : path
        Where this worker writes: ``trials/NNNN/`` (each trial's model), ``best/`` (the best trial's
        model, its card's ``search`` records the study), ``summary.md``, ``search.png``, and
        ``study.db`` (the default storage).
    n_trials : int
        Complete trials the study stops at (over all workers); run again to resume, or with a larger
        number to extend it.
    study : str, optional
        The study's name; default ``"<system>-<method>"``.
    storage : str, optional
        An SQLAlchemy URL (``postgresql://user@host:port/db``, ``sqlite:///path``); default the
        SQLite file ``out_dir/study.db``.
    config : dataclass, optional
        The base configuration (default ``default_config(system.name, method)``).
    caps : dict, optional
        Budget caps (``{"runs": N, "epochs": M}``), default the configuration's own.
    base : path, optional
        The Phase-1 model, for methods that build on one.
    seed : int
        Training seed of every trial (the trials differ by configuration only).
    threads : int
        Torch threads of each training (1 per worker on a shared machine).
    val_trials : int
        Validation trials per cell.
    heartbeat : int
        Seconds between a running trial's heartbeats; a trial silent for three of them is failed
        and queued again by the next worker that starts a trial.
    baseline : bool
        Also train the base configuration at the budget caps (the recipe) and record its validation
        score in the study (once per study).
    copy_from : str, optional
        A storage URL to copy the study from before joining it (e.g. a local SQLite study that is
        to continue on PostgreSQL); nothing is copied when the study already exists in ``storage``
        (several workers may be started with it: one copies, the others join).
    sampler_seed : int, optional
        Seed of this worker's TPE sampler (default: none; workers must not share one).
    progress : bool
        Optuna's log lines per trial.

    Returns
    -------
    TuneResult
    """
    optuna = _optuna()
    if not isinstance(system, System):
        raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
    n_trials = positive_int(n_trials, "n_trials")
    heartbeat = positive_int(heartbeat, "heartbeat")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    name = study or f"{system.name}-{method}"
    url = storage_url(storage, out)
    space = search_space(method, config, system=system.name, caps=caps)
    if base is None and variants.get(method).needs_base:
        raise error("base", f"the Phase-1 model {method!r} builds on (every worker's trials share it)", None,
                    "Train it once first: kklcasadi train --method autonomous --out DIR, then pass --base DIR.")
    base_path = None if base is None else Path(base).resolve()
    validation = Validation.build(system, validation_cells(space.base, n_trials=val_trials),
                                  trials=TrialCache(out / "cache"))
    record = _study_record(system, method, space, validation, seed)
    optuna.logging.set_verbosity(optuna.logging.INFO if progress else optuna.logging.WARNING)
    storage_obj = _storage(url, heartbeat)
    if copy_from and name not in optuna.get_all_study_names(storage_obj):
        try:
            optuna.copy_study(from_study_name=name, from_storage=_driver_url(copy_from), to_storage=storage_obj)
        except optuna.exceptions.DuplicatedStudyError:
            pass                          # another worker started with --copy-from copied it first: join it
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        sampler = optuna.samplers.TPESampler(seed=sampler_seed, multivariate=True, group=True, constant_liar=True,
                                             n_startup_trials=min(10, max(2, n_trials // 3)))
    the_study = optuna.create_study(study_name=name, storage=storage_obj, direction="minimize", sampler=sampler,
                                    load_if_exists=True)
    _check_record(the_study, record, name)
    if baseline and "baseline" not in the_study.user_attrs:
        path = out / BASELINE_DIR
        seconds = _train(system, method, space.baseline(), path, base=base_path, seed=seed, threads=threads)
        value, cells = score(load_observer(path, system=system), validation)
        the_study.set_user_attr("baseline", {"value": value, "cells": cells, "train_s": round(seconds, 1)})

    started: list[int] = []                       # the trials this worker starts

    def objective(trial: Any) -> float:
        started.append(trial.number)
        trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
        path = out / TRIALS_DIR / f"{trial.number:04d}"
        seconds = _train(system, method, space.suggest(trial), path, base=base_path, seed=seed, threads=threads)
        value, cells = score(load_observer(path, system=system), validation)
        trial.set_user_attr("cells", cells)
        trial.set_user_attr("train_s", round(seconds, 1))
        return value

    complete = len(the_study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)))
    todo = n_trials - complete
    if todo > 0:
        stop = optuna.study.MaxTrialsCallback(n_trials, states=(optuna.trial.TrialState.COMPLETE,))
        # at most the missing number of trials in this worker: trials that fail count too
        the_study.optimize(objective, n_trials=todo + MAX_RETRY, callbacks=[stop], catch=(ValueError, RuntimeError))
    best_dir = export_best(the_study, out, system, method, space, validation, url=url, base=base_path, seed=seed,
                           threads=threads)
    summary = out / "summary.md"
    summary.write_text(summary_table(the_study, url) + "\n")
    plot = search_plot(the_study, out / "search.png")
    return TuneResult(the_study, best_dir, summary, plot, len(started))


def _check_record(study: Any, record: dict, name: str) -> None:
    """Record what the study searches, or check that a resumed study searches the same (plant, method,
    seed, space and validation cells; the EKF's scores are measured again by every worker)."""
    ours = json.loads(json.dumps(record))
    stored = study.user_attrs.get("record")
    if stored is None:
        study.set_user_attr("record", ours)
        return

    def key(r: dict) -> dict:
        return {"plant": r["fingerprint"], "method": r["method"], "seed": r["seed"], "space": r["space"],
                "cells": r["objective"]["cells"]}

    differ = [k for k, v in key(ours).items() if key(stored)[k] != v]
    if differ:
        raise error("study", f"the settings study {name!r} was started with", Text(f"another {', '.join(differ)}"),
                    "Use another --study name, or the study's own settings.")


def _complete(study: Any) -> list:
    optuna = _optuna()
    return study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))


def export_best(study: Any, out: Path, system: System, method: str, space: Space, validation: Validation, *,
                url: str, base: Optional[Path] = None, seed: int = 0, threads: int = 1) -> Optional[Path]:
    """Write the best trial's model to ``out/best`` with the study in its card (``search``).

    The trial's model is taken from ``out/trials/NNNN`` where this worker (or another on this
    machine) trained it, else trained again from the trial's parameters with the study's seed.
    Returns None while the study has no complete trial.
    """
    optuna = _optuna()
    if not _complete(study):
        return None
    best = study.best_trial
    source = out / TRIALS_DIR / f"{best.number:04d}"
    if not (source / "card.json").exists():
        _train(system, method, space.suggest(optuna.trial.FixedTrial(best.params)), source, base=base, seed=seed,
               threads=threads)
    model = load_model(source)
    baseline = study.user_attrs.get("baseline")
    search = Search(study.study_name, _public_url(url), best.number, float(best.value), dict(best.params),
                    space.describe(), validation.describe(), None if baseline is None else baseline["value"])
    target = out / BEST_DIR
    card = {**model.card, "search": search.to_card()}
    if card.get("base") is not None:                    # the base's path is relative to the model's directory
        card["base"] = {**card["base"], "path": os.path.relpath(model.base.path, target.resolve())}
    save_model(target, model.arrays, card, overwrite=True)
    for extra in ("history.json", "history.png"):
        if (source / extra).exists():
            shutil.copyfile(source / extra, target / extra)
    return target


def summary_table(study: Any, url: str, top: int = 10) -> str:
    """Markdown: the study's state, its baseline and its best trials with their parameters."""
    optuna = _optuna()
    states = {state.name.lower(): 0 for state in optuna.trial.TrialState}
    for trial in study.get_trials(deepcopy=False):
        states[trial.state.name.lower()] += 1
    lines = [f"# study {study.study_name}", "", f"storage: {_public_url(url)}",
             "trials: " + ", ".join(f"{n} {state}" for state, n in states.items() if n), ""]
    baseline = study.user_attrs.get("baseline")
    record = study.user_attrs.get("record", {})
    objective = record.get("objective", {})
    if objective:
        lines += [f"score: {objective['score']} (1 = the EKF); cells: "
                  + ", ".join(f"{c['name']} ({c['n_trials']} trials, seed {c['seed']})" for c in objective["cells"]),
                  ""]
    if baseline is not None:
        lines += [f"baseline (the recipe at the budget caps): {baseline['value']:.4f}, trained in "
                  f"{baseline['train_s']} s", ""]
    complete = sorted(_complete(study), key=lambda t: t.value)[:top]
    if not complete:
        return "\n".join(lines + ["no complete trial yet"])
    names = sorted({name for trial in complete for name in trial.params})
    cells = sorted({name for trial in complete for name in trial.user_attrs.get("cells", {})})
    lines.append("| trial | score | " + " | ".join(cells) + " | train (s) | " + " | ".join(names) + " | retry of |")
    lines.append("|---" * (4 + len(cells) + len(names)) + "|")
    for trial in complete:
        retry = trial.system_attrs.get("failed_trial")
        values = [_short(trial.params.get(name, "-")) for name in names]
        smape = [f"{trial.user_attrs.get('cells', {}).get(c, float('nan')):.2f}" for c in cells]
        lines.append(f"| {trial.number} | {trial.value:.4f} | " + " | ".join(smape) + f" | "
                     f"{trial.user_attrs.get('train_s', '-')} | " + " | ".join(values) + f" | "
                     f"{'-' if retry is None else retry} |")
    lines += ["", "cells: the observer's mean SMAPE % per validation cell"]
    return "\n".join(lines)


def _short(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def search_plot(study: Any, path: Path) -> Path:
    """PNG of the search: the score of every complete trial against its number (with the best so
    far and the baseline), and Optuna's parameter importances."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    optuna = _optuna()
    complete = sorted(_complete(study), key=lambda t: t.number)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4))
    if complete:
        numbers = [t.number for t in complete]
        values = [t.value for t in complete]
        ax.plot(numbers, values, "o", ms=4, label="trial")
        ax.step(numbers, np.minimum.accumulate(values), where="post", label="best so far")
    baseline = study.user_attrs.get("baseline")
    if baseline is not None:
        ax.axhline(baseline["value"], color="k", ls="--", lw=1, label="recipe (baseline)")
    ax.axhline(1.0, color="gray", ls=":", lw=1, label="EKF")
    ax.set(xlabel="trial", ylabel="validation score (SMAPE / EKF's)", title=study.study_name)
    ax.legend(fontsize=8)
    if len(complete) >= 4:
        importances = optuna.importance.get_param_importances(study)
        names = list(importances)[::-1]
        bx.barh(names, [importances[n] for n in names])
        bx.set(xlabel="importance (Optuna, PED-ANOVA)", title="what mattered")
    else:
        bx.text(0.5, 0.5, f"importances need 4 complete trials ({len(complete)} so far)", ha="center")
        bx.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
