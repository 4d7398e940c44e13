"""The operational runs: noisy simulated runs of a plant under the training families' inputs.

The runs start from initial states in the X0 box, take inputs from the ``train`` (or ``wide``) ranges of
:mod:`kklcasadi.plant.signals` and the families of :data:`FAMILIES` (open loop, or closed around the noisy
output), and carry process and measurement noise at levels drawn per run about the design level (the
measurement noise of a model of :mod:`kklcasadi.plant.noise` drawn per run among ``noise_models``), and,
for a plant with parameters, the parameters of each run drawn from the plant's box. A ``bank``
decoder is fitted on the latents the observer sees along them (:mod:`kklcasadi.model.operational`); no torch.

Budgets count simulated seconds and runs, not samples: the runs are simulated in chunks (a progress
bar per chunk). A run whose state escapes (leaves the X0 box scaled by ``escape_scale`` about its
centre, angle states compared on the circle, or fails in the integrator) is cut there.

* :class:`RolloutConfig` -- the runs' recipe: how many, how long, families, ranges, noise, sample times.
* :func:`rollouts` -- the runs themselves (full trajectories of the runs that did not escape).
* :func:`fit_families` -- the families of a recipe with their parameter ranges (a card's ``fit_families``).

Over 600 lines: one concept, how a training run is drawn (the recipe's checks and documentation are a
fifth of it; the families' inputs, the loops they run under, the envelope's replayed runs and the chunked
simulation share the recipe's private helpers). The feedback laws (``_Feedback`` to ``_closed_loop``) are
the part that could leave for a module of their own once issue 45's work on these runs has settled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Iterator, Mapping, Optional, Sequence

import numpy as np
from tqdm.auto import tqdm

from ..validation import Text, error
from . import signals as sig
from .design import time_scales
from .envelope import LIKE_AMPLITUDE_FACTORS, LIKE_TIME_FACTORS, OUTPUT_MARGIN, Envelope
from .noise import GAUSS, NoiseModel, noise_model
from .simulate import TrajectoryBatch, simulate_batch, step_function, time_grid
from .systems import System, read_states

__all__ = ["RolloutConfig", "rollouts", "RK_STEP", "FAMILIES", "DEFAULT_KINDS", "PD_RANGES", "ROLLOUT_REGIMES",
           "fit_families", "input_factors", "loop_signs", "drifting_states", "input_range", "declares_envelope",
           "resolved", "ENVELOPE_ESCAPE", "LEGACY_ESCAPE", "ENVELOPE_FIT_AFTER", "LOG_INPUT_MARGIN", "inside_box"]

#: Input families of the runs (:attr:`RolloutConfig.kinds`): the benchmark's four; ``multisine``, a
#: random spectrum (2-6 tones with log-uniform frequencies over the sinusoid's range and Dirichlet
#: weights of a sinusoid's amplitude); ``feedback``, a closed loop ``u_k = clip(g (r - y_k) / s, -l, l)``
#: around a set point ``r`` redrawn every 2-10 s within the outputs' range over the box (gain
#: ``|g|`` in [0.5, 3] of either sign, limit ``l`` the regime's largest constant input); ``pd``, what a
#: controller with derivative action sends,
#: ``u_k = clip((g (r - y_k) - g T_d (yf_k - yf_k-1) / dt) / s, -l, l)`` with ``yf`` the output through a
#: first-order lag of time constant ``tau`` (:data:`PD_RANGES`; the sign of ``g`` the one that feeds
#: back negatively, :func:`loop_signs`; set points and limit as ``feedback``'s). ``pd`` is not a default
#: family (:data:`DEFAULT_KINDS`): ask for it (``kklcasadi train --kinds``).
FAMILIES = (*sig.BENCHMARK_KINDS, "multisine", "feedback", "pd")
#: The families of :attr:`RolloutConfig.kinds` by default.
DEFAULT_KINDS = (*sig.BENCHMARK_KINDS, "multisine", "feedback")
#: Ranges of the ``pd`` family's gain ``|g|``, derivative time ``T_d`` and lag ``tau`` (the times in units of
#: ``1 / time_scale``).
PD_RANGES = {"gain": (0.5, 5.0), "derivative_time": (0.1, 1.5), "lag": (0.05, 0.5)}
#: Parameter ranges of the runs: those of :data:`kklcasadi.plant.signals.REGIMES`, or ``wide``, the hull
#: of the ``id`` and ``ood`` ranges of docs/protocol.md.
ROLLOUT_REGIMES = (*sig.REGIMES, "wide")
#: Largest RK4 step of the plant in units of its time scale (``h * omega``) when ``substeps`` is None.
RK_STEP = 0.05
#: ``escape_scale`` where the plant declares where it lives (a ``u_box``, or an envelope from its logs) and
#: the recipe leaves it to the plant (None): a run leaving the X0 box by a quarter of its half-width is cut.
ENVELOPE_ESCAPE = 1.25
#: ``escape_scale`` where it does not (the runs of the benchmark's conventions).
LEGACY_ESCAPE = 10.0
#: ``fit_after`` where the plant declares where it lives and the recipe leaves it to the plant: chosen on the
#: EMPS run's development part, where it halved the velocity error of its noise copy's decoder (6.7e-4 -> 3.4e-4
#: m/s; the copy's transient from the box centre had taken the squared error).
ENVELOPE_FIT_AFTER = 0.5
#: Without a ``u_box``, the families' input range from logs is the logged inputs' range widened by this
#: share of its half-width on each side (a rig run harder than its logs stays covered).
LOG_INPUT_MARGIN = 0.25


@dataclass(frozen=True)
class RolloutConfig:
    """The noisy operational runs and the samples the decoder takes from them.

    The noise levels and the sample period are the caller's (:func:`operational_data`).

    Attributes
    ----------
    n_traj : int
        Number of runs, spread evenly over ``kinds`` (round-robin).
    T : float
        Horizon of each run (docs/protocol.md: 50 s). This and every time below are in units of
        ``1 / time_scale`` (seconds for the shipped systems, whose time scale is 1; see
        :func:`operational_data`), and the inputs' frequencies in units of ``time_scale``.
    kinds : tuple of str
        Input families (:data:`FAMILIES`), in turn over the runs; the card records them.
    regime : str
        Parameter ranges (:data:`ROLLOUT_REGIMES`: ``train``, or ``wide`` up to the ood ranges;
        never the protocol's test draws).
    noise_range : (float, float)
        Each run's noise levels are the nominal ones times factors drawn log-uniformly from this
        range (measurement noise per run, process noise per chunk of runs); ``(1, 1)``: the nominal
        levels.
    noise_models : tuple of str
        The measurement noise's model (:mod:`kklcasadi.plant.noise`: ``gauss``, ``student-t:NU``,
        ``outliers:P,K``, ``quantised:STEP``, combined with ``+``), its scale the run's measurement
        std; with several, each run's drawn uniformly among them (``default_rng([seed, 3])``, after
        the chunk's noise factors).
    method, substeps : str, int or None
        Plant integrator (see :func:`kklcasadi.plant.simulate.step_function`); ``substeps=None``
        takes the fewest RK4 steps per sample with ``h * omega <= RK_STEP`` (``omega``: the plant's
        time scale, :func:`kklcasadi.plant.design.time_scales`).
    box_scale : float or (float, float)
        Scale of the X0 box (about its centre) the initial states are drawn from, or a range: each
        run's initial state scaled about the centre by a factor drawn uniformly from it (a wider
        spread of energies, e.g. the upper branch of a hardening resonance).
    box_share : float
        With a ``box_scale`` range: the share of the runs (drawn at random) whose initial state is
        scaled so; the others start in the X0 box itself (a few runs reach far states without
        spending the fit on them).
    escape_scale : float or None
        A run is cut where its state leaves the X0 box scaled by this about its centre (counted in the
        card); None: :data:`ENVELOPE_ESCAPE` where the plant declares where it lives
        (:func:`declares_envelope`), else :data:`LEGACY_ESCAPE` (:func:`resolved`).
    stabilise : bool or None
        Run every open-loop family under a PD loop around set points in the outputs' range (the
        ``pd`` family's law, its input added to the family's, scaled by a factor drawn from
        :data:`FEEDFORWARD_FACTORS`), and the ``feedback`` family with the sign that feeds back negatively, as a
        rig runs under its controller: the plant's integrators then cover the box rather than drift out of it.
        None: where the plant has drifting states (:func:`drifting_states`).
    envelope : Envelope or None
        The rig's envelope from its logs (:func:`kklcasadi.estimators.noise.rig_envelope`): a share
        ``like_share`` of the runs replays segments of the logged inputs (``like``: resampled in time and
        rescaled by factors :data:`kklcasadi.plant.envelope.LIKE_TIME_FACTORS`,
        :data:`~kklcasadi.plant.envelope.LIKE_AMPLITUDE_FACTORS`) from the state the rig was in at the
        segment's start (under the loop of ``stabilise``, around the logged outputs); the other runs start
        at states the rig was in too (the logs' energies), and every run is cut where an output that is not
        an angle leaves the logged range widened by :data:`~kklcasadi.plant.envelope.OUTPUT_MARGIN` of its
        width (an angle turns freely).
    like_share : float
        With an envelope: the share of the runs that are ``like`` runs.
    input_scale : float or (float, float)
        A factor on every family's input (not on ``like`` runs), or a range each run's factor is drawn from
        log-uniformly (``default_rng([seed, 8])``; the runs at 1 are those without it): the open-loop families'
        inputs and the ``feedback`` and ``pd`` laws' limit scaled about the input range's centre. Beyond 1 the
        runs reach larger inputs than the regime's ranges (the card's ``fit_families`` say how far): meant for
        a distilled student (``BankConfig.teacher``), which only copies its teacher and may be fit on runs
        wider than the teacher's (docs/design.md, "A compact observer").
    fit_after : float or None
        The decoder's samples start this long after each run's start (in units of ``1 / time_scale``): the
        latent's first moments from ``z = 0`` (a model copy far from the state, a filter not yet settled) are
        left out, where a squared error would spend the fit on them. None: :data:`ENVELOPE_FIT_AFTER` where
        the plant declares where it lives, else 0 (:func:`resolved`).
    sample_period, dense_period, dense_time : float
        The decoder's samples: one every ``dense_period`` seconds over the first ``dense_time``
        (the transient from ``z = 0``), one every ``sample_period`` seconds after (the first
        sample in each period; every sample where a period is shorter than ``dt``).
    chunk : int
        Runs simulated at once (the memory of a chunk is about ``chunk * T / dt * (nx + nz)`` numbers).
    """

    n_traj: int = 2000
    T: float = 50.0
    kinds: tuple[str, ...] = DEFAULT_KINDS
    regime: str = "wide"
    noise_range: tuple[float, float] = (0.5, 2.0)
    noise_models: tuple[str, ...] = ("gauss",)
    method: str = "rk"
    substeps: int | None = None
    box_scale: float | tuple[float, float] = 1.0
    box_share: float = 1.0
    escape_scale: Optional[float] = LEGACY_ESCAPE
    sample_period: float = 0.1
    dense_period: float = 0.05
    dense_time: float = 5.0
    chunk: int = 100
    stabilise: Optional[bool] = False
    envelope: Optional[Envelope] = None
    like_share: float = 0.5
    fit_after: Optional[float] = 0.0
    input_scale: float | tuple[float, float] = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.n_traj, int) or self.n_traj < 1:
            raise error("n_traj", "a positive integer", self.n_traj)
        if self.regime not in ROLLOUT_REGIMES:
            raise error("regime", f"one of {list(ROLLOUT_REGIMES)}", self.regime)
        bad = [k for k in self.kinds if k not in FAMILIES]
        if bad or not self.kinds:
            raise error("kinds", f"a non-empty subset of {FAMILIES}", self.kinds)
        if not isinstance(self.noise_models, tuple) or not self.noise_models:
            raise error("noise_models", "a non-empty tuple of noise models", self.noise_models)
        object.__setattr__(self, "noise_models", tuple(str(noise_model(m)) for m in self.noise_models))
        lo, hi = self.noise_range
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise error("noise_range", "factors 0 < lo <= hi", self.noise_range)
        scales = np.atleast_1d(np.asarray(self.box_scale, dtype=float))
        if scales.size not in (1, 2) or not np.all(np.isfinite(scales)) or not (0 < scales[0] <= scales[-1]):
            raise error("box_scale", "a factor > 0 or a range 0 < lo <= hi", self.box_scale)
        if not (isinstance(self.box_share, (int, float)) and 0 < self.box_share <= 1):
            raise error("box_share", "a share in (0, 1]", self.box_share)
        for name in ("T", "escape_scale", "sample_period", "dense_period"):
            if name == "escape_scale" and self.escape_scale is None:
                continue
            if not (getattr(self, name) > 0 and math.isfinite(getattr(self, name))):
                raise error(name, "a finite number > 0", getattr(self, name))
        if not self.dense_time >= 0:
            raise error("dense_time", "a number >= 0 (seconds)", self.dense_time)
        if self.substeps is not None and (not isinstance(self.substeps, int) or self.substeps < 1):
            raise error("substeps", "a positive integer or None", self.substeps)
        if not isinstance(self.chunk, int) or self.chunk < 1:
            raise error("chunk", "a positive integer", self.chunk)
        if self.stabilise not in (None, True, False):
            raise error("stabilise", "True, False or None (where the plant drifts)", self.stabilise)
        if self.envelope is not None and not isinstance(self.envelope, Envelope):
            raise error("envelope", "a kklcasadi.plant.envelope.Envelope or None", Text(type(self.envelope).__name__),
                        kind=TypeError)
        after = self.fit_after
        if after is not None and not (isinstance(after, (int, float)) and 0 <= after < self.T):
            raise error("fit_after", f"a time >= 0 and below T = {self.T!r}, or None", self.fit_after)
        if not (isinstance(self.like_share, (int, float)) and 0 <= self.like_share <= 1):
            raise error("like_share", "a share in [0, 1]", self.like_share)
        gains = np.atleast_1d(np.asarray(self.input_scale, dtype=float))
        if gains.size not in (1, 2) or not np.all(np.isfinite(gains)) or not 0 < gains[0] <= gains[-1]:
            raise error("input_scale", "a factor > 0 or a range 0 < lo <= hi", self.input_scale)
        object.__setattr__(self, "input_scale",                 # a card's list back as the tuple it was
                           float(gains[0]) if gains.size == 1 else (float(gains[0]), float(gains[1])))



def _keep(n: int, dt: float, config: RolloutConfig, rate: float = 1.0) -> np.ndarray:
    """The kept samples of a run of ``n`` as a mask (N,): the first sample in each ``dense_period``
    over the first ``dense_time``, and in each ``sample_period`` after (every sample where the period
    is shorter than ``dt``); the times are in units of ``1 / rate``."""
    t = np.arange(n) * dt * rate                   # in units of 1 / rate
    eps = 1e-9
    dense_bins = np.ceil(config.dense_time / config.dense_period - eps)
    bins = np.where(t < config.dense_time, np.floor(t / config.dense_period + eps),
                    dense_bins + np.floor((t - config.dense_time) / config.sample_period + eps))
    keep = np.concatenate([[True], bins[1:] != bins[:-1]])
    return keep & (t >= config.fit_after - eps) if config.fit_after else keep


def _horizon(T: float, rate: float, dt: float) -> float:
    """``T / rate`` seconds rounded to whole samples (at least 2)."""
    return max(2, int(round(T / rate / dt))) * dt


def _substeps(system: System, config: RolloutConfig, dt: float) -> int:
    if config.substeps is not None:
        return config.substeps
    omega, _ = time_scales(system)
    return max(1, int(math.ceil(dt * omega / RK_STEP)))


def drifting_states(system: System) -> tuple[int, ...]:
    """The states the plant lets drift: the non-angle state that dominates (in units of the X0 box's
    half-widths) each real mode of the plant linearised at its box centre and ``u = 0`` that does not
    decay (eigenvalue ``>= -1e-6`` times the time scale), e.g. the position of a mass that only friction
    slows. Open-loop runs of such a plant wander out of its box; an angle that turns freely does not
    (it is compared on the circle)."""
    centre = system.x0_box.mean(axis=1)
    half = 0.5 * (system.x0_box[:, 1] - system.x0_box[:, 0])
    f_x = np.asarray(system.f_jac(centre, np.zeros(system.nu))[0], dtype=float)
    values, vectors = np.linalg.eig(f_x)
    rate = time_scales(system)[0]
    out = set()
    for value, vector in zip(values, vectors.T):
        if abs(value.imag) <= 1e-6 * rate and value.real >= -1e-6 * rate:
            i = int(np.argmax(np.abs(vector) / half))
            if i not in system.angle_states:
                out.add(i)
    return tuple(sorted(out))


def declares_envelope(system: System, envelope: Optional[Envelope]) -> bool:
    """Whether the plant says where it lives: it declares a ``u_box``, or the runs have its logs' envelope."""
    return system.u_box is not None or envelope is not None


