"""The robustness benchmark of docs/protocol.md "Robustness": where the EKF's model or noise is wrong.

A *case* changes the plant or the noise the trials are simulated with, while every estimator keeps
what it was told: the plant's parameters at the corners of their declared box or drawn inside it,
effects outside the family (unmodelled damping, an input gain error), heavy-tailed noise, outliers,
quantisation, and the exact model with Gaussian noise. On the same trials of each case it scores the
models (with their domain monitor), the EKF with the simulator's ``Q`` and ``R``, the EKF whose
scales were chosen on the case's **tuning** trials (:class:`~kklcasadi.estimators.TunedEKF`), the
augmented EKF (:class:`~kklcasadi.estimators.AugmentedEKF`: parameters as random walks, with or
without an input-disturbance state, whichever scores better on the tuning trials, its scales and
walk rate chosen there too) and optionally the particle filter over states and parameters
(:class:`~kklcasadi.estimators.ParameterPF`, the box as its prior, the case's noise model as its
likelihood: the Bayes reference where the case is inside the family).

Trials (docs/protocol.md "Robustness"): x0 from the Latin hypercube over X0 (``seed``); trial ``i``'s
input of family ``ID_FAMILIES[i % 4]`` in the ``id`` ranges, drawn in trial order from
``default_rng([seed, 2])``; its noise from ``SeedSequence([seed, 3]).spawn(n)[i]``; the parameters
of the ``inside`` case from a Latin hypercube over the box (``default_rng([seed, 1])``). Every case shares
these draws (common random numbers); tuning trials are the same construction with ``tuning_seed``.
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Optional, Sequence

import numpy as np
from tqdm.auto import tqdm

from .. import metrics, provenance
from ..estimators.augmented import SHRINKAGE, AugmentedEKF, ParameterPF
from ..estimators.pf import ROUGHENING, SUBSTEPS
from ..estimators.tuned import TunedEKF
from ..observer.kkl import KKLObserver
from ..plant import signals as sig
from ..plant.augment import perturbed
from ..plant.noise import noise_model
from ..plant.rk4 import substeps_for
from ..plant.simulate import TrajectoryBatch, simulate_batch
from ..plant.systems import System
from ..validation import Text, error, nonnegative_number, one_of, positive_int, positive_number
from .compiled import Compiler, observer_estimator
from .generalisation import DEFAULT_COMPILER, FLAG_SHARE, MonitoredObserver, case_ekf
from .trialcache import TrialCache
from .uncertainty import UncertaintyRow, observer_uncertainty, uncertainty_record, uncertainty_row, uncertainty_table

__all__ = ["RobustCase", "RobustCell", "Settings", "Report", "cases", "run", "targets", "ID_FAMILIES", "KINDS",
           "BASELINES", "TITLES", "DEFAULT_NOISE_MODELS"]

#: The input families of the trials, in turn (the protocol's ``id`` ranges).
ID_FAMILIES = ("zero", "constant", "sinusoid", "square")
#: What a case changes: ``exact`` nothing; ``corner`` the parameters at a corner of the box; ``inside`` drawn
#: inside it per trial; ``outside`` an effect no parameter value gives; ``noise`` the measurement noise's model.
KINDS = ("exact", "corner", "inside", "outside", "noise")
#: The baselines beside the models, as the report names them.
BASELINES = ("ekf", "tuned", "augmented", "pf")
#: The baselines' names in the tables.
TITLES = {"ekf": "EKF", "tuned": "tuned EKF", "augmented": "augmented EKF", "pf": "PF (x, p)"}
#: The noise cases of the default grid.
DEFAULT_NOISE_MODELS = ("student-t:2", "outliers:0.05,10", "quantised:0.2")
#: The issue's targets per case kind: (baseline, largest ratio of the model's mean SMAPE to the baseline's).
TARGETS = {"exact": (("ekf", 1.05),), "corner": (("tuned", 0.85), ("augmented", 1.0)),
           "inside": (("tuned", 0.85), ("augmented", 1.0)), "outside": (("tuned", 1.0),),
           "noise": (("tuned", 0.9),)}


@dataclass(frozen=True)
class Settings:
    """What every case shares.

    Attributes
    ----------
    n_trials, n_tuning : int
        Scored trials and tuning trials per case.
    T, dt : float
    seed, tuning_seed : int
        Seeds of the scored and of the tuning trials.
    noise : float
        Process and measurement noise std (scale) of every case.
    method : str
        The plant's integrator.
    t_settle : float
        The domain monitor is read after this time.
    """

    n_trials: int = 100
    n_tuning: int = 40
    T: float = 50.0
    dt: float = 0.05
    seed: int = 2026
    tuning_seed: int = 4242
    noise: float = 0.1
    method: str = "cvodes"
    t_settle: float = 5.0

    def __post_init__(self) -> None:
        positive_int(self.n_trials, "n_trials")
        positive_int(self.n_tuning, "n_tuning")
        positive_number(self.noise, "noise")
        if self.seed == self.tuning_seed:
            raise error("tuning_seed", f"a seed other than the scored trials' ({self.seed})", self.tuning_seed)


@dataclass(frozen=True)
class RobustCase:
    """One way the trials differ from what the estimators are told.

    Attributes
    ----------
    name : str
        The row's label (``alpha- beta+``, ``inside``, ``damping 0.3``, ``student-t:2``, ...).
    kind : str
        One of :data:`KINDS`.
    params : tuple of float or None
        The plant's parameter values (``corner``); None: the nominal ones, or drawn per trial (``inside``).
    damping, input_gain : float
        Effects outside the family (:func:`kklcasadi.plant.augment.perturbed`).
    noise_model : str
        The measurement noise (:mod:`kklcasadi.plant.noise`).
    """

    name: str
    kind: str
    params: Optional[tuple[float, ...]] = None
    damping: float = 0.0
    input_gain: float = 1.0
    noise_model: str = "gauss"

    def __post_init__(self) -> None:
        one_of(self.kind, "kind", KINDS)
        nonnegative_number(self.damping, "damping")
        object.__setattr__(self, "noise_model", str(noise_model(self.noise_model)))

    @property
    def targets(self) -> tuple[tuple[str, float], ...]:
        return TARGETS[self.kind]


def cases(family: System, *, damping: float = 0.3, input_gain: float = 0.7,
          noise_models: Sequence[str] = DEFAULT_NOISE_MODELS, kinds: Sequence[str] = KINDS) -> list[RobustCase]:
    """The default grid: the exact model, every corner of the parameter box, draws inside it, damping and an
    input gain error, and each noise model; ``kinds`` keeps those of these kinds."""
    if not family.n_params:
        raise error("family", "a plant with parameters (kc.systems.get(name, param_spread=0.3), or params=)",
                    Text(f"plant {family.name!r} without parameters"))
    for kind in kinds:
        one_of(kind, "kinds", KINDS)
    out = [RobustCase("exact", "exact")]
    for signs in itertools.product((0, 1), repeat=family.n_params):
        values = tuple(float(family.param_box[j, s]) for j, s in enumerate(signs))
        label = " ".join(f"{n}{'-+'[s]}" for n, s in zip(family.param_names, signs))
        out.append(RobustCase(label, "corner", values))
    out.append(RobustCase("inside", "inside"))
    if damping:
        out.append(RobustCase(f"damping {damping:g}", "outside", damping=damping))
    if input_gain != 1.0:
        out.append(RobustCase(f"input gain {input_gain:g}", "outside", input_gain=input_gain))
    out.extend(RobustCase(str(noise_model(m)), "noise", noise_model=m) for m in noise_models)
    return [c for c in out if c.kind in kinds]


@dataclass(frozen=True)
class RobustCell:
    """A case's scored or tuning trials, as a trial-cache cell (module docstring for the draws)."""

    case: RobustCase
    settings: Settings
    tuning: bool = False

    @property
    def seed(self) -> int:
        return self.settings.tuning_seed if self.tuning else self.settings.seed

    @property
    def n_trials(self) -> int:
        return self.settings.n_tuning if self.tuning else self.settings.n_trials

    @property
    def label(self) -> str:
        return f"robustness-{self.case.name}-{'tuning' if self.tuning else 'scored'}"

    def describe(self) -> dict:
        s = self.settings
        return {"robustness": {"case": asdict(self.case), "n_trials": self.n_trials, "seed": self.seed, "T": s.T,
                               "dt": s.dt, "noise": s.noise, "method": s.method, "families": list(ID_FAMILIES)}}

    def shape(self) -> tuple[int, int]:
        return self.n_trials, round(self.settings.T / self.settings.dt)

    def params(self, family: System) -> Optional[np.ndarray]:
        """The parameter values per trial (n, n_params), or None for the nominal plant."""
        if self.case.kind == "inside":
            return family.sample_params(self.n_trials, np.random.default_rng([self.seed, 1]))
        return None if self.case.params is None else np.tile(self.case.params, (self.n_trials, 1))

    def simulate(self, system: System) -> TrajectoryBatch:
        s, n, case = self.settings, self.n_trials, self.case
        plant = perturbed(system, damping=case.damping, input_gain=case.input_gain) \
            if case.damping or case.input_gain != 1.0 else system
        rng = np.random.default_rng([self.seed, 2])
        inputs = [sig.in_box(sig.draw(ID_FAMILIES[i % 4], rng, sig.family_ranges(ID_FAMILIES[i % 4], "id"),
                                      nu=system.nu, horizon=s.T), system.u_box) for i in range(n)]
        return simulate_batch(plant, system.sample_box(n, self.seed), inputs, s.T, s.dt, process_std=s.noise,
                              measurement_std=s.noise, seed=np.random.SeedSequence([self.seed, 3]).spawn(n),
                              method=s.method, params=self.params(system), noise_model=case.noise_model)


