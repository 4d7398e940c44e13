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
from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence

import casadi as ca
import numpy as np
from tqdm.auto import tqdm

from .. import metrics
from ..estimators.ekf import EKF
from ..estimators.pf import ROUGHENING, SUBSTEPS, ParticleFilter
from ..observer.kkl import KKLObserver
from ..plant import signals as sig
from ..plant.rk4 import substeps_for
from ..plant.simulate import TrajectoryBatch, simulate_batch
from ..plant.systems import System
from ..validation import Text, error, nonnegative_number, one_of, positive_int, positive_number
from .compiled import CompiledEstimator, Compiler, ekf_estimator, observer_estimator
from .protocol import Protocol
from .trialcache import TrialCache

__all__ = ["Case", "FamilyCell", "Settings", "ModelResult", "Report", "cases", "fit_families", "category", "case_ekf",
           "output_range", "families_text", "run", "MonitoredObserver", "NOISE_LEVELS", "FAMILY_STREAMS",
           "CATEGORIES", "BAD_RATIO", "FLAG_SHARE"]

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
#: How observers and the EKF are compiled unless told otherwise (portable flags, cached libraries).
DEFAULT_COMPILER = Compiler()
#: RK4 steps per interval of the particle filter (one step diverges on FitzHugh-Nagumo's stiff corners).


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
        if not (isinstance(self.noise, (int, float)) and math.isfinite(self.noise) and self.noise > 0):
            raise error("noise", "a noise std > 0 (the EKF and the particle filter need measurement noise)",
                        self.noise)

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
        """The per-trial inputs (signals, or output-feedback laws for ``feedback``), in the plant's input units
        where it declares a ``u_box`` (:func:`kklcasadi.plant.signals.in_box`)."""
        s = self.settings
        rng = np.random.default_rng([s.seed, FAMILY_STREAMS[self.family]])
        span = output_range(system) if self.family == "feedback" else None
        return [sig.in_box(sig.draw(self.family, rng, self.ranges, nu=system.nu, horizon=s.T, output_range=span),
                           system.u_box) for _ in range(s.n_trials)]

    def simulate(self, system: System) -> TrajectoryBatch:
        s = self.settings
        x0 = system.sample_box(s.n_trials, s.seed)
        seeds = np.random.SeedSequence([s.seed, FAMILY_STREAMS[self.family]]).spawn(s.n_trials)
        return simulate_batch(system, x0, self.inputs(system), s.T, s.dt, process_std=self.noise,
                              measurement_std=self.noise, seed=seeds, method=s.method)


def case_ekf(plant: System, noise: float, dt: float) -> EKF:
    """The EKF scored beside the models on a case of noise std ``noise``: tuned to the case's noise,
    ``Q = (noise dt)^2 I`` (the process noise over one sample) and ``R = noise^2 I``.

    Parameters
    ----------
    plant : System
    noise : float
        The case's process and measurement noise std (> 0).
    dt : float
        Sample period.

    Returns
    -------
    EKF
    """
    noise = positive_number(noise, "noise")
    return EKF(plant, dt, Q=np.eye(plant.nx) * (noise * dt) ** 2, R=np.eye(plant.ny) * noise ** 2)


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