def input_range(system: System, envelope: Optional[Envelope] = None) -> tuple[Optional[np.ndarray], str]:
    """The range the runs' inputs span, (nu, 2) or None (the families' own ranges, ``|u| <= 2`` in the
    ``wide`` regime), and where it comes from: the plant's ``u_box``; else the logged inputs' range
    widened by :data:`LOG_INPUT_MARGIN` of its half-width on each side; else None."""
    if system.u_box is not None:
        return np.array(system.u_box, dtype=float), "the plant's u_box"
    if envelope is not None and envelope.u_range is not None:
        lo, hi = envelope.u_range[:, 0], envelope.u_range[:, 1]
        pad = LOG_INPUT_MARGIN * np.maximum(0.5 * (hi - lo), 1e-9)
        return np.column_stack([lo - pad, hi + pad]), (f"the logged inputs' range widened by {LOG_INPUT_MARGIN:g} "
                                                       "of its half-width (the plant declares no u_box)")
    return None, ("the benchmark's ranges (|u| <= 2 in the wide regime): the plant declares no u_box; declare the "
                  "rig's input range with kc.System(..., u_box=[[lo, hi], ...])")


def resolved(system: System, config: RolloutConfig) -> RolloutConfig:
    """``config`` with what it leaves to the plant decided: ``escape_scale`` (:data:`ENVELOPE_ESCAPE` where
    the plant declares where it lives, else :data:`LEGACY_ESCAPE`), ``stabilise`` (where the plant has
    :func:`drifting_states`) and ``fit_after`` (:data:`ENVELOPE_FIT_AFTER` where it declares where it lives)."""
    escape = config.escape_scale
    if escape is None:
        escape = ENVELOPE_ESCAPE if declares_envelope(system, config.envelope) else LEGACY_ESCAPE
    stabilise = bool(drifting_states(system)) if config.stabilise is None else config.stabilise
    fit_after = config.fit_after
    if fit_after is None:
        fit_after = ENVELOPE_FIT_AFTER if declares_envelope(system, config.envelope) else 0.0
    return replace(config, escape_scale=escape, stabilise=stabilise, fit_after=fit_after)


