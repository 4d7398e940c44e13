"""The operational runs: noisy simulated runs of a plant under the training families' inputs.

The runs start from initial states in the X0 box, take inputs from the ``train`` (or ``wide``) ranges of
:mod:`kklcasadi.plant.signals` and the families of :data:`FAMILIES` (open loop, or closed around the noisy
output), and carry process and measurement noise at levels drawn per run about the design level. A ``bank``
decoder is fitted on the latents the observer sees along them (:mod:`kklcasadi.model.operational`); no torch.

Budgets count simulated seconds and runs, not samples: the runs are simulated in chunks (a progress
bar per chunk). A run whose state escapes (leaves the X0 box scaled by ``escape_scale`` about its
centre, angle states compared on the circle, or fails in the integrator) is cut there.

* :class:`RolloutConfig` -- the runs' recipe: how many, how long, families, ranges, noise, sample times.
* :func:`rollouts` -- the runs themselves (full trajectories of the runs that did not escape).
* :func:`fit_families` -- the families of a recipe with their parameter ranges (a card's ``fit_families``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator, Mapping, Sequence

import numpy as np
from tqdm.auto import tqdm

from . import signals as sig
from .design import time_scales
from .simulate import TrajectoryBatch, simulate_batch, step_function, time_grid
from .systems import System

__all__ = ["RolloutConfig", "rollouts", "RK_STEP", "FAMILIES", "DEFAULT_KINDS", "PD_RANGES", "ROLLOUT_REGIMES",
           "fit_families", "loop_signs"]

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
    escape_scale : float
        A run is cut where its state leaves the X0 box scaled by this about its centre.
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
    method: str = "rk"
    substeps: int | None = None
    box_scale: float | tuple[float, float] = 1.0
    box_share: float = 1.0
    escape_scale: float = 10.0
    sample_period: float = 0.1
    dense_period: float = 0.05
    dense_time: float = 5.0
    chunk: int = 100

    def __post_init__(self) -> None:
        if not isinstance(self.n_traj, int) or self.n_traj < 1:
            raise ValueError(f"n_traj: expected a positive integer, received {self.n_traj!r}.")
        if self.regime not in ROLLOUT_REGIMES:
            raise ValueError(f"regime: expected one of {list(ROLLOUT_REGIMES)}, received {self.regime!r}.")
        bad = [k for k in self.kinds if k not in FAMILIES]
        if bad or not self.kinds:
            raise ValueError(f"kinds: expected a non-empty subset of {FAMILIES}, received {self.kinds!r}.")
        lo, hi = self.noise_range
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise ValueError(f"noise_range: expected factors 0 < lo <= hi, received {self.noise_range!r}.")
        scales = np.atleast_1d(np.asarray(self.box_scale, dtype=float))
        if scales.size not in (1, 2) or not np.all(np.isfinite(scales)) or not (0 < scales[0] <= scales[-1]):
            raise ValueError(f"box_scale: expected a factor > 0 or a range 0 < lo <= hi, received {self.box_scale!r}.")
        if not (isinstance(self.box_share, (int, float)) and 0 < self.box_share <= 1):
            raise ValueError(f"box_share: expected a share in (0, 1], received {self.box_share!r}.")
        for name in ("T", "escape_scale", "sample_period", "dense_period"):
            if not (getattr(self, name) > 0 and math.isfinite(getattr(self, name))):
                raise ValueError(f"{name}: expected a finite number > 0, received {getattr(self, name)!r}.")
        if not self.dense_time >= 0:
            raise ValueError(f"dense_time: expected a number >= 0 (seconds), received {self.dense_time!r}.")
        if self.substeps is not None and (not isinstance(self.substeps, int) or self.substeps < 1):
            raise ValueError(f"substeps: expected a positive integer or None, received {self.substeps!r}.")
        if not isinstance(self.chunk, int) or self.chunk < 1:
            raise ValueError(f"chunk: expected a positive integer, received {self.chunk!r}.")



def _keep(n: int, dt: float, config: RolloutConfig, rate: float = 1.0) -> np.ndarray:
    """The kept samples of a run of ``n`` as a mask (N,): the first sample in each ``dense_period``
    over the first ``dense_time``, and in each ``sample_period`` after (every sample where the period
    is shorter than ``dt``); the times are in units of ``1 / rate``."""
    t = np.arange(n) * dt * rate                   # in units of 1 / rate
    eps = 1e-9
    dense_bins = np.ceil(config.dense_time / config.dense_period - eps)
    bins = np.where(t < config.dense_time, np.floor(t / config.dense_period + eps),
                    dense_bins + np.floor((t - config.dense_time) / config.sample_period + eps))
    return np.concatenate([[True], bins[1:] != bins[:-1]])


def _horizon(T: float, rate: float, dt: float) -> float:
    """``T / rate`` seconds rounded to whole samples (at least 2)."""
    return max(2, int(round(T / rate / dt))) * dt


def _substeps(system: System, config: RolloutConfig, dt: float) -> int:
    if config.substeps is not None:
        return config.substeps
    omega, _ = time_scales(system)
    return max(1, int(math.ceil(dt * omega / RK_STEP)))


def _escaped(system: System, x: np.ndarray, scale: float) -> np.ndarray:
    """First escaped sample of each run (M,), ``N`` where none: outside the X0 box scaled by ``scale``
    about its centre (angle states on the circle: never), or not finite."""
    lo, hi = system.x0_box[:, 0], system.x0_box[:, 1]
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * scale
    dev = x - centre
    if system.angle_states:
        a = list(system.angle_states)
        dev[..., a] = np.angle(np.exp(1j * dev[..., a]))
    with np.errstate(invalid="ignore"):
        bad = ~np.all(np.abs(dev) <= half, axis=-1)
    return np.where(bad.any(axis=1), bad.argmax(axis=1), x.shape[1])


def _initial_states(system: System, config: RolloutConfig, seed: int) -> np.ndarray:
    """The runs' initial states (n_traj, nx): a Latin hypercube over the X0 box, scaled about its centre."""
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