# ---------------------------------------------------------------------- estimators
class MonitoredObserver(CompiledEstimator):
    """An observer's compiled trajectory with its domain monitor at every sample.

    The trajectory is :class:`~kklcasadi.evaluation.compiled.CompiledObserver`'s (the observer's own
    ``memory_init``, ``decode`` and ``step`` folded with ``mapaccum``), and the observer's
    ``domain_check(z_k, w_k, xhat_k)`` mapped over its samples: calling it returns
    ``[xhat; in_domain]`` (M, N, nx + 1); :meth:`estimate` splits them.

    Parameters
    ----------
    observer : KKLObserver
        With a domain monitor (``observer.domain_check`` not None).
    compiler, n_threads
        See :class:`~kklcasadi.evaluation.compiled.CompiledEstimator`.
    """

    def __init__(self, observer: KKLObserver, *, compiler: Optional[Compiler] = DEFAULT_COMPILER,
                 n_threads: Optional[int] = None) -> None:
        if not isinstance(observer, KKLObserver):
            raise error("observer", "a kklcasadi.KKLObserver", Text(type(observer).__name__), kind=TypeError)
        if observer.domain_check is None:
            raise error("observer", "an observer with a domain monitor (a card with a domain or a monitor)",
                        Text(repr(observer)))
        super().__init__(observer.nx + 1, observer.nu, observer.ny, observer.dt, compiler=compiler,
                         n_threads=n_threads)
        self.observer = observer

    def trajectory(self, n: int, group: int = 1) -> ca.Function:
        if group != 1:
            raise ValueError(f"group: expected 1 (the monitored trajectory shares no work), received {group!r}.")
        obs = self.observer
        y, u, z0 = ca.MX.sym("y", obs.ny, n), ca.MX.sym("u", obs.nu, n), ca.MX.sym("z0", obs.nz)
        w0 = obs.memory_init(y[:, 0], u[:, 0])
        steps = obs.step.mapaccum("trajectory", n - 1, [0, 1], [0, 1])
        z, w, xhat = steps(z0, w0, y[:, :n - 1], y[:, 1:], u[:, 1:])
        zs, ws, xhats = ca.horzcat(z0, z), ca.horzcat(w0, w), ca.horzcat(obs.decode(z0, w0), xhat)
        flags = obs.domain_check.map(n)(zs, ws, xhats)
        return ca.Function(f"monitored_{obs.method}_n{n}", [y, u, z0], [ca.vertcat(xhats, flags)],
                           ["y", "u", "s0"], ["xhat_in_domain"])

    def initial_state(self) -> np.ndarray:
        """``z_0 = 0`` (nz,)."""
        return np.zeros(self.observer.nz)

    def estimate(self, t: Any, y: Any, u: Any) -> tuple[np.ndarray, np.ndarray]:
        """``xhat`` (M, N, nx) and ``in_domain`` (M, N) of bool for M trials."""
        out = self(t, y, u)
        return out[..., :-1], out[..., -1] > 0.5


@dataclass(frozen=True, eq=False)
class ModelResult:
    """One observer on every case: per case, its per-trial SMAPE (%) and the share of its samples
    after the settle time that the domain monitor flags (None without a monitor)."""

    label: str
    fit_families: Optional[dict]
    fit_noise: float
    smape: list
    flagged_share: list

    def category(self, case: Case) -> str:
        return category(case, self.fit_families)


