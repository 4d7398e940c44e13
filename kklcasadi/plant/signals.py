"""Known input signals ``u(t)``, output-feedback laws, and the seeded samplers of the input families.

Every signal is an immutable callable: ``u(t)`` returns shape (nu,) for a scalar ``t`` and
(N, nu) for a time array of shape (N,). Simulation applies them zero-order hold, ``u_k = u(t_k)``.

An :class:`OutputFeedback` law (:class:`PDFeedback`) is an input that depends on the run: the
simulator computes ``u_k`` from the measured ``y_k`` and the law's own state, and holds it over
``[t_k, t_k+1)`` (:func:`kklcasadi.plant.simulate.simulate_batch`).

:func:`sample` draws the benchmark's four regimes from the docs/protocol.md ranges (:data:`RANGES`);
:func:`draw` draws any family from explicit parameter ranges, among them the held-out families of
docs/protocol.md "Generalisation" (:data:`HELD_OUT_RANGES`: a swept sine, random steps and a PD
controller around a stepping set point).

The families are drawn in the benchmark's units (``|u| <= 2``). For a plant that declares its input range
(``kc.System(..., u_box=...)``), :func:`in_box` maps a drawn input onto it: the benchmark's widest level
:data:`UNIT_LEVEL` goes to the box's edges, so the ``id`` families span the box's central half and the ``ood``
ones the whole box (what the training runs span: :func:`kklcasadi.plant.runs.input_range`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Mapping, overload

import casadi as ca
import numpy as np

from ..validation import Text, error, finite_number, nonnegative_number, one_of, positive_int, positive_number

__all__ = ["Signal", "Zero", "Constant", "Sinusoid", "Square", "Step", "Chirp", "RandomSteps",
           "OutputFeedback", "PDFeedback", "Mapped", "make", "kinds", "sample", "draw", "family_ranges", "in_box",
           "box_map", "RANGES", "REGIMES", "BENCHMARK_KINDS", "HELD_OUT_RANGES", "FAMILIES", "UNIT_LEVEL"]


def _vector(value: Any, arg: str) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.ndim != 1 or arr.size == 0:
        raise error(arg, "a scalar or a 1-D vector (one entry per input)", Text(f"shape {arr.shape}"))
    if not np.all(np.isfinite(arr)):
        raise error(arg, "finite values", arr.tolist())
    arr.setflags(write=False)
    return arr


def _per_channel(obj: Any, n: int, channel: str, checks: tuple) -> None:
    """Set each ``(name, check)`` field of the frozen ``obj`` to a read-only (n,) vector: a scalar broadcast, or
    ``n`` entries, each passing ``check``."""
    for name, check in checks:
        value = _vector(getattr(obj, name), name)
        if value.size not in (1, n):
            raise error(name, f"a scalar or {n} entries (one per {channel})", Text(f"size {value.size}"))
        value = np.broadcast_to(value, (n,)).copy()
        for v in value:
            check(float(v), name)
        value.setflags(write=False)
        object.__setattr__(obj, name, value)


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
    """Seeded random piecewise-constant signal: a new level ``offset + U[-amplitude, amplitude]`` every ``hold`` s.

    Levels are drawn once from ``numpy.random.default_rng(seed)`` for ``[0, horizon]``; the last level
    is held after ``horizon`` and the first before 0.
    """

    amplitude: Any = 1.0
    hold: float = 1.0
    seed: int = 0
    horizon: float = 50.0
    offset: Any = 0.0
    levels: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "amplitude", _vector(self.amplitude, "amplitude"))
        object.__setattr__(self, "offset", _vector(self.offset, "offset"))
        if self.offset.size not in (1, self.amplitude.size):
            raise error("offset", f"a scalar or {self.amplitude.size} entries (one per input)",
                        Text(f"size {self.offset.size}"))
        positive_number(self.hold, "hold")
        positive_number(self.horizon, "horizon")
        n = int(np.ceil(self.horizon / self.hold)) + 1
        levels = self.offset + np.random.default_rng(self.seed).uniform(-1.0, 1.0, (n, self.nu)) * self.amplitude
        levels.setflags(write=False)
        object.__setattr__(self, "levels", levels)

    @property
    def nu(self) -> int:
        return self.amplitude.size

    def _eval(self, t: np.ndarray) -> np.ndarray:
        idx = np.clip(np.floor(t / self.hold).astype(int), 0, len(self.levels) - 1)
        return self.levels[idx]


class OutputFeedback:
    """An input computed from the measurement: a control law ``u_k = law(c_k, y_k, r_k)``.

    The simulator calls the law once per sample with the measured (noisy) ``y_k``, the reference
    ``r_k = reference(t_k)`` and the law's state ``c_k`` (``c_0 = state0(y_0)``), and holds ``u_k``
    over ``[t_k, t_k+1)``. One CasADi Function serves every law of a class (their numbers are its
    ``theta`` input), so the closed loops of many trials run as one mapped call.

    Subclasses give :attr:`channels`, :attr:`n_state`, :meth:`function`, :meth:`theta`,
    :meth:`reference` and :meth:`state0`.
    """

    @property
    def channels(self) -> int:
        """Inputs the law drives (the outputs it reads: one per input)."""
        raise NotImplementedError

    @property
    def n_state(self) -> int:
        """Size of the law's state ``c``."""
        raise NotImplementedError

    def function(self, dt: float) -> ca.Function:
        """``law(c (n_state,), y (ny,), r (ny,), theta) -> (u (nu,), c_next (n_state,))`` at sample period ``dt``."""
        raise NotImplementedError

    def theta(self) -> np.ndarray:
        """The law's numbers, the ``theta`` input of :meth:`function`."""
        raise NotImplementedError

    def reference(self, t: Any) -> np.ndarray:
        """The reference ``r(t_k)``, shape (N, channels)."""
        raise NotImplementedError

    def state0(self, y0: Any) -> np.ndarray:
        """The law's state at the first sample, from the first measurement ``y_0`` (ny,)."""
        raise NotImplementedError