def fit_families(config: RolloutConfig, rate: float = 1.0) -> dict[str, dict[str, tuple[float, float]]]:
    """The input families of ``config``'s runs with the range of each parameter, as a card's
    ``fit_families`` records them (frequencies in rad/s and holds in seconds at the time scale ``rate``).

    The benchmark's families carry :func:`kklcasadi.plant.signals.family_ranges`' parameters;
    ``multisine`` its tones' amplitude and frequency ranges and their number; ``feedback`` (a
    proportional law, not the PD law of the held-out family of that name) its gain, hold and limit;
    ``pd`` (:data:`PD_RANGES`) also its derivative time and lag.
    """
    out: dict[str, dict[str, tuple[float, float]]] = {}
    sine = _ranges("sinusoid", config.regime)
    for kind in config.kinds:
        if kind == "zero":
            out[kind] = {}
        elif kind in ("constant", "sinusoid", "square"):
            out[kind] = {name: ((lo * rate, hi * rate) if name == "omega" else (lo, hi))
                         for name, (lo, hi) in _ranges(kind, config.regime).items()}
        elif kind == "multisine":
            out[kind] = {"amplitude": sine["amplitude"], "omega": (sine["omega"][0] * rate, sine["omega"][1] * rate),
                         "tones": (2.0, 6.0)}
        else:
            limit = float(_ranges("constant", config.regime)["value"][1])
            out[kind] = {"gain": (0.5, 3.0), "hold": (2.0 / rate, 10.0 / rate), "limit": (limit, limit)}
            if kind == "pd":
                out[kind].update(gain=PD_RANGES["gain"],
                                 **{name: (lo / rate, hi / rate) for name, (lo, hi) in PD_RANGES.items()
                                    if name != "gain"})
    return out