@dataclass(frozen=True, eq=False)
class Report:
    """The generalisation benchmark of one plant: the cases, the models, the EKF and the particle filter.

    Attributes
    ----------
    system : str
    settings : Settings
    cases : list of Case
    models : list of ModelResult
    ekf : list of numpy.ndarray
        Per case, the EKF's per-trial SMAPE (%).
    pf : list of numpy.ndarray or None
        The particle filter's, when run.
    pf_particles : int or None
    pf_roughening : float or None
        The particle filter's roughening (None: no filter, or a report written before it was recorded: 0).
    """

    system: str
    settings: Settings
    cases: list
    models: list
    ekf: list
    pf: Optional[list] = None
    pf_particles: Optional[int] = None
    pf_roughening: Optional[float] = None

    def bad(self, model: ModelResult, i: int) -> np.ndarray:
        """Per trial of case ``i``: the model's SMAPE above :data:`BAD_RATIO` times the EKF's on that trial."""
        return model.smape[i] > BAD_RATIO * self.ekf[i]

    def markdown(self) -> str:
        """One table per model: mean SMAPE of the model, EKF and PF per case, ratios, bad and flagged trials."""
        blocks = []
        for model in self.models:
            pf = self.pf is not None
            head = ["family", "regime", "noise", "vs fit", "trials", model.label, "EKF"] + (["PF"] if pf else []) + \
                [f"{model.label} / EKF"] + ([f"{model.label} / PF"] if pf else []) + \
                ["bad trials", "flagged trials", f"flagged samples after {self.settings.t_settle:g} s"]
            lines = [f"**{self.system}, {model.label}** (fit on: {families_text(model.fit_families)}; "
                     f"noise std {model.fit_noise:g})", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
            for i, case in enumerate(self.cases):
                m, e = model.smape[i].mean(), self.ekf[i].mean()
                row = [case.family, case.regime, f"{case.noise:g}", model.category(case), str(len(self.ekf[i])),
                       f"{m:.2f}", f"{e:.2f}"] + ([f"{self.pf[i].mean():.2f}"] if pf else []) + [f"{m / e:.2f}x"] + \
                    ([f"{m / self.pf[i].mean():.2f}x"] if pf else [])
                bad = self.bad(model, i)
                share = model.flagged_share[i]
                if share is None:
                    row += [str(int(bad.sum())), "-", "-"]
                else:
                    row += [str(int(bad.sum())), str(int((share >= FLAG_SHARE).sum())), f"{share.mean():.3f}"]
                lines.append("| " + " | ".join(row) + " |")
            blocks.append("\n".join(lines))
        return "\n\n".join(blocks)

    def monitor_summary(self, model: ModelResult) -> list[dict]:
        """The monitor's precision and recall per group of cases (None entries without a monitor).

        Groups: ``in distribution`` (fitted families at the model's noise level; the target is at
        most 5 % of samples after the settle time flagged), ``ood and held out`` at the model's
        noise level, and every case at the other noise levels. A trial is bad when its SMAPE
        exceeds :data:`BAD_RATIO` times the EKF's, flagged when at least :data:`FLAG_SHARE` of its
        samples after the settle time are out of domain.
        """
        groups = {"in distribution": [], f"ood and held out, noise {model.fit_noise:g}": [],
                  "other noise levels": []}
        for i, case in enumerate(self.cases):
            if model.flagged_share[i] is None:
                continue
            if not math.isclose(case.noise, model.fit_noise):
                groups["other noise levels"].append(i)
            elif model.category(case) == "fit":
                groups["in distribution"].append(i)
            else:
                groups[f"ood and held out, noise {model.fit_noise:g}"].append(i)
        out = []
        for name, index in groups.items():
            if not index:
                continue
            bad = np.concatenate([self.bad(model, i) for i in index])
            share = np.concatenate([model.flagged_share[i] for i in index])
            flagged = share >= FLAG_SHARE
            hits = int((bad & flagged).sum())
            out.append({"group": name, "cases": len(index), "trials": int(bad.size), "bad": int(bad.sum()),
                        "flagged": int(flagged.sum()),
                        "precision": hits / int(flagged.sum()) if flagged.any() else None,
                        "recall": hits / int(bad.sum()) if bad.any() else None,
                        "share_bad": float(share[bad].mean()) if bad.any() else None,
                        "share_other": float(share[~bad].mean()) if (~bad).any() else None})
        return out

    def monitor_markdown(self) -> str:
        """The monitor summaries as one table."""
        head = ["model", "cases", "trials", "bad", "flagged", "precision", "recall",
                f"flagged samples after {self.settings.t_settle:g} s: bad trials", "other trials"]
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for model in self.models:
            for g in self.monitor_summary(model):
                cells = [f"{model.label}: {g['group']}", str(g["cases"]), str(g["trials"]), str(g["bad"]),
                         str(g["flagged"])]
                cells += ["-" if g[k] is None else f"{g[k]:.2f}" for k in ("precision", "recall")]
                cells += ["-" if g[k] is None else f"{g[k]:.3f}" for k in ("share_bad", "share_other")]
                lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)

    def to_json(self) -> dict:
        """Every per-trial number, the means, the ratios and the monitor summaries (plain JSON values)."""
        out = []
        for i, case in enumerate(self.cases):
            entry = {"family": case.family, "regime": case.regime, "noise": case.noise, "ranges":
                     {k: list(v) for k, v in case.ranges.items()}, "trials": len(self.ekf[i]),
                     "ekf": {"smape_mean": float(self.ekf[i].mean()), "smape": self.ekf[i].tolist()}, "models": {}}
            if self.pf is not None:
                entry["pf"] = {"smape_mean": float(self.pf[i].mean()), "smape": self.pf[i].tolist()}
            for model in self.models:
                mean = float(model.smape[i].mean())
                record = {"category": model.category(case), "smape_mean": mean, "smape": model.smape[i].tolist(),
                          "ratio_ekf": mean / float(self.ekf[i].mean()), "bad": self.bad(model, i).tolist()}
                if self.pf is not None:
                    record["ratio_pf"] = mean / float(self.pf[i].mean())
                share = model.flagged_share[i]
                record["flagged_share"] = None if share is None else share.tolist()
                entry["models"][model.label] = record
            out.append(entry)
        return {"system": self.system, "settings": vars(self.settings), "pf_particles": self.pf_particles,
                "pf_roughening": self.pf_roughening,
                "bad_ratio": BAD_RATIO, "flag_share": FLAG_SHARE,
                "models": {m.label: {"fit_families": _plain(m.fit_families), "fit_noise": m.fit_noise,
                                     "monitor": self.monitor_summary(m)} for m in self.models},
                "cases": out}