@dataclass(frozen=True)
class PDFeedback(OutputFeedback):
    """A saturated PD controller on the measured output around a set point: what a controller sends.

    ``yf_k = yf_k-1 + alpha (y_k - yf_k-1)`` (a first-order filter of the noisy measurement, time
    constant ``tau``, ``alpha = 1 - exp(-dt / tau)``, ``yf_-1 = y_0``), then
    ``u_k = clip(kp (r_k - y_k) - kd (yf_k - yf_k-1) / dt, -u_max, u_max)`` per channel (the
    derivative acts on the filtered measurement, not on the set point). One input per output.

    Attributes
    ----------
    setpoint : Signal
        The set point ``r(t)``, one entry per output (e.g. :class:`RandomSteps`).
    kp, kd : float or array_like (channels,)
        Proportional gain and derivative gain (>= 0).
    tau : float or array_like (channels,)
        Time constant of the measurement filter of the derivative term, seconds (> 0).
    u_max : float or array_like (channels,)
        Saturation of the input (> 0).
    u_offset, u_scale : float or array_like (channels,)
        The input sent is ``u_offset + u_scale * u_k`` (> 0 scale): the law in a plant's input units
        (:func:`in_box`); 0 and 1 by default.
    """

    setpoint: Signal = field(default_factory=Zero)
    kp: Any = 1.0
    kd: Any = 0.5
    tau: Any = 0.2
    u_max: Any = 1.0
    u_offset: Any = 0.0
    u_scale: Any = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.setpoint, Signal):
            raise error("setpoint", "a kklcasadi signal r(t)", Text(type(self.setpoint).__name__), kind=TypeError)
        _per_channel(self, self.setpoint.nu, "set-point channel",
                     (("kp", nonnegative_number), ("kd", nonnegative_number), ("tau", positive_number),
                      ("u_max", positive_number), ("u_offset", finite_number), ("u_scale", positive_number)))

    @property
    def channels(self) -> int:
        return self.setpoint.nu

    @property
    def nu(self) -> int:
        return self.channels

    @property
    def n_state(self) -> int:
        return self.channels

    def function(self, dt: float) -> ca.Function:
        dt = positive_number(dt, "dt")
        n = self.channels
        c, y, r, theta = ca.SX.sym("c", n), ca.SX.sym("y", n), ca.SX.sym("r", n), ca.SX.sym("theta", 6 * n)
        kp, kd, tau, u_max, u_offset, u_scale = ca.vertsplit(theta, [0, n, 2 * n, 3 * n, 4 * n, 5 * n, 6 * n])
        yf = c + (1.0 - ca.exp(-dt / tau)) * (y - c)
        u = u_offset + u_scale * ca.fmin(ca.fmax(kp * (r - y) - kd * (yf - c) / dt, -u_max), u_max)
        return ca.Function("pd_feedback", [c, y, r, theta], [u, yf], ["c", "y", "r", "theta"], ["u", "c_next"])

    def theta(self) -> np.ndarray:
        return np.concatenate([self.kp, self.kd, self.tau, self.u_max, self.u_offset, self.u_scale])

    def reference(self, t: Any) -> np.ndarray:
        times, _ = _times(t)
        return self.setpoint(times)

    def state0(self, y0: Any) -> np.ndarray:
        return np.asarray(y0, dtype=float).reshape(self.channels).copy()