def inside_box(x: np.ndarray, box: np.ndarray, angles: Sequence[int] = (), *, scale: float = 1.0) -> np.ndarray:
    """Whether each state lies in ``box`` scaled by ``scale`` about its centre, shape ``x.shape[:-1]``.

    Parameters
    ----------
    x : numpy.ndarray, shape (..., nx)
    box : numpy.ndarray, shape (nx, 2)
        ``[lo, hi]`` per state.
    angles : sequence of int
        States compared on the circle: their deviation from the centre wrapped to [-pi, pi).
    scale : float
        The box's half-widths times ``scale``.

    Returns
    -------
    numpy.ndarray of bool
        False where a state is not finite.

    Raises
    ------
    ValueError
        ``box`` is not (nx, 2).
    """
    x, box = np.array(x, dtype=float), np.asarray(box, dtype=float)
    if box.shape != (x.shape[-1], 2):
        raise error("box", f"shape (nx, 2) = ({x.shape[-1]}, 2), one [lo, hi] row per state of x",
                    Text(f"shape {box.shape}"))
    lo, hi = box[:, 0], box[:, 1]
    dev = x - 0.5 * (lo + hi)
    if angles:
        a = list(angles)
        dev[..., a] = np.angle(np.exp(1j * dev[..., a]))
    with np.errstate(invalid="ignore"):
        return np.all(np.abs(dev) <= 0.5 * (hi - lo) * scale, axis=-1)