@dataclass(frozen=True, eq=False)
class Report:
    """The robustness benchmark of one plant family.

    Attributes
    ----------
    system : str
    param_names : tuple of str
    param_box : list
    settings : Settings
    cases : list of RobustCase
    models : dict
        ``{label: {"smape": [per case (M,)], "flagged_share": [per case (M,) or None]}}``.
    baselines : dict
        ``{name: [per case (M,)]}`` for :data:`BASELINES` that ran.
    tuning : list of dict
        Per case, the choices made on the tuning trials (the tuned and the augmented EKF's).
    pf_particles : int or None
    consistency : list of UncertaintyRow
        With :func:`run`'s ``consistency``: per case, each estimator's covariance scored on its trials (the models
        with a covariance head, then the baselines, labelled as :data:`TITLES`); empty otherwise.
    """

    system: str
    param_names: tuple
    param_box: list
    settings: Settings
    cases: list
    models: dict
    baselines: dict
    tuning: list
    pf_particles: Optional[int] = None
    extra: dict = field(default_factory=dict)
    consistency: list[UncertaintyRow] = field(default_factory=list)

    def mean(self, label: str, i: int) -> float:
        """The mean SMAPE of a model or a baseline on case ``i``."""
        values = self.models[label]["smape"][i] if label in self.models else self.baselines[label][i]
        return float(np.mean(values))

    def flagged(self, label: str, i: int) -> Optional[float]:
        """The share of case ``i``'s trials the model's domain monitor flags (None without a monitor)."""
        share = self.models[label]["flagged_share"][i]
        return None if share is None else float(np.mean(share >= FLAG_SHARE))

    def ratio(self, label: str, baseline: str, i: int) -> float:
        """The model's mean SMAPE over a baseline's on case ``i``, on the trials the baseline ran (the particle
        filter may run on the first of them only: :func:`run`'s ``pf_trials``)."""
        n = len(self.baselines[baseline][i])
        return float(np.mean(self.models[label]["smape"][i][:n])) / self.mean(baseline, i)

    def checks(self, label: str, i: int) -> list[tuple[str, float, float, bool]]:
        """The issue's targets of case ``i`` for a model: ``(baseline, ratio, target, met)`` each."""
        out = []
        for baseline, target in self.cases[i].targets:
            if baseline in self.baselines:
                ratio = self.ratio(label, baseline, i)
                out.append((baseline, ratio, target, ratio <= target))
        return out

    def markdown(self) -> str:
        """One table per model: the mean SMAPE of every estimator per case, the ratios, the targets; then, where the
        covariances were scored, their consistency (:func:`kklcasadi.evaluation.uncertainty.uncertainty_table`)."""
        names = [b for b in BASELINES if b in self.baselines]
        titles = TITLES
        pf_trials = self.extra.get("pf_trials")
        pf_text = f"; the PF on the first {pf_trials} of each case's trials" if pf_trials is not None else ""
        blocks = []
        for label in self.models:
            head = ["case", "kind", "trials", label] + [titles[b] for b in names] + \
                [f"/ {titles[b]}" for b in names] + ["targets", "flagged trials"]
            lines = [f"**{self.system}, {label}** (parameters {', '.join(self.param_names)} in "
                     f"{_box_text(self.param_box)}; noise {self.settings.noise:g}; mean SMAPE %, "
                     f"{self.settings.n_trials} trials per case{pf_text})", "",
                     "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
            for i, case in enumerate(self.cases):
                m = self.mean(label, i)
                checks = self.checks(label, i)
                target = ", ".join(f"{titles[b]} <= {t:g}x: {'met' if ok else 'missed'}" for b, _, t, ok in checks)
                flagged = self.flagged(label, i)
                row = [case.name, case.kind, str(len(self.models[label]["smape"][i])), f"{m:.2f}"] + \
                    [f"{self.mean(b, i):.2f}" for b in names] + [f"{self.ratio(label, b, i):.2f}x" for b in names] + \
                    [target or "-", "-" if flagged is None else f"{flagged:.2f}"]
                lines.append("| " + " | ".join(row) + " |")
            blocks.append("\n".join(lines))
        if self.consistency:
            blocks.append(f"**{self.system}: the covariances** (each estimator's own variances against its errors, "
                          "on the trials of its SMAPE: mean NEES against the 95 % band of the trials' count, 1- and "
                          "2-sigma coverage per state, log-likelihood of the truth)\n\n"
                          + uncertainty_table(self.consistency))
        return "\n\n".join(blocks)

    def to_json(self) -> dict:
        """Every per-trial number, the means, the ratios, the targets and the tuning choices (plain JSON)."""
        entries = []
        for i, case in enumerate(self.cases):
            entry: dict[str, Any] = {"case": asdict(case), "tuning": self.tuning[i], "baselines": {}, "models": {}}
            for b, values in self.baselines.items():
                entry["baselines"][b] = {"smape_mean": self.mean(b, i), "smape": np.asarray(values[i]).tolist()}
            for label, result in self.models.items():
                share = result["flagged_share"][i]
                entry["models"][label] = {
                    "smape_mean": self.mean(label, i), "smape": np.asarray(result["smape"][i]).tolist(),
                    "ratios": {b: self.ratio(label, b, i) for b in self.baselines},
                    "targets": [{"baseline": b, "ratio": r, "target": t, "met": bool(ok)}
                                for b, r, t, ok in self.checks(label, i)],
                    "flagged_share": None if share is None else share.tolist(),
                    "flagged_trials": self.flagged(label, i)}
            entries.append(entry)
        return {"system": self.system, "param_names": list(self.param_names), "param_box": self.param_box,
                "settings": asdict(self.settings), "pf_particles": self.pf_particles, "flag_share": FLAG_SHARE,
                "targets": {k: [list(t) for t in v] for k, v in TARGETS.items()}, "cases": entries, **self.extra,
                **({"consistency": uncertainty_record(self.consistency)} if self.consistency else {})}

    def plot(self, path: Any, *, stamp: Optional[provenance.Stamp] = None) -> None:
        """Per model, each case's ratio to every baseline, the targets drawn, as a PNG to ``path`` (a file path or a
        binary stream); ``stamp`` (default: this process's) goes into the PNG's metadata."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        names = [b for b in ("ekf", "tuned", "augmented", "pf") if b in self.baselines]
        fig, axes = plt.subplots(len(self.models), 1, figsize=(max(8, 0.7 * len(self.cases) + 3),
                                                               3.2 * len(self.models)), squeeze=False)
        x = np.arange(len(self.cases))
        width = 0.8 / len(names)
        for ax, label in zip(axes[:, 0], self.models):
            for j, b in enumerate(names):
                ratios = [self.ratio(label, b, i) for i in range(len(self.cases))]
                ax.bar(x + (j - (len(names) - 1) / 2) * width, ratios, width, label=f"{label} / {b}")
            for i, case in enumerate(self.cases):
                for b, target in case.targets:
                    if b in names:
                        j = names.index(b)
                        centre = x[i] + (j - (len(names) - 1) / 2) * width
                        ax.hlines(target, centre - width / 2, centre + width / 2, colors="k", linewidth=2)
            ax.axhline(1.0, color="grey", linewidth=0.8, linestyle=":")
            ax.set_xticks(x, [c.name for c in self.cases], rotation=30, ha="right")
            ax.set_ylabel("mean SMAPE ratio")
            ax.set_title(f"{self.system}: {label} against the baselines (black: the targets)")
            ax.legend(fontsize=8, ncol=len(names), loc="upper left", bbox_to_anchor=(0, -0.35))
        fig.tight_layout()
        fig.savefig(path, format="png", dpi=110, metadata=provenance.png_metadata(stamp or provenance.stamp()))
        plt.close(fig)


def _box_text(box: Sequence[Sequence[float]]) -> str:
    return " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in box)


def targets(report: Report, label: str) -> dict[str, bool]:
    """Per case name, whether the model meets every target of its case (the outside cases also need the
    monitor to flag at least half of the trials)."""
    out = {}
    for i, case in enumerate(report.cases):
        met = all(ok for *_, ok in report.checks(label, i))
        if case.kind == "outside":
            flagged = report.flagged(label, i)
            met = met and flagged is not None and flagged >= 0.5
        out[case.name] = met
    return out


def _model_runner(obs: KKLObserver, compiler: Optional[Compiler], n_threads: Optional[int]) -> Any:
    if obs.domain_check is not None:
        monitored = MonitoredObserver(obs, compiler=compiler, n_threads=n_threads)
        return lambda t, y, u: monitored.estimate(t, y, u)
    plain = observer_estimator(obs, compiler=compiler, n_threads=n_threads)
    return lambda t, y, u: (plain(t, y, u), None)


def _augmented(family: System, settings: Settings, tuning: TrajectoryBatch) -> tuple[AugmentedEKF, dict]:
    """The augmented EKF with and without the input-disturbance state, each tuned; the better on the tuning trials."""
    fits = [AugmentedEKF.fit(family, settings.dt, tuning, process_std=settings.noise,
                             measurement_std=settings.noise, input_disturbance=d) for d in (False, True)]
    best = min(fits, key=lambda f: f.tuning.best_score)
    record = {"input_disturbance": best is fits[1], **best.tuning.best,
              "score": best.tuning.best_score, "score_without_disturbance": fits[0].tuning.best_score,
              "score_with_disturbance": fits[1].tuning.best_score}
    return best, record


def run(observers: Sequence[tuple[str, KKLObserver]], family: System, case_list: Sequence[RobustCase],
        settings: Settings = Settings(), *, trials: Optional[TrialCache] = None, pf_particles: Optional[int] = None,
        pf_trials: Optional[int] = None, pf_roughening: float = ROUGHENING,
        compiler: Optional[Compiler] = DEFAULT_COMPILER, n_threads: Optional[int] = None,
        consistency: bool = False, progress: bool = False) -> Report:
    """Score observers of one plant family and the baselines on every case.

    Parameters
    ----------
    observers : sequence of (label, KKLObserver)
        Observers of ``family``'s nominal plant.
    family : System
        The plant with its parameters and their box.
    case_list : sequence of RobustCase
        See :func:`cases`.
    settings : Settings
    trials : TrialCache, optional
        Where the trials come from (default: simulated for this call).
    pf_particles : int, optional
        Run the particle filter over states and parameters with this many particles.
    pf_trials : int, optional
        Run it on the first this many scored trials of each case only (default: all); its ratios compare the
        observers on the same trials, and the table says so.
    pf_roughening : float
        Its roughening of the states.
    compiler : Compiler or None
        How the observers and the particle filter are compiled (None: the CasADi VM); the EKFs run in the VM.
    n_threads : int, optional
    consistency : bool
        Also score every covariance on each case's trials (:attr:`Report.consistency`): the observers with a
        covariance head (the others have none), the EKF's, the tuned EKF's, the augmented EKF's on the plant's states
        and the particle filter's (on its trials), as ``kklcasadi evaluate --consistency`` scores them.
    progress : bool

    Returns
    -------
    Report
        Trials that failed in the simulation are left out of their case (for every estimator).
    """
    if not observers:
        raise error("observers", "at least one (label, observer)", Text("none"))
    if not family.n_params:
        raise error("family", "a plant with parameters", Text(f"plant {family.name!r} without parameters"))
    nominal = family.at(family.param_nominal)
    for label, obs in observers:
        if obs.system.fingerprint != nominal.fingerprint:
            raise error("observers", f"observers of the family's nominal plant ({family.name!r})",
                        Text(f"{label!r} for another plant {obs.system.name!r}"))
    if pf_particles is not None:
        positive_int(pf_particles, "pf_particles")
    if pf_trials is not None:
        positive_int(pf_trials, "pf_trials")
        if pf_particles is None:
            raise error("pf_trials", "None without pf_particles (no particle filter runs)", pf_trials)
    trials = TrialCache(None) if trials is None else trials
    runners = {label: _model_runner(obs, compiler, n_threads) for label, obs in observers}
    uncertain = {label: observer_uncertainty(obs, compiler=compiler, n_threads=n_threads) for label, obs in observers
                 if consistency and obs.covariance is not None}
    rows: list[UncertaintyRow] = []
    models = {label: {"smape": [], "flagged_share": []} for label in runners}
    baselines: dict[str, list] = {b: [] for b in BASELINES if b != "pf" or pf_particles is not None}
    tuning_records = []
    for case in tqdm(list(case_list), desc=family.name, unit="case", disable=not progress):
        batch = trials.trials(family, RobustCell(case, settings))
        tuning = trials.trials(family, RobustCell(case, settings, tuning=True))
        ok = batch.ok
        t, x, y, u = batch.t, batch.x[ok], batch.y[ok], batch.u[ok]
        after = t >= settings.t_settle
        escaped = int((~ok).sum())
        for label, runner in runners.items():
            xhat, inside = runner(t, y, u)
            models[label]["smape"].append(metrics.smape(x, xhat, angles=family.angle_states))
            models[label]["flagged_share"].append(None if inside is None else (~inside[:, after]).mean(axis=1))
            if label in uncertain:
                rows.append(uncertainty_row(label, family, case.name, t, x, *uncertain[label](t, y, u),
                                            smape=models[label]["smape"][-1], escaped=escaped))
        case_rows = []

        def score(name: str, est: Any, part: Callable[[np.ndarray], np.ndarray] = np.asarray) -> None:
            """A baseline's SMAPE on the case's trials (its first ``len(xhat)``) from its estimate ``est`` (``part``:
            the plant's states of it), and its covariance's consistency."""
            xhat = part(est.xhat)
            baselines[name].append(metrics.smape(x[:len(xhat)], xhat, angles=family.angle_states))
            if consistency:
                case_rows.append(uncertainty_row(TITLES[name], family, case.name, t, x[:len(xhat)], xhat,
                                                 part(est.var), smape=baselines[name][-1], escaped=escaped))

        score("ekf", case_ekf(nominal, settings.noise, settings.dt).simulate(t, y, u, n_threads=n_threads))
        tuned = TunedEKF.fit(nominal, settings.dt, tuning, process_std=settings.noise, measurement_std=settings.noise)
        score("tuned", tuned.simulate(t, y, u, n_threads=n_threads))
        aekf, record = _augmented(family, settings, tuning)
        score("augmented", aekf.simulate(t, y, u), lambda a: aekf.split(a)[0])
        tuning_records.append({"tuned": {**tuned.tuning.best, "score": tuned.tuning.best_score,
                                         "grid": tuned.tuning.to_json()},
                               "augmented": record, "tuning_trials": int(tuning.ok.sum())})
        if pf_particles is not None:
            how = {"jit": False} if compiler is None else {"compile": compiler.compile}
            pf = ParameterPF(family, settings.dt, n_particles=pf_particles, process_std=settings.noise,
                             measurement_std=settings.noise, noise_model=case.noise_model,
                             substeps=substeps_for(family, settings.dt, SUBSTEPS), roughening=pf_roughening,
                             seed=settings.seed,
                             n_threads=n_threads, **how)
            k = len(x) if pf_trials is None else min(pf_trials, len(x))
            score("pf", pf.simulate(t, y[:k], u[:k]), lambda a: pf.split(a)[0])
        rows += case_rows
    return Report(family.name, family.param_names, family.param_box.tolist(), settings, list(case_list), models,
                  baselines, tuning_records, pf_particles,
                  {"pf_roughening": None if pf_particles is None else pf_roughening, "pf_trials": pf_trials,
                   "pf_shrinkage": None if pf_particles is None else SHRINKAGE}, rows)
