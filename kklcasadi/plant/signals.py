"""Known input signals ``u(t)`` and the seeded sampler of the benchmark's input regimes.

Every signal is an immutable callable: ``u(t)`` returns shape (nu,) for a scalar ``t`` and
(N, nu) for a time array of shape (N,). Simulation applies them zero-order hold, ``u_k = u(t_k)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from ..validation import Text, error, finite_number, one_of, positive_int, positive_number

__all__ = ["Signal", "Zero", "Constant", "Sinusoid", "Square", "Step", "Chirp", "RandomSteps",
           "make", "kinds", "sample", "RANGES", "REGIMES", "BENCHMARK_KINDS"]


def _vector(value: Any, arg: str) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.ndim != 1 or arr.size == 0:
        raise error(arg, "a scalar or a 1-D vector (one entry per input)", Text(f"shape {arr.shape}"))
    if not np.all(np.isfinite(arr)):
        raise error(arg, "finite values", arr.tolist())
    arr.setflags(write=False)
    return arr


def _times(t: Any) -> tuple[np.ndarray, bool]:
    arr = np.asarray(t, dtype=float)
    if arr.ndim > 1:
        raise error("t", "a scalar or a 1-D array of times", Text(f"shape {arr.shape}"))
    if not np.all(np.isfinite(arr)):
        raise error("t", "finite times", Text("NaN or inf"))
    return np.atleast_1d(arr), arr.ndim == 0


@dataclass(frozen=True)
class Signal:
    """Base class of input signals; subclasses implement ``_eval(t (N,)) -> (N, nu)``."""

    def __call__(self, t: Any) -> np.ndarray:
        times, scalar = _times(t)
        out = self._eval(times)
        return out[0] if scalar else out

    @property
    def nu(self) -> int:
        raise NotImplementedError

    def _eval(self, t: np.ndarray) -> np.ndarray:
        raise NotImplementedError


@dataclass(frozen=True)
class Zero(Signal):
    """``u(t) = 0`` with ``size`` inputs."""

    size: int = 1

    def __post_init__(self) -> None:
        positive_int(self.size, "size (number of inputs)")

    @property
    def nu(self) -> int:
        return int(self.size)

    def _eval(self, t: np.ndarray) -> np.ndarray:
        return np.zeros((t.size, self.nu))


@dataclass(frozen=True)
class Constant(Signal):
    """``u(t) = value``."""

    value: Any = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "value", _vector(self.value, "value"))

    @property
    def nu(self) -> int:
        return self.value.size

    def _eval(self, t: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.value, (t.size, self.nu)).copy()


@dataclass(frozen=True)
class _Periodic(Signal):
    amplitude: Any = 1.0
    omega: float = 1.0
    phase: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "amplitude", _vector(self.amplitude, "amplitude"))
        object.__setattr__(self, "omega", positive_number(self.omega, "omega (rad/s)"))
        object.__setattr__(self, "phase", finite_number(self.phase, "phase"))

    @property
    def nu(self) -> int:
        return self.amplitude.size

    def _angle(self, t: np.ndarray) -> np.ndarray:
        return np.sin(self.omega * t + self.phase)[:, None]


@dataclass(frozen=True)
class Sinusoid(_Periodic):
    """``u(t) = amplitude sin(omega t + phase)``, omega in rad/s."""

    def _eval(self, t: np.ndarray) -> np.ndarray:
        return self.amplitude * self._angle(t)


@dataclass(frozen=True)
class Square(_Periodic):
    """``u(t) = amplitude sign(sin(omega t + phase))``, omega in rad/s."""

    def _eval(self, t: np.ndarray) -> np.ndarray:
        return self.amplitude * np.sign(self._angle(t))


@dataclass(frozen=True)
class Step(Signal):
    """``u(t) = before`` for ``t < time`` and ``after`` from then on."""

    time: float = 0.0
    before: Any = 0.0
    after: Any = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "before", _vector(self.before, "before"))
        object.__setattr__(self, "after", _vector(self.after, "after"))
        if self.before.size != self.after.size:
            raise error("after", f"the size of before ({self.before.size})", Text(f"size {self.after.size}"))
        finite_number(self.time, "time")

    @property
    def nu(self) -> int:
        return self.after.size

    def _eval(self, t: np.ndarray) -> np.ndarray:
        return np.where((t >= self.time)[:, None], self.after, self.before)


@dataclass(frozen=True)
class Chirp(Signal):
    """Linear chirp ``amplitude sin(phase + omega0 t + (omega1 - omega0) t^2 / (2 duration))``.

    The instantaneous frequency sweeps from ``omega0`` to ``omega1`` (rad/s) over ``duration`` seconds
    and stays at ``omega1`` afterwards.
    """

    amplitude: Any = 1.0
    omega0: float = 0.5
    omega1: float = 3.0
    duration: float = 50.0
    phase: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "amplitude", _vector(self.amplitude, "amplitude"))
        positive_number(self.omega0, "omega0 (rad/s)")
        positive_number(self.omega1, "omega1 (rad/s)")
        positive_number(self.duration, "duration")

    @property
    def nu(self) -> int:
        return self.amplitude.size

    def _eval(self, t: np.ndarray) -> np.ndarray:
        tc = np.clip(t, 0.0, self.duration)
        rate = (self.omega1 - self.omega0) / self.duration
        angle = self.phase + self.omega0 * tc + 0.5 * rate * tc ** 2 + self.omega1 * (t - tc)
        return self.amplitude * np.sin(angle)[:, None]


@dataclass(frozen=True)
class RandomSteps(Signal):
    """Seeded random piecewise-constant signal: a new level ``U[-amplitude, amplitude]`` every ``hold`` s.

    Levels are drawn once from ``numpy.random.default_rng(seed)`` for ``[0, horizon]``; the last level
    is held after ``horizon`` and the first before 0.
    """

    amplitude: Any = 1.0
    hold: float = 1.0
    seed: int = 0
    horizon: float = 50.0
    levels: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "amplitude", _vector(self.amplitude, "amplitude"))
        positive_number(self.hold, "hold")
        positive_number(self.horizon, "horizon")
        n = int(np.ceil(self.horizon / self.hold)) + 1
        levels = np.random.default_rng(self.seed).uniform(-1.0, 1.0, (n, self.nu)) * self.amplitude
        levels.setflags(write=False)
        object.__setattr__(self, "levels", levels)

    @property
    def nu(self) -> int:
        return self.amplitude.size

    def _eval(self, t: np.ndarray) -> np.ndarray:
        idx = np.clip(np.floor(t / self.hold).astype(int), 0, len(self.levels) - 1)
        return self.levels[idx]


_KINDS: dict[str, type[Signal]] = {
    "zero": Zero, "constant": Constant, "sinusoid": Sinusoid, "square": Square,
    "step": Step, "chirp": Chirp, "random": RandomSteps,
}


def kinds() -> list[str]:
    """Names accepted by :func:`make`."""
    return list(_KINDS)


def make(kind: str, **params: Any) -> Signal:
    """Build a signal by name, e.g. ``make("square", amplitude=0.5, omega=1.0, phase=0.0)``.

    Known kinds: ``zero`` (size), ``constant`` (value), ``sinusoid`` and ``square`` (amplitude, omega,
    phase), ``step`` (time, before, after), ``chirp`` (amplitude, omega0, omega1, duration, phase),
    ``random`` (amplitude, hold, seed, horizon).
    """
    cls = _KINDS[one_of(kind, "kind", _KINDS)]
    fields = [f for f in cls.__dataclass_fields__ if f != "levels"]
    unknown = sorted(set(params) - set(fields))
    if unknown:
        raise error("params", f"parameters of signal {kind!r} among {fields}", Text(f"unknown {unknown}"),
                    kind=TypeError)
    return cls(**params)


_ID_RANGES = {
    "constant": {"value": (-1.0, 1.0)},
    "sinusoid": {"amplitude": (0.1, 1.0), "omega": (0.5, 3.0)},
    "square": {"amplitude": (0.1, 1.0), "omega": (0.5, 2.0)},
}
#: Per-trial parameter ranges of docs/protocol.md. ``train`` (the training distribution) equals ``id``.
RANGES: Mapping[str, Mapping[str, Mapping[str, tuple[float, float]]]] = {
    "train": _ID_RANGES,
    "id": _ID_RANGES,
    "ood": {
        "constant": {"value": (-2.0, 2.0)},
        "sinusoid": {"amplitude": (1.0, 2.0), "omega": (3.0, 6.0)},
        "square": {"amplitude": (1.0, 2.0), "omega": (2.0, 4.0)},
    },
}
REGIMES = tuple(RANGES)
#: The input regimes of the benchmark table, in column order.
BENCHMARK_KINDS = ("zero", "constant", "sinusoid", "square")


def sample(kind: str, rng: np.random.Generator, regime: str = "id", *, nu: int = 1) -> Signal:
    """Draw one signal of ``kind`` with parameters from the docs/protocol.md ranges of ``regime``.

    Parameters
    ----------
    kind : {"zero", "constant", "sinusoid", "square"}
    rng : numpy.random.Generator
        Source of randomness (the caller seeds it).
    regime : {"train", "id", "ood"}
    nu : int
        Number of inputs; each input gets independent parameters for constant signals and
        independent amplitudes for periodic ones.
    """
    if not isinstance(rng, np.random.Generator):
        raise error("rng", "a numpy.random.Generator (np.random.default_rng(seed))", Text(type(rng).__name__),
                    kind=TypeError)
    ranges = RANGES[one_of(regime, "regime", REGIMES)]
    one_of(kind, "kind", ("zero", *ranges))
    if kind == "zero":
        return Zero(nu)
    r = ranges[kind]
    if kind == "constant":
        return Constant(rng.uniform(*r["value"], size=nu))
    amplitude = rng.uniform(*r["amplitude"], size=nu)
    omega = rng.uniform(*r["omega"])
    phase = rng.uniform(0.0, 2.0 * np.pi)
    return _KINDS[kind](amplitude=amplitude, omega=omega, phase=phase)