def _in_read_box(system: System, x: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """:func:`inside_box` of the X0 box over the states the plant's equations read
    (:func:`~kklcasadi.plant.systems.read_states`): a state nothing reads changes nothing a run does, so it neither
    cuts a run nor keeps a start out (every state where all are read: the test as it always was)."""
    read = read_states(system)
    if len(read) == system.nx:
        return inside_box(x, system.x0_box, system.angle_states, scale=scale)
    angles = [k for k, i in enumerate(read) if i in system.angle_states]
    return inside_box(x[..., list(read)], system.x0_box[list(read)], angles, scale=scale)


def _escaped(system: System, x: np.ndarray, scale: float) -> np.ndarray:
    """First escaped sample of each run (M,), ``N`` where none: outside the X0 box scaled by ``scale``
    about its centre (angle states compared on the circle; the states the equations read), or not finite."""
    bad = ~_in_read_box(system, x, scale)
    return np.where(bad.any(axis=1), bad.argmax(axis=1), x.shape[1])


def _output_bounds(envelope: Envelope) -> np.ndarray:
    """The logged outputs' range widened by :data:`~kklcasadi.plant.envelope.OUTPUT_MARGIN` of its width, (ny, 2)."""
    lo, hi = envelope.y_range[:, 0], envelope.y_range[:, 1]
    pad = OUTPUT_MARGIN * np.maximum(hi - lo, 1e-12)
    return np.column_stack([lo - pad, hi + pad])


def _left_outputs(y: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """First sample of each run (M,) whose output lies outside ``bounds`` (ny, 2), ``N`` where none."""
    with np.errstate(invalid="ignore"):
        bad = ~np.all((y >= bounds[:, 0]) & (y <= bounds[:, 1]), axis=-1)
    return np.where(bad.any(axis=1), bad.argmax(axis=1), y.shape[1])


def _initial_states(system: System, config: RolloutConfig, seed: int) -> np.ndarray:
    """The runs' initial states (n_traj, nx): a Latin hypercube over the X0 box, scaled about its centre;
    with an envelope, states the rig was in (drawn from the states along its logs: its energies, not the
    box's corners)."""
    if config.envelope is not None:
        starts = _starts(config.envelope, system)
        pick = starts[np.random.default_rng([seed, 6]).integers(len(starts), size=config.n_traj)]
        return np.array([config.envelope.states[i][k] for i, k in pick])
    if np.ndim(config.box_scale) == 0:
        return system.sample_box(config.n_traj, seed, scale=float(config.box_scale))
    lo, hi = config.box_scale
    centre = system.x0_box.mean(axis=1)
    draws = np.random.default_rng([seed, 4])
    factor = draws.uniform(lo, hi, (config.n_traj, 1))
    if config.box_share < 1:
        factor[draws.uniform(size=config.n_traj) >= config.box_share] = 1.0
    return centre + (system.sample_box(config.n_traj, seed) - centre) * factor


def _ranges(kind: str, regime: str) -> Mapping[str, tuple[float, float]]:
    """Parameter ranges of a benchmark kind: :data:`kklcasadi.plant.signals.RANGES`, or for ``wide`` the
    hull of the ``id`` and ``ood`` ranges."""
    if regime != "wide":
        return sig.RANGES[regime][kind]
    ranges = {}
    for name in sig.RANGES["id"][kind]:
        lo, hi = zip(sig.RANGES["id"][kind][name], sig.RANGES["ood"][kind][name])
        ranges[name] = (min(lo), max(hi))
    return ranges


def input_factors(config: RolloutConfig, seed: int) -> np.ndarray:
    """Each run's factor on its input (n_traj,): :attr:`RolloutConfig.input_scale`, drawn log-uniformly from
    ``default_rng([seed, 8])`` where it is a range."""
    scale = config.input_scale
    if not isinstance(scale, tuple):
        return np.full(config.n_traj, float(scale))
    lo, hi = np.log(scale[0]), np.log(scale[1])
    return np.exp(np.random.default_rng([seed, 8]).uniform(lo, hi, size=config.n_traj))


def _scaled_input(drawn: object, factor: float, t: np.ndarray, u_map: tuple | None) -> object:
    """A run's input (a signal, samples (N, nu) or a :class:`_Feedback` law) with its input scaled by ``factor``
    about the input range's centre (the open-loop samples; a law's limit)."""
    if factor == 1.0:
        return drawn
    if isinstance(drawn, _Feedback):
        return replace(drawn, limit=drawn.limit * factor)
    samples = np.asarray(drawn(t) if callable(drawn) else drawn, dtype=float)
    centre = 0.0 if u_map is None else u_map[0]
    return centre + factor * (samples - centre)


def fit_families(config: RolloutConfig, rate: float = 1.0,
                 system: Optional[System] = None) -> dict[str, dict[str, tuple[float, float]]]:
    """The input families of ``config``'s runs with the range of each parameter, as a card's
    ``fit_families`` records them (frequencies in rad/s and holds in seconds at the time scale ``rate``).

    The benchmark's families carry :func:`kklcasadi.plant.signals.family_ranges`' parameters;
    ``multisine`` its tones' amplitude and frequency ranges and their number; ``feedback`` (a
    proportional law, not the PD law of the held-out family of that name) its gain, hold and limit;
    ``pd`` (:data:`PD_RANGES`) also its derivative time and lag; ``like`` (with an envelope) the factors
    its log segments are resampled and rescaled by. With ``system``, values, amplitudes and limits are
    in the plant's input units (:func:`input_range`; over all inputs where they differ), and stretched by
    :attr:`~RolloutConfig.input_scale` (a range: its lowest factor on the lower bound and its highest on the
    upper one).
    """
    out: dict[str, dict[str, tuple[float, float]]] = {}
    sine = _ranges("sinusoid", config.regime)
    limit = float(_ranges("constant", config.regime)["value"][1])
    u_box = None if system is None else input_range(system, config.envelope)[0]
    low, high = (float(np.min(config.input_scale)), float(np.max(config.input_scale)))

    def units(name: str, lo: float, hi: float) -> tuple[float, float]:
        if name not in ("value", "amplitude", "limit"):
            return (lo, hi)
        lo, hi = lo * (low if lo > 0 else high), hi * (high if hi > 0 else low)
        if u_box is None:
            return (lo, hi)
        offset = u_box.mean(axis=1) if name == "value" else 0.0
        scale = 0.5 * (u_box[:, 1] - u_box[:, 0]) / limit
        return (float(np.min(offset + scale * lo)), float(np.max(offset + scale * hi)))

    for kind in config.kinds:
        if kind == "zero":
            out[kind] = {}
        elif kind in ("constant", "sinusoid", "square"):
            out[kind] = {name: ((lo * rate, hi * rate) if name == "omega" else units(name, lo, hi))
                         for name, (lo, hi) in _ranges(kind, config.regime).items()}
        elif kind == "multisine":
            out[kind] = {"amplitude": units("amplitude", *sine["amplitude"]),
                         "omega": (sine["omega"][0] * rate, sine["omega"][1] * rate), "tones": (2.0, 6.0)}
        else:
            out[kind] = {"gain": (0.5, 3.0), "hold": (2.0 / rate, 10.0 / rate), "limit": units("limit", limit, limit)}
            if kind == "pd":
                out[kind].update(gain=PD_RANGES["gain"],
                                 **{name: (lo / rate, hi / rate) for name, (lo, hi) in PD_RANGES.items()
                                    if name != "gain"})
    if config.envelope is not None and config.like_share > 0:
        out["like"] = {"time_factor": LIKE_TIME_FACTORS, "amplitude_factor": LIKE_AMPLITUDE_FACTORS}
    return out


@dataclass(frozen=True)
class _Feedback:
    """``u_k = offset + scale clip(ff_k + (gain (r(t_k) - y_k[j]) - dgain dyf_k[j]) / y_scale, -limit, limit)`` per
    input, ``r`` piecewise constant, ``dyf_k`` the rate of the output through a first-order lag of time
    constant ``lag`` (``dgain = 0``: a proportional law), ``ff`` a feedforward input (none: 0) and
    ``offset + scale v`` the map of the families' unit range onto the plant's input range (none: ``u = v``)."""

    gain: np.ndarray          # (nu,)
    output: np.ndarray        # (nu,) output index per input
    y_scale: np.ndarray       # (nu,)
    limit: float
    times: np.ndarray         # (L,) switching times, first 0
    levels: np.ndarray        # (L, nu) set points
    dgain: np.ndarray | None = None   # (nu,) derivative gains (gain times the derivative time)
    lag: float = 0.0
    feedforward: np.ndarray | None = None   # (N, nu) per sample, in the families' units
    u_map: tuple | None = None              # (offset (nu,), scale (nu,))

    def __call__(self, t: float, y: np.ndarray, dyf: np.ndarray, k: int = 0) -> np.ndarray:
        r = self.levels[np.searchsorted(self.times, t, side="right") - 1]
        v = self.gain * (r - y[self.output])
        if self.dgain is not None:
            v = v - self.dgain * dyf[self.output]
        v = v / self.y_scale
        if self.feedforward is not None:
            v = v + self.feedforward[k]
        v = np.clip(v, -self.limit, self.limit)
        return v if self.u_map is None else self.u_map[0] + self.u_map[1] * v


def _pd_law(rng: np.random.Generator, system: System, t: np.ndarray, rate: float, output: np.ndarray,
            y_scale: np.ndarray, limit: float, times: np.ndarray, levels: np.ndarray, **options: object) -> _Feedback:
    """The ``pd`` family's law: gain in :data:`PD_RANGES` with the sign that feeds back negatively."""
    nu = system.nu
    gain = rng.uniform(*PD_RANGES["gain"], size=nu) * loop_signs(system)
    dgain = gain * rng.uniform(*PD_RANGES["derivative_time"], size=nu) / rate
    return _Feedback(gain, output, y_scale, limit, times, levels, dgain, rng.uniform(*PD_RANGES["lag"]) / rate,
                     **options)


def _set_points(rng: np.random.Generator, system: System, t: np.ndarray, y_range: np.ndarray,
                rate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Set points held 2-10 time units each within ``y_range``: (times, levels (L, nu)), the output each
    input's law reads (nu,) and its scale (nu,)."""
    nu = system.nu
    holds = rng.uniform(2.0, 10.0, size=int(np.ceil(t[-1] * rate / 2.0)) + 1) / rate
    times = np.concatenate([[0.0], np.cumsum(holds)])[:-1]
    lo, hi = y_range
    output = np.arange(nu) % system.ny
    levels = rng.uniform(lo[output], hi[output], size=(times.size, nu))
    y_scale = np.maximum(0.5 * (hi - lo)[output], 1e-9)
    return times, levels, output, y_scale


#: The stabilising loop's set points (``RolloutConfig.stabilise``): tones over this band, in units of the time
#: scale, spanning the outputs' range (a reference a rig's controller would follow, not steps).
REFERENCE_BAND = (0.05, 0.5)
#: Range of the factor (log-uniform) a family's input is scaled by under the stabilising loop.
FEEDFORWARD_FACTORS = (0.05, 1.0)


def _reference(rng: np.random.Generator, system: System, t: np.ndarray, y_range: np.ndarray,
               rate: float) -> np.ndarray:
    """A smooth set point per input (N, nu) within ``y_range`` of the output it reads: 2-4 tones with
    log-uniform frequencies over :data:`REFERENCE_BAND` times ``rate`` and Dirichlet weights."""
    nu = system.nu
    output = np.arange(nu) % system.ny
    lo, hi = y_range[0][output], y_range[1][output]
    k = int(rng.integers(2, 5))
    omega = np.exp(rng.uniform(*np.log(REFERENCE_BAND), size=(k, 1))) * rate
    weights = rng.dirichlet(np.ones(k), size=nu).T
    phase = rng.uniform(0.0, 2.0 * np.pi, size=(k, nu))
    wave = np.einsum("kn,tkn->tn", weights, np.sin(omega[None] * t[:, None, None] + phase[None]))
    return 0.5 * (lo + hi) + 0.5 * (hi - lo) * wave


def _draw_input(kind: str, rng: np.random.Generator, regime: str, system: System, t: np.ndarray,
                y_range: np.ndarray, rate: float, u_map: tuple | None = None) -> object:
    """One run's input: a signal or samples (N, nu) for open-loop kinds, a :class:`_Feedback` law.

    Frequencies are the regime's times ``rate`` and hold times the regime's over ``rate`` (the
    plant's time scale; 1 for the shipped systems, whose draws are those of
    :func:`kklcasadi.plant.signals.sample`). With ``u_map = (offset, scale)`` every family's input ``v``
    (within the regime's largest constant input) becomes ``offset + scale v`` (open-loop ones as samples)."""
    nu = system.nu
    signal = None
    if kind == "zero":
        signal = sig.make("zero", size=nu)
    elif kind in ("constant", "sinusoid", "square"):
        r = _ranges(kind, regime)
        if kind == "constant":
            signal = sig.make("constant", value=rng.uniform(*r["value"], size=nu))
        else:
            amplitude = rng.uniform(*r["amplitude"], size=nu)
            omega = rng.uniform(*r["omega"]) * rate
            signal = sig.make(kind, amplitude=amplitude, omega=omega, phase=rng.uniform(0.0, 2.0 * np.pi))
    if signal is not None:
        return signal if u_map is None else u_map[0] + u_map[1] * signal(t)
    sine = _ranges("sinusoid", regime)
    if kind == "multisine":          # a random spectrum: 2-6 tones, log-uniform frequencies
        k = int(rng.integers(2, 7))
        omega = np.exp(rng.uniform(*np.log(sine["omega"]), size=(k, 1))) * rate
        weights = rng.dirichlet(np.ones(k), size=nu).T                     # (k, nu)
        amplitude = rng.uniform(*sine["amplitude"], size=nu)
        phase = rng.uniform(0.0, 2.0 * np.pi, size=(k, nu))
        samples = np.einsum("kn,tkn->tn", weights * amplitude, np.sin(omega[None] * t[:, None, None] + phase[None]))
        return samples if u_map is None else u_map[0] + u_map[1] * samples
    limit = float(_ranges("constant", regime)["value"][1])
    times, levels, output, y_scale = _set_points(rng, system, t, y_range, rate)
    if kind == "feedback":
        return _Feedback(rng.uniform(0.5, 3.0, size=nu) * rng.choice([-1.0, 1.0], size=nu), output, y_scale, limit,
                         times, levels, u_map=u_map)
    return _pd_law(rng, system, t, rate, output, y_scale, limit, times, levels, u_map=u_map)


def _starts(envelope: Envelope, system: System) -> np.ndarray:
    """The samples ``(log, k)`` (S, 2) a run may start at: after the envelope's ``settle`` seconds (the EKF's
    transient from its prior) and in the X0 box (angle states on the circle; the states the equations read: the
    EKF's estimate of a state nothing reads drifts, and the rig's widest swings would be left out by it); all
    samples where none is."""
    pairs = []
    for i, states in enumerate(envelope.states):
        ok = _in_read_box(system, states)
        ok[:int(np.ceil(envelope.settle / envelope.dt - 1e-9))] = False
        pairs.append(np.column_stack([np.full(int(ok.sum()), i), np.flatnonzero(ok)]))
    pairs = np.vstack(pairs)
    if len(pairs):
        return pairs
    return np.vstack([np.column_stack([np.full(len(s), i), np.arange(len(s))]) for i, s in enumerate(envelope.states)])


def _like_run(envelope: Envelope, rng: np.random.Generator, system: System, t: np.ndarray,
              u_box: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A ``like`` run: a segment of a log from a sample of :func:`_starts` (all equally likely) on, resampled
    in time by a factor from :data:`~kklcasadi.plant.envelope.LIKE_TIME_FACTORS` (continued
    from the log's start where it runs out) and its input rescaled about zero by one from
    :data:`~kklcasadi.plant.envelope.LIKE_AMPLITUDE_FACTORS` (clipped to ``u_box``): the state there (nx,), the
    input (N, nu) (0 for a log without inputs) and the logged outputs along it (N, ny), ``h`` of its states."""
    starts = _starts(envelope, system)
    i, start = (int(v) for v in starts[int(rng.integers(len(starts)))])
    states = envelope.states[i]
    factor, amplitude = (float(np.exp(rng.uniform(*np.log(r)))) for r in (LIKE_TIME_FACTORS, LIKE_AMPLITUDE_FACTORS))
    rows = (start + np.floor(factor * (t - t[0]) / envelope.dt).astype(int)) % len(states)
    if envelope.inputs:
        u = amplitude * envelope.inputs[i][rows]
        if u_box is not None:
            u = np.clip(u, u_box[:, 0], u_box[:, 1])
    else:
        u = np.zeros((t.size, system.nu))
    return states[start], u, system.h_batch(states[rows])


def loop_signs(system: System) -> np.ndarray:
    """The sign of each input's gain on the output its feedback law reads (nu,): of the first Markov
    parameter ``H F^k G`` (``k < nx``) of the plant linearised at its X0 box centre and ``u = 0`` that
    is not zero, +1 where none is. A law ``u = g (r - y)`` with ``g`` of this sign feeds back
    negatively (the ``pd`` family damps the plant as a controller would, rather than drive it off)."""
    centre = system.x0_box.mean(axis=1)
    f_x, f_u = (np.asarray(m, dtype=float) for m in system.f_jac(centre, np.zeros(system.nu)))
    h_x = np.asarray(system.h_jac(centre), dtype=float)
    markov = [h_x @ np.linalg.matrix_power(f_x, k) @ f_u for k in range(system.nx)]
    scale = max(float(np.abs(m).max()) for m in markov)
    signs = np.ones(system.nu)
    for j, out in enumerate(np.arange(system.nu) % system.ny):
        first = next((m[out, j] for m in markov if abs(m[out, j]) > 1e-9 * scale), 1.0)
        signs[j] = np.sign(first)
    return signs


def _closed_loop(system: System, x0: np.ndarray, laws: Sequence[_Feedback], t: np.ndarray, process: np.ndarray,
                 seeds: Sequence[object], v: np.ndarray, method: str, substeps: int, theta: np.ndarray | None = None,
                 measure: Sequence[NoiseModel] = ()) -> TrajectoryBatch:
    """Runs under their feedback laws, one sample at a time (``v``: the measurement noise (M, N, ny); ``theta``:
    the runs' parameter values (M, n_params) or None; ``measure``: each run's noise model, which quantises; default
    Gaussian)."""
    m, n = len(x0), t.size
    dt = float(t[1] - t[0])
    measure = list(measure) or [GAUSS] * m
    step = step_function(system, dt, method, substeps=substeps, parametric=theta is not None).map(m)
    h = system.h.map(m) if theta is None else system.h_param.map(m)
    held = [] if theta is None else [theta]
    w = np.stack([np.random.default_rng(s).normal(0.0, 1.0, (n - 1, system.nx)) for s in seeds]) * process
    x = np.full((m, n, system.nx), np.nan)
    u, y = np.zeros((m, n, system.nu)), np.zeros((m, n, system.ny))
    x[:, 0] = x0
    pull = np.array([1.0 - np.exp(-dt / law.lag) if law.lag > 0 else 1.0 for law in laws])[:, None]
    yf = np.zeros((m, system.ny))
    for k in range(n):
        y[:, k] = _measured(np.asarray(h(x[:, k].T, *[a.T for a in held])).T + v[:, k], measure)
        yf_next = y[:, k] if k == 0 else yf + pull * (y[:, k] - yf)       # the lagged output, from y_0
        dyf = (yf_next - yf) / dt if k else np.zeros_like(yf)
        yf = yf_next
        for i in np.flatnonzero(np.all(np.isfinite(y[:, k]), axis=1)):       # runs that have not blown up
            u[i, k] = laws[i](t[k], y[i, k], dyf[i], k)
        if k < n - 1:
            with np.errstate(invalid="ignore", over="ignore"):
                x[:, k + 1] = np.asarray(step(x[:, k].T, np.concatenate([u[:, k], w[:, k], *held], axis=1).T)).T
                x[:, k + 1][~(np.abs(x[:, k + 1]) < 1e6)] = np.nan
    ok = np.all(np.isfinite(x), axis=(1, 2))
    return TrajectoryBatch(t, x, u, y, ok)


def _inputs(system: System, config: RolloutConfig, seed: int, t: np.ndarray, rate: float,
            x0: np.ndarray) -> tuple[list, np.ndarray, list]:
    """Every run's input (a signal, samples (N, nu) or a :class:`_Feedback` law), its initial state
    (n_traj, nx) and its kind: the families in turn, and with an envelope ``like`` runs among them."""
    rng = np.random.default_rng([seed, 1])
    u_box, _ = input_range(system, config.envelope)
    limit = float(_ranges("constant", config.regime)["value"][1])
    u_map = None if u_box is None else (u_box.mean(axis=1), 0.5 * (u_box[:, 1] - u_box[:, 0]) / limit)
    y_range = (_output_bounds(config.envelope).T if config.envelope is not None else
               np.quantile(system.h_batch(system.sample_box(256, seed + 1)), [0.05, 0.95], axis=0))
    like = np.zeros(config.n_traj, dtype=bool)
    extra = np.random.default_rng([seed, 5])             # draws the legacy runs do not make
    if config.envelope is not None and config.like_share > 0:
        like[extra.permutation(config.n_traj)[:int(round(config.like_share * config.n_traj))]] = True
    kinds = [config.kinds[j % len(config.kinds)] for j in range(int((~like).sum()))][::-1]
    factors = input_factors(config, seed)
    x0 = x0.copy()
    inputs, names = [], []
    for i in range(config.n_traj):
        if like[i]:
            x0[i], u, reference = _like_run(config.envelope, extra, system, t, u_box)
            names.append("like")
            if not config.stabilise:
                inputs.append(u)
                continue
            output = np.arange(system.nu) % system.ny
            y_scale = np.maximum(0.5 * (y_range[1] - y_range[0])[output], 1e-9)
            unit = u if u_map is None else (u - u_map[0]) / u_map[1]
            inputs.append(_pd_law(extra, system, t, rate, output, y_scale, limit, t, reference[:, output],
                                  feedforward=unit, u_map=u_map))
            continue
        kind = kinds.pop()
        names.append(kind)
        drawn = _scaled_input(_draw_input(kind, rng, config.regime, system, t, y_range, rate, u_map), factors[i], t,
                              u_map)
        if config.stabilise and kind == "feedback":            # negative feedback only: the plant drifts
            drawn = replace(drawn, gain=np.abs(drawn.gain) * loop_signs(system))
        if config.stabilise and not isinstance(drawn, _Feedback):
            samples = np.asarray(drawn(t) if callable(drawn) else drawn, dtype=float)
            unit = samples if u_map is None else (samples - u_map[0]) / u_map[1]
            unit = unit * float(np.exp(extra.uniform(*np.log(FEEDFORWARD_FACTORS))))
            output = np.arange(system.nu) % system.ny
            y_scale = np.maximum(0.5 * (y_range[1] - y_range[0])[output], 1e-9)
            drawn = _pd_law(extra, system, t, rate, output, y_scale, limit, t,
                            _reference(extra, system, t, y_range, rate), feedforward=unit, u_map=u_map)
        inputs.append(drawn)
    return inputs, x0, names


def _measured(y: np.ndarray, models: Sequence[NoiseModel]) -> np.ndarray:
    """Each run's (row's) noisy output ``h(x) + v`` as its noise model measures it (quantised or not)."""
    if not any(model.step for model in models):
        return y
    out = np.array(y, dtype=float)
    for model in set(models):
        rows = np.array([m == model for m in models])
        out[rows] = model.measure(out[rows])
    return out


def _chunks(system: System, config: RolloutConfig, seed: int, dt: float, measurement_std: float,
            process_std: float | Sequence[float], rate: float, progress: bool,
            desc: str) -> Iterator[tuple[TrajectoryBatch, np.ndarray, dict]]:
    """The runs, ``config.chunk`` at a time: each chunk's batch (``y`` carries the measurement noise),
    the first escaped sample of each run, and the chunk's noise factors (``config`` as :func:`resolved`)."""
    config = resolved(system, config)
    horizon = _horizon(config.T, rate, dt)
    t = time_grid(horizon, dt)
    inputs, x0, kinds = _inputs(system, config, seed, t, rate, _initial_states(system, config, seed))
    bounds = None if config.envelope is None else _output_bounds(config.envelope)
    if bounds is not None:                         # an angle turns freely (its range on the circle bounds nothing)
        bounds[list(system.angle_outputs)] = [-np.inf, np.inf]
    seeds = np.random.SeedSequence([seed, 2]).spawn(config.n_traj)
    noise = np.random.default_rng([seed, 3])
    log_lo, log_hi = np.log(config.noise_range)
    substeps = _substeps(system, config, dt)
    process = np.asarray(process_std, dtype=float)
    theta = system.sample_params(config.n_traj, np.random.default_rng([seed, 7])) if system.n_params else None
    models = [noise_model(m) for m in config.noise_models]
    with tqdm(total=config.n_traj, desc=desc, unit="run", disable=not progress, leave=False) as bar:
        for start in range(0, config.n_traj, config.chunk):
            idx = np.arange(start, min(start + config.chunk, config.n_traj))
            p_factor = float(np.exp(noise.uniform(log_lo, log_hi)))
            m_factor = np.exp(noise.uniform(log_lo, log_hi, len(idx)))
            which = noise.integers(len(models), size=len(idx)) if len(models) > 1 else np.zeros(len(idx), int)
            if models == [GAUSS]:
                base = noise.normal(size=(len(idx), t.size, system.ny))
            else:
                base = np.stack([models[j].sample(noise, (t.size, system.ny), 1.0) for j in which])
            v = base * (measurement_std * m_factor)[:, None, None]
            measure = [models[j] for j in which]
            loop = np.array([isinstance(inputs[i], _Feedback) for i in idx])
            x = np.full((len(idx), t.size, system.nx), np.nan)
            u, y = np.zeros((len(idx), t.size, system.nu)), np.zeros((len(idx), t.size, system.ny))
            for part, closed in ((idx[~loop], False), (idx[loop], True)):
                if not part.size:
                    continue
                where = part - start
                params = None if theta is None else theta[part]
                runs_measure = [measure[i] for i in where]
                if closed:
                    batch = _closed_loop(system, x0[part], [inputs[i] for i in part], t, process * p_factor,
                                         [seeds[i] for i in part], v[where], config.method, substeps, params,
                                         runs_measure)
                    y[where] = batch.y
                else:
                    batch = simulate_batch(system, x0[part], [inputs[i] for i in part], horizon, dt,
                                           process_std=process * p_factor, seed=[seeds[i] for i in part],
                                           method=config.method, substeps=substeps, params=params)
                    y[where] = _measured(np.asarray(batch.y) + v[where], runs_measure)
                x[where], u[where] = batch.x, batch.u
            escape = _escaped(system, x.copy(), config.escape_scale)
            if bounds is not None:
                escape = np.minimum(escape, _left_outputs(y, bounds))
            bar.update(len(idx))
            yield (TrajectoryBatch(t, x, u, y, escape == t.size), escape,
                   {"process": p_factor, "measurement": m_factor, "substeps": substeps,
                    "kinds": [kinds[i] for i in idx],
                    "noise_models": [str(models[j]) for j in which],
                    "params": None if theta is None else theta[idx]})


def rollouts(system: System, config: RolloutConfig, seed: int, *, dt: float = 0.05, measurement_std: float = 0.1,
             process_std: float | Sequence[float] = 0.1, time_scale: float = 1.0,
             progress: bool = False) -> TrajectoryBatch:
    """The operational runs as whole trajectories (the runs that escaped are dropped).

    The same runs as :func:`operational_data` with the same arguments (for scoring a decoder on
    held-out runs, or caching runs for experiments).

    Returns
    -------
    TrajectoryBatch
        ``x`` (M, N, nx), ``y`` (M, N, ny), ``u`` (M, N, nu) with ``M <= n_traj``.
    """
    parts = []
    for batch, escape, _ in _chunks(system, config, seed, dt, measurement_std, process_std, time_scale, progress,
                                    "runs"):
        ok = escape == batch.t.size
        parts.append((batch.x[ok], batch.u[ok], batch.y[ok]))
    x, u, y = (np.concatenate([p[i] for p in parts]) for i in range(3))
    return TrajectoryBatch(time_grid(_horizon(config.T, time_scale, dt), dt), x, u, y, np.ones(len(x), dtype=bool))