@dataclass(frozen=True)
class _Feedback:
    """``u_k = clip((gain (r(t_k) - y_k[j]) - dgain dyf_k[j]) / y_scale, -limit, limit)`` per input, ``r``
    piecewise constant, ``dyf_k`` the rate of the output through a first-order lag of time constant
    ``lag`` (``dgain = 0``: a proportional law)."""

    gain: np.ndarray          # (nu,)
    output: np.ndarray        # (nu,) output index per input
    y_scale: np.ndarray       # (nu,)
    limit: float
    times: np.ndarray         # (L,) switching times, first 0
    levels: np.ndarray        # (L, nu) set points
    dgain: np.ndarray | None = None   # (nu,) derivative gains (gain times the derivative time)
    lag: float = 0.0

    def __call__(self, t: float, y: np.ndarray, dyf: np.ndarray) -> np.ndarray:
        r = self.levels[np.searchsorted(self.times, t, side="right") - 1]
        v = self.gain * (r - y[self.output])
        if self.dgain is not None:
            v = v - self.dgain * dyf[self.output]
        return np.clip(v / self.y_scale, -self.limit, self.limit)


def _draw_input(kind: str, rng: np.random.Generator, regime: str, system: System, t: np.ndarray,
                y_range: np.ndarray, rate: float) -> object:
    """One run's input: a signal or samples (N, nu) for open-loop kinds, a :class:`_Feedback` law.

    Frequencies are the regime's times ``rate`` and hold times the regime's over ``rate`` (the
    plant's time scale; 1 for the shipped systems, whose draws are those of
    :func:`kklcasadi.plant.signals.sample`)."""
    nu = system.nu
    if kind == "zero":
        return sig.make("zero", size=nu)
    if kind in ("constant", "sinusoid", "square"):
        r = _ranges(kind, regime)
        if kind == "constant":
            return sig.make("constant", value=rng.uniform(*r["value"], size=nu))
        amplitude = rng.uniform(*r["amplitude"], size=nu)
        omega = rng.uniform(*r["omega"]) * rate
        return sig.make(kind, amplitude=amplitude, omega=omega, phase=rng.uniform(0.0, 2.0 * np.pi))
    sine = _ranges("sinusoid", regime)
    if kind == "multisine":          # a random spectrum: 2-6 tones, log-uniform frequencies
        k = int(rng.integers(2, 7))
        omega = np.exp(rng.uniform(*np.log(sine["omega"]), size=(k, 1))) * rate
        weights = rng.dirichlet(np.ones(k), size=nu).T                     # (k, nu)
        amplitude = rng.uniform(*sine["amplitude"], size=nu)
        phase = rng.uniform(0.0, 2.0 * np.pi, size=(k, nu))
        return np.einsum("kn,tkn->tn", weights * amplitude, np.sin(omega[None] * t[:, None, None] + phase[None]))
    limit = float(_ranges("constant", regime)["value"][1])
    holds = rng.uniform(2.0, 10.0, size=int(np.ceil(t[-1] * rate / 2.0)) + 1) / rate
    times = np.concatenate([[0.0], np.cumsum(holds)])[:-1]
    lo, hi = y_range
    output = np.arange(nu) % system.ny
    levels = rng.uniform(lo[output], hi[output], size=(times.size, nu))
    y_scale = np.maximum(0.5 * (hi - lo)[output], 1e-9)
    if kind == "feedback":
        return _Feedback(rng.uniform(0.5, 3.0, size=nu) * rng.choice([-1.0, 1.0], size=nu), output, y_scale, limit,
                         times, levels)
    gain = rng.uniform(*PD_RANGES["gain"], size=nu) * loop_signs(system)
    dgain = gain * rng.uniform(*PD_RANGES["derivative_time"], size=nu) / rate
    return _Feedback(gain, output, y_scale, limit, times, levels, dgain, rng.uniform(*PD_RANGES["lag"]) / rate)


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
                 seeds: Sequence[object], v: np.ndarray, method: str, substeps: int) -> TrajectoryBatch:
    """Runs under their feedback laws, one sample at a time (``v``: the measurement noise (M, N, ny))."""
    m, n = len(x0), t.size
    dt = float(t[1] - t[0])
    step = step_function(system, dt, method, substeps=substeps).map(m)
    h = system.h.map(m)
    w = np.stack([np.random.default_rng(s).normal(0.0, 1.0, (n - 1, system.nx)) for s in seeds]) * process
    x = np.full((m, n, system.nx), np.nan)
    u, y = np.zeros((m, n, system.nu)), np.zeros((m, n, system.ny))
    x[:, 0] = x0
    pull = np.array([1.0 - np.exp(-dt / law.lag) if law.lag > 0 else 1.0 for law in laws])[:, None]
    yf = np.zeros((m, system.ny))
    for k in range(n):
        y[:, k] = np.asarray(h(x[:, k].T)).T + v[:, k]
        yf_next = y[:, k] if k == 0 else yf + pull * (y[:, k] - yf)       # the lagged output, from y_0
        dyf = (yf_next - yf) / dt if k else np.zeros_like(yf)
        yf = yf_next
        for i in np.flatnonzero(np.all(np.isfinite(y[:, k]), axis=1)):       # runs that have not blown up
            u[i, k] = laws[i](t[k], y[i, k], dyf[i])
        if k < n - 1:
            with np.errstate(invalid="ignore", over="ignore"):
                x[:, k + 1] = np.asarray(step(x[:, k].T, np.concatenate([u[:, k], w[:, k]], axis=1).T)).T
                x[:, k + 1][~(np.abs(x[:, k + 1]) < 1e6)] = np.nan
    ok = np.all(np.isfinite(x), axis=(1, 2))
    return TrajectoryBatch(t, x, u, y, ok)