@dataclass(frozen=True)
class Mapped(Signal):
    """``u(t) = offset + scale * inner(t)``: a signal drawn in the benchmark's units, in a plant's (:func:`in_box`).

    Attributes
    ----------
    inner : Signal
    offset, scale : array_like (nu,)
        Per input; ``scale > 0``.
    """

    inner: Signal
    offset: Any
    scale: Any

    def __post_init__(self) -> None:
        if not isinstance(self.inner, Signal):
            raise error("inner", "a kklcasadi signal u(t)", Text(type(self.inner).__name__), kind=TypeError)
        _per_channel(self, self.inner.nu, "input", (("offset", finite_number), ("scale", positive_number)))

    @property
    def nu(self) -> int:
        return self.inner.nu

    def _eval(self, t: np.ndarray) -> np.ndarray:
        return self.offset + self.scale * self.inner(t)


#: The benchmark's widest input level (the ``ood`` constant's ``|u|``): :func:`in_box` maps it to a ``u_box``'s edges.
UNIT_LEVEL = 2.0


def box_map(u_box: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(offset, scale)``, each (nu,), mapping the benchmark's ``[-UNIT_LEVEL, UNIT_LEVEL]`` onto ``u_box`` (nu, 2)."""
    box = np.asarray(u_box, dtype=float)
    if box.ndim != 2 or box.shape[1] != 2 or not np.all(np.isfinite(box)) or np.any(box[:, 1] <= box[:, 0]):
        raise error("u_box", "finite rows [lo, hi] with lo < hi, one per input", Text(repr(box.tolist())))
    return box.mean(axis=1), 0.5 * (box[:, 1] - box[:, 0]) / UNIT_LEVEL


@overload
def in_box(u: Signal, u_box: Any) -> Signal: ...
@overload
def in_box(u: OutputFeedback, u_box: Any) -> OutputFeedback: ...
def in_box(u: Signal | OutputFeedback, u_box: Any) -> Signal | OutputFeedback:
    """The input ``u``, drawn in the benchmark's units, in the units of a plant whose inputs span ``u_box``.

    Parameters
    ----------
    u : Signal or PDFeedback
        As :func:`sample` or :func:`draw` return it.
    u_box : array_like (nu, 2) or None
        The plant's ``u_box``; None returns ``u`` itself (the shipped plants: the benchmark's units are theirs).

    Returns
    -------
    Signal or PDFeedback
        ``offset + scale * u`` with :func:`box_map`'s numbers (a :class:`Mapped` signal, or the law with its
        ``u_offset`` and ``u_scale``).
    """
    if u_box is None:
        return u
    offset, scale = box_map(u_box)
    if isinstance(u, PDFeedback):
        return replace(u, u_offset=offset, u_scale=scale)
    if isinstance(u, Signal):
        return Mapped(u, offset, scale)
    raise error("u", "a kklcasadi signal or a PDFeedback law", Text(type(u).__name__), kind=TypeError)


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


#: Parameter ranges of the held-out input families of docs/protocol.md "Generalisation": a swept sine
#: of in-range amplitude from below to above the sinusoid's fitted band (to the top of its ood band),
#: random steps of in-range amplitude, and a saturated PD controller around a stepping set point
#: (``setpoint``: the set point as a share of the output's half-range over the X0 box, about its centre).
HELD_OUT_RANGES: Mapping[str, Mapping[str, tuple[float, float]]] = {
    "chirp": {"amplitude": (0.1, 1.0), "omega0": (0.1, 0.5), "omega1": (3.0, 6.0)},
    "random": {"amplitude": (0.1, 1.0), "hold": (0.5, 5.0)},
    "feedback": {"setpoint": (-0.5, 0.5), "hold": (2.0, 10.0), "kp": (0.5, 2.0), "kd": (0.2, 1.0),
                 "tau": (0.1, 0.3), "u_max": (1.0, 1.0)},
}
#: Every input family :func:`draw` knows, benchmark regimes first.
FAMILIES = (*BENCHMARK_KINDS, *HELD_OUT_RANGES)
_FAMILY_PARAMS = {"zero": (), "constant": ("value",), "sinusoid": ("amplitude", "omega"),
                  "square": ("amplitude", "omega"), **{k: tuple(v) for k, v in HELD_OUT_RANGES.items()}}


def family_ranges(kind: str, regime: str) -> dict[str, tuple[float, float]]:
    """The parameter ranges of family ``kind`` in ``regime``, as :func:`draw` takes them.

    Parameters
    ----------
    kind : str
        One of :data:`FAMILIES`.
    regime : {"train", "id", "ood", "held_out"}
        :data:`RANGES` for the benchmark's families, ``"held_out"`` (:data:`HELD_OUT_RANGES`) for the others.

    Returns
    -------
    dict
        ``{parameter: (lo, hi)}``; empty for ``zero``.
    """
    one_of(kind, "kind", FAMILIES)
    if kind == "zero":
        return {}
    table = {**RANGES, "held_out": HELD_OUT_RANGES}
    ranges = table[one_of(regime, "regime", tuple(table))]
    if kind not in ranges:
        known = [name for name, r in table.items() if kind in r]
        raise error("regime", f"a regime that defines family {kind!r}: one of {known}", regime)
    return dict(ranges[kind])


def draw(kind: str, rng: np.random.Generator, ranges: Mapping[str, tuple[float, float]], *, nu: int = 1,
         horizon: float = 50.0, output_range: Any = None) -> Signal | OutputFeedback:
    """Draw one input of family ``kind`` with every parameter uniform in ``ranges``.

    Parameters
    ----------
    kind : str
        One of :data:`FAMILIES`.
    rng : numpy.random.Generator
        Source of randomness (the caller seeds it).
    ranges : Mapping
        ``{parameter: (lo, hi)}`` with exactly the family's parameters (:func:`family_ranges`).
    nu : int
        Number of inputs. Constant, sinusoid, square, chirp and random-step inputs get independent
        values/amplitudes per input; the other parameters are shared.
    horizon : float
        Duration of a chirp's sweep and of a random-step sequence (and of a set-point sequence), seconds.
    output_range : (array_like (nu,), array_like (nu,)), optional
        ``feedback`` only (required there): the low and high ends of the measured output, to which
        the set points are relative (docs/protocol.md: ``h`` over the X0 box).

    Returns
    -------
    Signal or OutputFeedback
        For ``feedback``: a :class:`PDFeedback` whose set point is a :class:`RandomSteps`.
    """
    if not isinstance(rng, np.random.Generator):
        raise error("rng", "a numpy.random.Generator (np.random.default_rng(seed))", Text(type(rng).__name__),
                    kind=TypeError)
    one_of(kind, "kind", FAMILIES)
    nu = positive_int(nu, "nu")
    expected = set(_FAMILY_PARAMS[kind])
    if not isinstance(ranges, Mapping) or set(ranges) != expected:
        raise error("ranges", f"the parameters {sorted(expected)} of family {kind!r}",
                    Text(repr(sorted(ranges)) if isinstance(ranges, Mapping) else type(ranges).__name__))
    for name, bounds in ranges.items():
        if (len(bounds) != 2 or not all(np.isfinite(bounds)) or bounds[0] > bounds[1]):
            raise error(f"ranges[{name!r}]", "finite (lo, hi) with lo <= hi", tuple(bounds))
    if kind == "zero":
        return Zero(nu)
    if kind == "constant":
        return Constant(rng.uniform(*ranges["value"], size=nu))
    if kind in ("sinusoid", "square"):
        amplitude = rng.uniform(*ranges["amplitude"], size=nu)
        omega = rng.uniform(*ranges["omega"])
        phase = rng.uniform(0.0, 2.0 * np.pi)
        return _KINDS[kind](amplitude=amplitude, omega=omega, phase=phase)
    horizon = positive_number(horizon, "horizon")
    if kind == "chirp":
        amplitude = rng.uniform(*ranges["amplitude"], size=nu)
        omega0, omega1 = rng.uniform(*ranges["omega0"]), rng.uniform(*ranges["omega1"])
        return Chirp(amplitude, omega0, omega1, horizon, rng.uniform(0.0, 2.0 * np.pi))
    if kind == "random":
        amplitude = rng.uniform(*ranges["amplitude"], size=nu)
        return RandomSteps(amplitude, rng.uniform(*ranges["hold"]), int(rng.integers(2 ** 32)), horizon)
    if output_range is None:
        raise error("output_range", "the (low, high) ends of the measured output for family 'feedback'", None)
    lo, hi = (np.broadcast_to(np.asarray(b, dtype=float), (nu,)) for b in output_range)
    centre, half = (lo + hi) / 2.0, (hi - lo) / 2.0
    s_lo, s_hi = ranges["setpoint"]
    setpoint = RandomSteps(half * (s_hi - s_lo) / 2.0, rng.uniform(*ranges["hold"]), int(rng.integers(2 ** 32)),
                           horizon, offset=centre + half * (s_hi + s_lo) / 2.0)
    gains = {name: rng.uniform(*ranges[name]) for name in ("kp", "kd", "tau", "u_max")}
    return PDFeedback(setpoint, **gains)


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
    return draw(kind, rng, family_ranges(kind, regime), nu=nu)