def _plain(families: Optional[dict]) -> Optional[dict]:
    return None if families is None else {k: {p: list(b) for p, b in v.items()} for k, v in families.items()}


def families_text(families: Optional[Mapping[str, Mapping[str, Sequence[float]]]]) -> str:
    """``zero, constant (value -1..1), ...``: input families with their ranges (:func:`fit_families`)."""
    if families is None:
        return "not recorded"
    return ", ".join(k + ("" if not v else " (" + ", ".join(f"{p} {lo:g}..{hi:g}" for p, (lo, hi) in v.items()) + ")")
                     for k, v in families.items())


def run(observers: Sequence[tuple[str, KKLObserver]], case_list: Sequence[Case], settings: Settings = Settings(), *,
        trials: Optional[TrialCache] = None, pf_particles: Optional[int] = None, pf_roughening: float = ROUGHENING,
        compiler: Optional[Compiler] = DEFAULT_COMPILER, n_threads: Optional[int] = None,
        progress: bool = False) -> Report:
    """Score observers of one plant, the EKF and optionally the particle filter on every case.

    Parameters
    ----------
    observers : sequence of (label, KKLObserver)
        The observers (one plant), each with its row label.
    case_list : sequence of Case
        See :func:`cases`.
    settings : Settings
    trials : TrialCache, optional
        Where the cases' trials come from (default: simulated for this call).
    pf_particles : int, optional
        Run the particle filter with this many particles (its noise levels the case's, seed
        ``settings.seed``, :data:`kklcasadi.estimators.pf.SUBSTEPS`).
    pf_roughening : float
        Its roughening (default :data:`kklcasadi.estimators.pf.ROUGHENING`).
    compiler : Compiler or None
        How the observers and the EKF are compiled (None: the CasADi VM).
    n_threads : int, optional
        Worker threads over trials.
    progress : bool
        A progress bar over the cases.

    Returns
    -------
    Report
        Trials that failed in the simulation are left out of their case.
    """
    if not observers:
        raise error("observers", "at least one (label, observer)", Text("none"))
    plant = observers[0][1].system
    for label, obs in observers:
        if obs.system.fingerprint != plant.fingerprint:
            raise error("observers", f"observers of one plant ({plant.name!r})",
                        Text(f"{label!r} for {obs.system.name!r}"))
    if pf_particles is not None:
        positive_int(pf_particles, "pf_particles")
        nonnegative_number(pf_roughening, "pf_roughening")
    trials = TrialCache(None) if trials is None else trials
    runners = [(label, obs, MonitoredObserver(obs, compiler=compiler, n_threads=n_threads)
                if obs.domain_check is not None else None) for label, obs in observers]
    plain = {label: None for label, _ in observers}
    results = {label: ([], []) for label, _ in observers}
    ekf_scores, pf_scores = [], ([] if pf_particles is not None else None)
    for case in tqdm(list(case_list), desc=plant.name, unit="case", disable=not progress):
        batch = trials.trials(plant, case.cell(settings))
        ok = batch.ok
        x, y, u = batch.x[ok], batch.y[ok], batch.u[ok]
        after = batch.t >= settings.t_settle
        for label, obs, monitored in runners:
            if monitored is None:
                if plain[label] is None:
                    plain[label] = observer_estimator(obs, compiler=compiler, n_threads=n_threads)
                xhat, share = plain[label](batch.t, y, u), None
            else:
                xhat, inside = monitored.estimate(batch.t, y, u)
                share = (~inside[:, after]).mean(axis=1)
            results[label][0].append(metrics.smape(x, xhat))
            results[label][1].append(share)
        ekf = case_ekf(plant, case.noise, settings.dt)
        ekf_scores.append(metrics.smape(x, ekf_estimator(ekf, compiler=compiler, n_threads=n_threads)(batch.t, y, u)))
        if pf_scores is not None:
            pf = ParticleFilter(plant, settings.dt, n_particles=pf_particles, process_std=case.noise,
                                measurement_std=case.noise, substeps=substeps_for(plant, settings.dt, SUBSTEPS),
                                roughening=pf_roughening, seed=settings.seed)
            pf_scores.append(metrics.smape(x, pf(batch.t, y, u)))
    models = [ModelResult(label, fit_families(obs), obs.model.spec.measurement_std, *results[label])
              for label, obs in observers]
    return Report(plant.name, settings, list(case_list), models, ekf_scores, pf_scores, pf_particles,
                  None if pf_particles is None else pf_roughening)