def _chunks(system: System, config: RolloutConfig, seed: int, dt: float, measurement_std: float,
            process_std: float | Sequence[float], rate: float, progress: bool,
            desc: str) -> Iterator[tuple[TrajectoryBatch, np.ndarray, dict]]:
    """The runs, ``config.chunk`` at a time: each chunk's batch (``y`` carries the measurement noise),
    the first escaped sample of each run, and the chunk's noise factors."""
    rng = np.random.default_rng([seed, 1])
    horizon = _horizon(config.T, rate, dt)
    t = time_grid(horizon, dt)
    x0 = _initial_states(system, config, seed)
    y_range = np.quantile(system.h_batch(system.sample_box(256, seed + 1)), [0.05, 0.95], axis=0)
    inputs = [_draw_input(config.kinds[i % len(config.kinds)], rng, config.regime, system, t, y_range, rate)
              for i in range(config.n_traj)]
    seeds = np.random.SeedSequence([seed, 2]).spawn(config.n_traj)
    noise = np.random.default_rng([seed, 3])
    log_lo, log_hi = np.log(config.noise_range)
    substeps = _substeps(system, config, dt)
    process = np.asarray(process_std, dtype=float)
    with tqdm(total=config.n_traj, desc=desc, unit="run", disable=not progress, leave=False) as bar:
        for start in range(0, config.n_traj, config.chunk):
            idx = np.arange(start, min(start + config.chunk, config.n_traj))
            p_factor = float(np.exp(noise.uniform(log_lo, log_hi)))
            m_factor = np.exp(noise.uniform(log_lo, log_hi, len(idx)))
            v = noise.normal(size=(len(idx), t.size, system.ny)) * (measurement_std * m_factor)[:, None, None]
            loop = np.array([isinstance(inputs[i], _Feedback) for i in idx])
            x = np.full((len(idx), t.size, system.nx), np.nan)
            u, y = np.zeros((len(idx), t.size, system.nu)), np.zeros((len(idx), t.size, system.ny))
            for part, closed in ((idx[~loop], False), (idx[loop], True)):
                if not part.size:
                    continue
                where = part - start
                if closed:
                    batch = _closed_loop(system, x0[part], [inputs[i] for i in part], t, process * p_factor,
                                         [seeds[i] for i in part], v[where], config.method, substeps)
                    y[where] = batch.y
                else:
                    batch = simulate_batch(system, x0[part], [inputs[i] for i in part], horizon, dt,
                                           process_std=process * p_factor, seed=[seeds[i] for i in part],
                                           method=config.method, substeps=substeps)
                    y[where] = np.asarray(batch.y) + v[where]
                x[where], u[where] = batch.x, batch.u
            escape = _escaped(system, x.copy(), config.escape_scale)
            bar.update(len(idx))
            yield (TrajectoryBatch(t, x, u, y, escape == t.size), escape,
                   {"process": p_factor, "measurement": m_factor, "substeps": substeps})


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
