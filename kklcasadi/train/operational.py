"""Operational decoders: fit the decoder on the latents the observer really sees.

The observer runs on simulated noisy trajectories (initial states from the X0 box, inputs from the
``train`` ranges of :mod:`kklcasadi.plant.signals`, process and measurement noise at the design level,
``z(0) = 0`` as in the benchmark), and the decoder is fitted to the true states along those runs.
For the linear filter-bank latent of :mod:`kklcasadi.model.variants.filterbank` the latent trajectory does not
depend on the decoder, so one pass suffices.

Budgets count simulated seconds and runs, not samples: the runs are simulated in chunks (a progress
bar per chunk), the latent is run over each chunk at the model's ``dt``, and the decoder keeps
samples at fixed times (every ``dense_period`` seconds over the first ``dense_time``, every
``sample_period`` after), so the data and the fit cost about the same at any sample time. A run
whose state escapes (leaves the X0 box scaled by ``escape_scale`` about its centre, angle states
compared on the circle, or fails in the integrator) is cut there: none of its samples from the
escape on is used, and the record counts the cut runs.

* :func:`operational_data` -- the decoder's samples of the noisy runs (CasADi and numpy; no torch).
* :func:`rollouts` -- the runs themselves (full trajectories of the runs that did not escape).
* :func:`fit_bank_decoder` -- fit the decoder MLP (torch) on ``[z; y_k; u_k] -> x_k`` with an
  optional asinh output transform per state and the angle layout of
  :class:`kklcasadi.model.variants.filterbank.Angles`, and return the model arrays of ``bank``.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from ..model.variants import filterbank as fb
from ..model.variants.copies import ModelCopies
from ..nets.specs import DECODER, MLPSpec
from ..plant import signals as sig
from ..plant.design import time_scales
from ..plant.simulate import TrajectoryBatch, simulate_batch, step_function, time_grid
from ..plant.systems import System
from ..validation import error, positive_number
from .config import LoopConfig
from .loop import ArrayDataset, FitResult, fit, torch_dtype
from .nets import MLP

__all__ = ["RolloutConfig", "DecoderConfig", "OperationalData", "operational_data", "rollouts", "fit_bank_decoder",
           "BankFit", "LOSSES", "config_record", "fold_whitening", "torch_decoder", "RK_STEP", "FAMILIES",
           "DEFAULT_KINDS", "PD_RANGES", "ROLLOUT_REGIMES", "fit_families", "loop_signs"]

Tensor = torch.Tensor

#: Training losses of :func:`fit_bank_decoder`.
LOSSES = ("mse", "smape", "mse+smape")
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


@dataclass(frozen=True)
class DecoderConfig:
    """Decoder architecture and its optimisation.

    Attributes
    ----------
    hidden : tuple of int
        Hidden layer widths.
    activation : str
    loss : {"mse", "smape", "mse+smape"}
        ``mse``: mean square error of the normalised (transformed) outputs; ``smape``: the
        protocol's SMAPE of ``xhat`` (with ``smape_eps`` in the denominator); ``mse+smape``: their
        sum with weight ``smape_weight`` on the SMAPE term.
    smape_eps, smape_weight : float
    asinh_scale : tuple of float or None
        Per-state output transform scale (0: none); ``None`` for none at all.
    whiten : bool
        Train on whitened features (the whitening is folded into the first layer afterwards).
    skip : bool
        Give the network a linear skip path (:class:`kklcasadi.nets.specs.MLPSpec`; zero at the start):
        off the fitted states the estimate keeps the slope of that path where the tanh layers level
        off (docs/design.md, "Runs").
    loop : LoopConfig
    dtype : {"float32", "float64"}
        Training precision; the returned arrays are float64 either way.
    """

    hidden: tuple[int, ...] = (256, 256, 256)
    activation: str = "tanh"
    loss: str = "mse"
    smape_eps: float = 1e-3
    smape_weight: float = 0.01
    asinh_scale: tuple[float, ...] | None = None
    whiten: bool = True
    skip: bool = False
    loop: LoopConfig = field(default_factory=lambda: LoopConfig(epochs=30, batch_size=1024, lr=1e-3,
                                                                  schedule="cosine", val_fraction=0.05))
    dtype: str = "float32"

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"loss: expected one of {LOSSES}, received {self.loss!r}.")
        positive_number(self.smape_weight, "smape_weight", "the weight of the SMAPE term of loss 'mse+smape'")
        if not self.hidden or not all(isinstance(h, int) and h > 0 for h in self.hidden):
            raise ValueError(f"hidden: expected a non-empty tuple of positive widths, received {self.hidden!r}.")
        torch_dtype(self.dtype)
        if not isinstance(self.skip, bool):
            raise error("skip", "True or False (a linear skip path in the decoder)", self.skip, kind=TypeError)


@dataclass(frozen=True, eq=False)
class OperationalData:
    """The decoder's samples of the operational runs.

    Attributes
    ----------
    z : numpy.ndarray, shape (S, nz)
        The bank's latent at the kept samples (from ``z = 0`` at each run's start).
    y : numpy.ndarray, shape (S, ny)
    u : numpy.ndarray, shape (S, nu)
    x : numpy.ndarray, shape (S, nx)
        The true states there.
    t : numpy.ndarray, shape (S,)
        Each sample's time from its run's start (seconds).
    run : numpy.ndarray, shape (S,)
        Each sample's run (int, ascending: the samples are ordered run by run).
    record : dict
        ``runs`` simulated, ``cut`` (runs that escaped and were cut there), ``failed`` (of them, the
        ones that blew up or that the integrator failed on), ``samples`` kept, ``simulated_s`` (seconds simulated), the
        per-run noise factors' range, ``substeps`` and ``seconds`` (wall time).
    """

    z: np.ndarray
    y: np.ndarray
    u: np.ndarray
    x: np.ndarray
    t: np.ndarray
    run: np.ndarray
    record: dict

    def __len__(self) -> int:
        return len(self.x)

    @classmethod
    def from_runs(cls, bank: fb.FilterBank, runs: TrajectoryBatch, config: RolloutConfig, *,
                  copies: ModelCopies | None = None) -> OperationalData:
        """The samples of given runs (all of each run valid), kept at ``config``'s sample times; ``copies``
        (the latent's model copies, if any) follow the filters in ``z``."""
        dt = float(runs.t[1] - runs.t[0])
        keep = _keep(runs.t.size, dt, config)
        z = fb.latent_run(bank, runs.y, runs.u, dt, copies=copies)[:, keep]
        nz, ny, nu, nx = z.shape[2], runs.y.shape[2], runs.u.shape[2], runs.x.shape[2]
        record = {"runs": len(runs), "cut": 0, "failed": 0, "samples": int(keep.sum() * len(runs)),
                  "simulated_s": float(len(runs) * runs.t.size * dt)}
        shape = (len(runs), int(keep.sum()))
        return cls(z.reshape(-1, nz), runs.y[:, keep].reshape(-1, ny), runs.u[:, keep].reshape(-1, nu),
                   runs.x[:, keep].reshape(-1, nx), np.broadcast_to(runs.t[keep], shape).ravel(),
                   np.broadcast_to(np.arange(len(runs))[:, None], shape).ravel(), record)


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


def operational_data(system: System, bank: fb.FilterBank, config: RolloutConfig, seed: int, *, dt: float,
                     measurement_std: float, process_std: float | Sequence[float] = 0.0, time_scale: float = 1.0,
                     copies: ModelCopies | None = None, progress: bool = False) -> OperationalData:
    """Simulate the operational runs and keep the decoder's samples of them.

    Parameters
    ----------
    system : System
    bank : FilterBank
        The observer's latent, run over each run from ``z = 0``.
    config : RolloutConfig
    seed : int
        Seeds the initial states (Latin hypercube), the input parameters and the noise.
    dt : float
        The model's sample period.
    measurement_std : float
        Measurement-noise std (nominal; times the per-run factor of ``config.noise_range``).
    process_std : float or sequence of float (nx,)
        Process-noise std added to ``xdot`` (one for all states or one per state).
    time_scale : float
        The rate (rad/s) ``config``'s times are in units of (``T`` seconds at 1): its horizon and
        sample times are divided by it, the inputs' frequencies multiplied.
    copies : ModelCopies or None
        The latent's model copies of the plant (:mod:`kklcasadi.model.variants.copies`), run over each run
        after the filters (their latents follow the bank's in ``z``).
    progress : bool
        A progress bar over the runs.

    Returns
    -------
    OperationalData
        Every run's samples before its escape (if any).
    """
    t0 = time.perf_counter()
    n = time_grid(_horizon(config.T, time_scale, dt), dt).size
    keep = _keep(n, dt, config, time_scale)
    parts: dict[str, list[np.ndarray]] = {"z": [], "y": [], "u": [], "x": [], "t": [], "run": []}
    first = 0
    cut = failed = 0
    factors: list[float] = []
    substeps = 0
    for batch, escape, noise in _chunks(system, config, seed, dt, measurement_std, process_std, time_scale, progress,
                                        "operational runs"):
        cut += int(np.sum(escape < n))
        failed += int(np.sum(~np.all(np.isfinite(batch.x), axis=(1, 2))))
        factors.extend(noise["measurement"].tolist())
        substeps = noise["substeps"]
        valid = np.arange(n)[None, :] < escape[:, None]
        y = np.where(valid[..., None], batch.y, 0.0)          # after an escape: ignored, kept finite
        u = np.where(valid[..., None], batch.u, 0.0)
        z = fb.latent_run(bank, y, u, dt, copies=copies)
        mask = valid & keep[None, :]
        runs = np.broadcast_to(np.arange(first, first + len(escape))[:, None], mask.shape)
        first += len(escape)
        for name, arr in (("z", z), ("y", y), ("u", u), ("x", np.asarray(batch.x)),
                          ("t", np.broadcast_to(batch.t, mask.shape)), ("run", runs)):
            parts[name].append(arr[mask])
    data = {k: np.concatenate(v) for k, v in parts.items()}
    record = {"runs": config.n_traj, "cut": cut, "failed": failed, "samples": int(len(data["x"])),
              "horizon_s": n * dt, "simulated_s": float(config.n_traj * n * dt),
              "sample_period_s": config.sample_period / time_scale, "substeps": substeps,
              "measurement_factor_range": [float(min(factors)), float(max(factors))],
              "seconds": round(time.perf_counter() - t0, 2)}
    return OperationalData(data["z"], data["y"], data["u"], data["x"], data["t"], data["run"], record)


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


def _whitening(f: np.ndarray, floor: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Mean (d,) and symmetric whitening matrix W (d, d): ``cov((f - mean) W^T) = I`` up to the floor."""
    mean = f.mean(axis=0)
    cov = np.cov((f - mean).T)
    cov = np.atleast_2d(cov)
    vals, vecs = np.linalg.eigh(cov)
    vals = np.maximum(vals, floor * vals.max())
    return mean, (vecs / np.sqrt(vals)) @ vecs.T


def fold_whitening(arrays: Mapping[str, np.ndarray], mean: np.ndarray, white: np.ndarray) -> dict[str, np.ndarray]:
    """Fold an input whitening into an MLP trained on ``(f - mean) W^T`` (with unit input normalisation).

    ``W0 ((f - mean) W^T)^T = (W0 W) (f - mean)``, so the returned arrays have ``W0 <- W0 W``
    (and ``Wskip <- Wskip W`` with the skip path), ``in_mean <- mean``, ``in_std <- 1`` and evaluate the
    same map on the raw features ``f``.

    Parameters
    ----------
    arrays : Mapping[str, numpy.ndarray]
        ``decoder/*`` arrays of the MLP trained on whitened features (``in_mean = 0``, ``in_std = 1``).
    mean : numpy.ndarray, shape (d,)
    white : numpy.ndarray, shape (d, d)
    """
    d = white.shape[0]
    if not (np.allclose(arrays[f"{DECODER}/in_mean"], 0.0) and np.allclose(arrays[f"{DECODER}/in_std"], 1.0)):
        raise ValueError("fold_whitening expects an MLP with in_mean = 0 and in_std = 1")
    out = dict(arrays)
    for name in (f"{DECODER}/W0", f"{DECODER}/Wskip"):
        if name in arrays:
            out[name] = np.asarray(arrays[name]) @ white
    out[f"{DECODER}/in_mean"] = np.asarray(mean, dtype=float).copy()
    out[f"{DECODER}/in_std"] = np.ones(d)
    return out


def _torch_outputs(v: Tensor, y: Tensor, scale: np.ndarray, angles: fb.Angles) -> Tensor:
    """:func:`kklcasadi.model.variants.filterbank.decoder_outputs` in torch."""
    nx = scale.size
    s = torch.as_tensor(scale, dtype=v.dtype, device=v.device)
    pos = s > 0
    cols = list(torch.where(pos, torch.where(pos, s, torch.ones_like(s)) * torch.sinh(v[..., :nx]),
                            v[..., :nx]).unbind(-1))
    for i, j in angles.measured:
        cols[i] = y[..., j] + v[..., i]
    for k, (i, c) in enumerate(angles.free):
        cols[i] = c + torch.atan2(v[..., nx + k], v[..., i])
    return torch.stack(cols, dim=-1)


def torch_decoder(arrays: Mapping[str, np.ndarray], arch: Mapping[str, object], *,
                  angles: fb.Angles = fb.NO_ANGLES) -> Callable[[Tensor, Tensor, Tensor], Tensor]:
    """The bank decoder in torch (float64): ``(z (..., nz), y (..., ny), u (..., nu)) -> xhat (..., nx)``.

    The same map as :func:`kklcasadi.model.variants.filterbank.decode` and
    :func:`kklcasadi.model.variants.filterbank.decoder_function`.
    """
    mlp = MLP.from_arrays(arrays, DECODER, MLPSpec.from_card(arch, "architecture", DECODER), dtype=torch.float64)
    scale = np.asarray(arrays[fb.ASINH_SCALE], dtype=float)
    a = list(angles.outputs)
    other = [j for j in range(np.asarray(arrays["bank/By"]).shape[1]) if j not in angles.outputs]
    gains = torch.as_tensor(fb.dc_gains(fb.bank_from_arrays(arrays))[:, a])

    def apply(z: Tensor, y: Tensor, u: Tensor) -> Tensor:
        if a:
            ya = y[..., a]
            f = torch.cat([z - ya @ gains.T, y[..., other], torch.sin(ya), torch.cos(ya), u], dim=-1)
        else:
            f = torch.cat([z, y, u], dim=-1)
        return _torch_outputs(mlp(f), y, scale, angles)

    return apply


@dataclass(frozen=True, eq=False)
class BankFit:
    """Result of :func:`fit_bank_decoder`.

    Attributes
    ----------
    arrays : dict
        ``bank/*``, ``decoder/*`` and ``decoder/asinh_scale`` arrays (float64).
    arch : dict
        The decoder's card entry.
    angles : Angles
        The decoder's angle layout.
    fit : FitResult
    n_samples : int
    seconds : float
    domain : dict
        Per-state 0.1 / 50 / 99.9 percentiles of the training states (the domain the model covers).
    """

    arrays: dict
    arch: dict
    angles: fb.Angles
    fit: FitResult
    n_samples: int
    seconds: float
    domain: dict


def fit_bank_decoder(bank: fb.FilterBank, data: OperationalData, config: DecoderConfig, *,
                     angles: fb.Angles = fb.NO_ANGLES, seed: int = 0, progress: bool = False) -> BankFit:
    """Fit the decoder ``[z_k; y_k; u_k] -> x_k`` on operational samples of the bank observer.

    Parameters
    ----------
    bank : FilterBank
    data : OperationalData
        Samples of noisy runs (:func:`operational_data`, or :meth:`OperationalData.from_runs`).
    config : DecoderConfig
    angles : Angles
        How angle outputs are read and angle states written (:meth:`Angles.of` the plant).
    seed : int
        Seeds torch, the split and the shuffles.
    progress : bool
        Show a progress bar.

    Returns
    -------
    BankFit
    """
    t0 = time.perf_counter()
    nx = data.x.shape[1]
    scale = np.zeros(nx) if config.asinh_scale is None else np.asarray(config.asinh_scale, dtype=float)
    if scale.shape != (nx,) or np.any(scale < 0):
        raise ValueError(f"asinh_scale: expected nx = {nx} entries >= 0, received {config.asinh_scale!r}.")
    feats = fb.decoder_features(data.z, data.y, data.u, angles=angles, gains=fb.dc_gains(bank))
    v = fb.decoder_targets(data.x, data.y, scale, angles)
    sizes = (feats.shape[1], *config.hidden, v.shape[1])
    dtype = torch_dtype(config.dtype)
    torch.manual_seed(seed)
    mlp = MLP(sizes, config.activation, skip=config.skip).to(torch.float64)
    if config.whiten:
        f_mean, white = _whitening(feats)
    else:
        f_mean, white = feats.mean(axis=0), np.diag(1.0 / (feats.std(axis=0) + 1e-12))
    mlp.set_normalisation(np.zeros(sizes[0]), np.ones(sizes[0]), v.mean(axis=0), v.std(axis=0) + 1e-12)
    mlp = mlp.to(dtype)
    data_set = ArrayDataset({"f": (feats - f_mean) @ white.T, "v": v, "x": data.x, "y": data.y}, dtype=dtype)
    out_std = torch.as_tensor(mlp.out_std.detach().clone())

    def loss_fn(batch: Mapping[str, Tensor], epoch: int) -> tuple[Tensor, dict[str, float]]:
        pred = mlp(batch["f"])
        parts: dict[str, float] = {}
        total = pred.new_zeros(())
        if config.loss in ("mse", "mse+smape"):
            mse = (((pred - batch["v"]) / out_std) ** 2).mean()
            parts["mse"] = mse.item()
            total = total + mse
        if config.loss in ("smape", "mse+smape"):
            xhat = _torch_outputs(pred, batch["y"], scale, angles)
            xt = batch["x"]
            sm = (2.0 * (xt - xhat).abs() / (xt.abs() + xhat.abs() + config.smape_eps)).mean()
            parts["smape"] = sm.item()
            total = total + (sm if config.loss == "smape" else config.smape_weight * sm)
        return total, parts

    result = fit(list(mlp.parameters()), loss_fn, data_set, config.loop, name="bank decoder", seed=seed,
                 progress=progress)
    arrays = fold_whitening(mlp.to(torch.float64).to_arrays(DECODER), f_mean, white)
    arrays[fb.ASINH_SCALE] = scale.copy()
    arrays.update(fb.bank_arrays(bank))
    pct = np.percentile(data.x, [0.1, 50.0, 99.9], axis=0)
    domain = {"x_p0.1": pct[0].tolist(), "x_p50": pct[1].tolist(), "x_p99.9": pct[2].tolist()}
    return BankFit(arrays, mlp.spec.to_card(), angles, result, int(len(v)), time.perf_counter() - t0, domain)


def config_record(rollout: RolloutConfig, decoder: DecoderConfig) -> dict:
    """JSON-able record of the two configurations (for a model card)."""
    return {"rollouts": asdict(rollout), "decoder": {**asdict(decoder), "loop": asdict(decoder.loop)}}
