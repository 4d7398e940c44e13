"""The covariance head's inflation by the measurement residual (torch-free): the head does not see the noise level.

The covariance head (:mod:`kklcasadi.model.variants.covariance`) is fit and calibrated at the noise level of its
fitting runs; where the measurements are noisier than that, the estimates are further off than it says (twice the
noise: 2-sigma coverage near 68 % instead of 95 %). The observer sees the noise level in its own residual: with
``P_k`` the head's covariance of the estimate ``xhat_k`` and ``y_k`` the measurement the estimate was decoded with,

    nu_k  = y_k - h(xhat_k)                            (the residual, ny)
    S_k   = H_k P_k H_k^T + diag(R)                    (H_k = dh/dx at xhat_k; R the card's measurement variances)
    r_k   = nu_k^T S_k^-1 nu_k / ny
    m_0   = 1,   m_k = (1 - a) m_{k-1} + a r_k / c     (k >= 1; a = 1 - exp(-dt / time_constant))
    P'_k  = max(1, m_k) P_k

``m`` is one more state the observer's step carries (the CasADi step's sixth input and fifth output, the C
``name_step``'s ``arg[5]`` and ``res[4]``); ``c`` is the mean of ``r`` on in-distribution validation runs, so that
``m`` stays near 1 there and the calibrated head is left as it is, and grows with the residual's variance where
the noise is larger. ``R`` is the fitting runs' measurement noise variance (the residual's scale under the
head's calibration); ``c`` and the time constant are chosen on validation runs
(``benchmarks/covariance_heads.py``). The estimates do not depend on ``m``: they are bitwise those of the step
without it.

The residual does not see a wrong model: a plant whose parameters differ from the model's is tracked in ``y``
while the unmeasured states drift. A bank with model copies (:mod:`kklcasadi.model.variants.copies`) has a
model-based estimate in its latent that does see it: a copy of the nominal plant under mismatch has a biased,
slowly varying innovation, where the exact model's is nearly white noise. The optional ``model`` entry
(:class:`ModelTest`) low-passes copy ``i``'s innovation and averages its square: with ``xhat_i`` the copy's state
in ``z_k``, ``b = exp(-pole dt)`` and ``a2 = 1 - exp(-dt / time_constant2)``,

    nu_i,k = y_k - h(xhat_i,k)
    s_k    = b s_{k-1} + (1 - b) nu_i,k                  (s_0 = 0)
    t_k    = t_{k-1} + dt                                (t_0 = 0)
    q_k    = sum_j s_k,j^2 / S_j / ny   if t_k > start - dt / 2,  else 1
    g_k    = (1 - a2) g_{k-1} + a2 q_k                   (g_0 = 1)
    P'_k   = max(1, m_k) max(1, 1 + gain (g_k / m_k - threshold)) P_k

``S`` is the mean of ``s^2`` on in-distribution validation runs after ``start`` (so ``g`` averages 1 there);
``start`` leaves out the copies' own transient from the box centre, and ``threshold`` the average's own
fluctuations in distribution. ``g`` is read against ``m``: noisier measurements raise both by the same factor
(twice the noise: about 4), which ``max(1, m)`` covers already; a wrong model raises ``g`` alone. The state is
then ``[m, s (ny), g, t]`` (``3 + ny`` numbers, start ``[1, 0, ..., 0, 1, 0]``: :meth:`Inflation.initial_state`).

Neither sees inputs that drive the plant where the head was not fit (its fitting runs' input ranges): there the
noise is the head's own and the residual stays noise, while the errors grow. A bank with a decoder ensemble sees it
in the members' disagreement (:func:`kklcasadi.model.variants.bankdecoder.spread`, the domain monitor's second
test), which the step computes with the estimate from the same evaluation. The optional ``spread`` entry
(:class:`SpreadTest`) averages its square: with ``d_k`` the spread at sample ``k`` and ``a3 = 1 - exp(-dt /
time_constant3)``,

    h_k    = (1 - a3) h_{k-1} + a3 d_k^2 / S             (h_0 = 1)
    P'_k   = (the factors above) max(1, 1 + gain3 (h_k - threshold3)) P_k

``S`` is the mean of ``d^2`` on in-distribution validation runs at the head's noise (so ``h`` averages 1 there);
``threshold3`` leaves the spread's growth with the noise alone (about 2 at twice the noise). ``h`` is the carried
state's last number (start 1).

:func:`inflation_numpy` is the reference; :func:`inflation_function` the same recursion in CasADi (what the
observer's step and its C code compute).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Optional

import casadi as ca
import numpy as np

from ...nets.specs import field_error
from ...plant.systems import System
from ...validation import is_number

__all__ = ["INFLATION", "Inflation", "ModelTest", "SpreadTest", "spread_factor", "residual_statistic",
           "inflation_numpy", "inflation_function", "fold"]

#: The card's entry (``architecture.inflation``).
INFLATION = "inflation"
_KEYS = ("R", "c", "time_constant")
#: The optional entry of the model test (:class:`ModelTest`), and its keys.
MODEL = "model"
_MODEL_KEYS = ("copy", "pole", "S", "time_constant", "gain", "threshold", "start")
#: The optional entry of the spread test (:class:`SpreadTest`), and its keys.
SPREAD = "spread"
_SPREAD_KEYS = ("S", "time_constant", "gain", "threshold")


def _positive(value: Any) -> bool:
    return is_number(value) and math.isfinite(value) and value > 0


@dataclass(frozen=True)
class ModelTest:
    """The model test's constants (``architecture.inflation.model``; the module docstring's second recursion).

    Attributes
    ----------
    copy : int
        Which model copy of the latent (0: the first, the slowest of the shipped banks).
    pole : float
        Of the innovation's first-order low-pass, in rad/s, > 0.
    S : tuple of float
        The mean of the low-passed innovation's square per output on in-distribution validation runs (ny), > 0.
    time_constant : float
        Of its exponential average, in seconds, > 0.
    gain : float
        ``P' = max(1, m) max(1, 1 + gain (g / m - threshold)) P``, > 0.
    threshold : float
        Of ``g``, >= 0 (1: none beyond the mean in distribution).
    start : float
        The statistic is fed from this time on (s), >= 0: the copies start at the box centre.
    """

    copy: int
    pole: float
    S: tuple[float, ...]
    time_constant: float
    gain: float
    threshold: float
    start: float

    @classmethod
    def from_card(cls, entry: Any, where: str, ny: int) -> ModelTest:
        """The constants of ``architecture.inflation.model``, checked (one-line errors naming the field)."""
        name = f"architecture.{INFLATION}.{MODEL}"
        if not isinstance(entry, Mapping) or set(entry) != set(_MODEL_KEYS):
            received = sorted(entry) if isinstance(entry, Mapping) else entry
            raise field_error(where, name, f"an object with exactly the keys {list(_MODEL_KEYS)}", received,
                              "docs/model-format.md.")
        copy = entry["copy"]
        if isinstance(copy, bool) or not isinstance(copy, int) or copy < 0:
            raise field_error(where, f"{name}.copy", "an integer >= 0 (a model copy of the latent)", copy,
                              "architecture.bank.copies lists the copies.")
        S = entry["S"]
        if not (isinstance(S, list) and len(S) == ny and all(_positive(v) for v in S)):
            raise field_error(where, f"{name}.S", f"a list of ny = {ny} finite numbers > 0", S,
                              "The low-passed innovation's mean square per output on validation runs.")
        for key in ("pole", "time_constant", "gain"):
            if not _positive(entry[key]):
                raise field_error(where, f"{name}.{key}", "a finite number > 0", entry[key],
                                  "Chosen on validation runs (docs/design.md).")
        for key in ("threshold", "start"):
            if not (is_number(entry[key]) and math.isfinite(entry[key]) and entry[key] >= 0):
                raise field_error(where, f"{name}.{key}", "a finite number >= 0", entry[key],
                                  "Chosen on validation runs (docs/design.md).")
        return cls(copy, float(entry["pole"]), tuple(float(v) for v in S), float(entry["time_constant"]),
                   float(entry["gain"]), float(entry["threshold"]), float(entry["start"]))

    def to_card(self) -> dict:
        return {"copy": self.copy, "pole": self.pole, "S": list(self.S), "time_constant": self.time_constant,
                "gain": self.gain, "threshold": self.threshold, "start": self.start}


@dataclass(frozen=True)
class SpreadTest:
    """The spread test's constants (``architecture.inflation.spread``; the module docstring's third recursion).

    Attributes
    ----------
    S : float
        The mean of the decoder ensemble's squared spread on in-distribution validation runs, > 0.
    time_constant : float
        Of its exponential average, in seconds, > 0.
    gain : float
        ``max(1, 1 + gain (h - threshold))``, > 0.
    threshold : float
        Of ``h``, >= 0.
    """

    S: float
    time_constant: float
    gain: float
    threshold: float

    @classmethod
    def from_card(cls, entry: Any, where: str) -> SpreadTest:
        """The constants of ``architecture.inflation.spread``, checked (one-line errors naming the field)."""
        name = f"architecture.{INFLATION}.{SPREAD}"
        if not isinstance(entry, Mapping) or set(entry) != set(_SPREAD_KEYS):
            received = sorted(entry) if isinstance(entry, Mapping) else entry
            raise field_error(where, name, f"an object with exactly the keys {list(_SPREAD_KEYS)}", received,
                              "docs/model-format.md.")
        for key in ("S", "time_constant", "gain"):
            if not _positive(entry[key]):
                raise field_error(where, f"{name}.{key}", "a finite number > 0", entry[key],
                                  "Chosen on validation runs (benchmarks/spread_test.py).")
        if not (is_number(entry["threshold"]) and math.isfinite(entry["threshold"]) and entry["threshold"] >= 0):
            raise field_error(where, f"{name}.threshold", "a finite number >= 0", entry["threshold"],
                              "Chosen on validation runs (benchmarks/spread_test.py).")
        return cls(float(entry["S"]), float(entry["time_constant"]), float(entry["gain"]), float(entry["threshold"]))

    def to_card(self) -> dict:
        return {"S": self.S, "time_constant": self.time_constant, "gain": self.gain, "threshold": self.threshold}

    def weight(self, dt: float) -> float:
        """The exponential average's weight of a new sample, ``a3 = 1 - exp(-dt / time_constant)``."""
        return -math.expm1(-dt / self.time_constant)


@dataclass(frozen=True)
class CopyLayout:
    """Where the model test's copy lives in the latent: ``xhat_i = reference + z[offset:offset + nx]``."""

    offset: int
    reference: tuple[float, ...]


@dataclass(frozen=True)
class Inflation:
    """The inflation's constants (``architecture.inflation``).

    Attributes
    ----------
    R : tuple of float
        The measurement noise variance per output (ny), > 0.
    c : float
        The mean of the residual statistic ``r`` on in-distribution validation runs, > 0.
    time_constant : float
        Of the statistic's exponential average, in seconds, > 0.
    model : ModelTest or None
        The model test of a bank with model copies (optional).
    spread : SpreadTest or None
        The spread test of a bank with a decoder ensemble (optional).
    """

    R: tuple[float, ...]
    c: float
    time_constant: float
    model: Optional[ModelTest] = None
    spread: Optional[SpreadTest] = None

    @classmethod
    def from_card(cls, entry: Any, where: str, ny: int) -> Inflation:
        """The constants of a card's ``architecture.inflation`` (``{"R": [ny numbers > 0], "c": number > 0,
        "time_constant": number > 0}``), checked; a bad one raises the package's one-line error naming it."""
        name = f"architecture.{INFLATION}"
        if not isinstance(entry, Mapping) or not set(_KEYS) <= set(entry) <= {*_KEYS, MODEL, SPREAD}:
            received = sorted(entry) if isinstance(entry, Mapping) else entry
            raise field_error(where, name, f"an object with exactly the keys {list(_KEYS)} (and optionally "
                              f"{MODEL!r} and {SPREAD!r})", received,
                              "docs/model-format.md (benchmarks/covariance_heads.py writes it).")
        R = entry["R"]
        if not (isinstance(R, list) and len(R) == ny and all(_positive(v) for v in R)):
            raise field_error(where, f"{name}.R", f"a list of ny = {ny} finite variances > 0", R,
                              "The measurement noise variance per output of the head's fitting runs.")
        for key in ("c", "time_constant"):
            if not _positive(entry[key]):
                raise field_error(where, f"{name}.{key}", "a finite number > 0", entry[key],
                                  "Chosen on validation runs by benchmarks/covariance_heads.py.")
        model = ModelTest.from_card(entry[MODEL], where, ny) if MODEL in entry else None
        spread = SpreadTest.from_card(entry[SPREAD], where) if SPREAD in entry else None
        return cls(tuple(float(v) for v in R), float(entry["c"]), float(entry["time_constant"]), model, spread)

    def to_card(self) -> dict:
        card: dict = {"R": list(self.R), "c": self.c, "time_constant": self.time_constant}
        if self.model is not None:
            card[MODEL] = self.model.to_card()
        if self.spread is not None:
            card[SPREAD] = self.spread.to_card()
        return card

    def initial_state(self) -> np.ndarray:
        """The carried state at a run's start: ``[1]``, with the model test ``[1, 0 (ny), 1, 0]``, and with the
        spread test one more ``1`` (``h_0``) at the end."""
        state = [1.0] if self.model is None else [1.0, *[0.0] * len(self.R), 1.0, 0.0]
        return np.asarray(state + ([1.0] if self.spread is not None else []))

    def weight(self, dt: float) -> float:
        """The exponential average's weight of a new sample, ``a = 1 - exp(-dt / time_constant)``."""
        return -math.expm1(-dt / self.time_constant)


def residual_statistic(y: np.ndarray, hx: np.ndarray, H: np.ndarray, P: np.ndarray, R: Any) -> np.ndarray:
    """``r = nu^T (H P H^T + diag(R))^-1 nu / ny`` with ``nu = y - h(xhat)`` (numpy; ``hx`` (..., ny) the values
    ``h(xhat)``, ``H`` (..., ny, nx) its Jacobians, ``P`` (..., nx, nx) the head's covariances) -> (...)."""
    nu = np.asarray(y, dtype=float) - hx
    S = H @ P @ np.swapaxes(H, -1, -2) + np.diag(np.asarray(R, dtype=float))
    return np.einsum("...i,...i->...", nu, np.linalg.solve(S, nu[..., None])[..., 0]) / nu.shape[-1]


def _copy_state(layout: CopyLayout, z: Any, nx: int) -> Any:
    """The model test's copy's state ``reference + z[offset:offset + nx]`` (numpy (..., nz) or CasADi (nz, 1))."""
    if isinstance(z, np.ndarray):
        return np.asarray(layout.reference) + z[..., layout.offset:layout.offset + nx]
    return ca.DM(list(layout.reference)) + z[layout.offset:layout.offset + nx]


def inflation_numpy(inflation: Inflation, system: System, dt: float, y: np.ndarray, xhat: np.ndarray,
                    P: np.ndarray, z: Optional[np.ndarray] = None, layout: Optional[CopyLayout] = None,
                    spread: Optional[np.ndarray] = None) -> np.ndarray:
    """The factors of runs (the module docstring's recursions; the reference of :func:`inflation_function`).

    Parameters
    ----------
    inflation : Inflation
    system : System
        The plant (its ``h`` and ``h_jac``).
    dt : float
        The sample period.
    y : numpy.ndarray, shape (M, N, ny)
    xhat : numpy.ndarray, shape (M, N, nx)
    P : numpy.ndarray, shape (M, N, nx, nx)
        The head's covariances of the estimates.
    z : numpy.ndarray, shape (M, N, nz), optional
        The latents (with the model test).
    layout : CopyLayout, optional
        Where its copy is in ``z`` (with the model test).
    spread : numpy.ndarray, shape (M, N), optional
        The decoder ensemble's spread at each sample (with the spread test).

    Returns
    -------
    numpy.ndarray, shape (M, N)
        1 at the first sample of each run.
    """
    M, N, nx = xhat.shape

    def h(x: np.ndarray) -> np.ndarray:
        return np.asarray(system.h.map(M * N)(x.reshape(-1, nx).T)).T.reshape(M, N, system.ny)

    H = np.asarray(system.h_jac.map(M * N)(np.asarray(xhat, dtype=float).reshape(-1, nx).T))
    H = H.reshape(system.ny, M * N, nx).transpose(1, 0, 2).reshape(M, N, system.ny, nx)
    r = residual_statistic(y, h(np.asarray(xhat, dtype=float)), H, P, inflation.R) / inflation.c
    a = inflation.weight(dt)
    m = np.ones((M, N))
    for k in range(1, N):
        m[:, k] = (1 - a) * m[:, k - 1] + a * r[:, k]
    factor = np.maximum(1.0, m)
    if inflation.spread is not None and spread is None:
        raise ValueError("spread: expected the decoder ensemble's spread (M, N) for an inflation with a spread test, "
                         "received None.")
    widen = (1.0 if inflation.spread is None or spread is None
             else spread_factor(inflation.spread, dt, np.asarray(spread, dtype=float)))
    test = inflation.model
    if test is None:
        return factor * widen
    if z is None or layout is None:
        raise ValueError("z, layout: expected the latents and the copy's layout for an inflation with a model test, "
                         "received None.")
    nu = np.asarray(y, dtype=float) - h(_copy_state(layout, np.asarray(z, dtype=float), nx))
    b, a2 = math.exp(-test.pole * dt), -math.expm1(-dt / test.time_constant)
    s, g, t = np.zeros((M, system.ny)), np.ones(M), 0.0
    for k in range(1, N):
        s = b * s + (1 - b) * nu[:, k]
        t = t + dt
        q = np.mean(s ** 2 / np.asarray(test.S), axis=-1) if t > test.start - dt / 2 else 1.0
        g = (1 - a2) * g + a2 * q
        factor[:, k] *= np.maximum(1.0, 1 + test.gain * (g / m[:, k] - test.threshold))
    return factor * widen


def spread_factor(test: SpreadTest, dt: float, spread: np.ndarray) -> np.ndarray:
    """``max(1, 1 + gain (h_k - threshold))`` of runs' spreads (M, N) -> (M, N) (``h_0 = 1``: 1 at the first
    sample, as the other factors)."""
    a3 = test.weight(dt)
    h = np.ones(spread.shape)
    for k in range(1, spread.shape[1]):
        h[:, k] = (1 - a3) * h[:, k - 1] + (a3 / test.S) * spread[:, k] ** 2
    out = np.maximum(1.0, 1 + test.gain * (h - test.threshold))
    out[:, 0] = 1.0
    return out


def inflation_function(inflation: Inflation, system: System, dt: float, nz: int,
                       layout: Optional[CopyLayout] = None) -> ca.Function:
    """``inflation(m, y, xhat, P, z) -> (m_next, P_inflated)``: one step of the recursions (module docstring) at the
    sample whose measurement is ``y`` (ny, 1), estimate ``xhat`` (nx, 1), head covariance ``P`` (nx, nx) and latent
    ``z`` (nz, 1); ``m`` the carried state after the previous sample (:meth:`Inflation.initial_state`'s size; the
    latent is read only by the model test, which needs ``layout``). With the spread test a sixth input, ``spread``
    (the decoder ensemble's spread at the sample). Plain scalar expressions (the residual's small solve expanded), so
    that its C equals the CasADi VM."""
    nx, ny = system.nx, system.ny
    size = inflation.initial_state().size
    m, y, x = ca.SX.sym("m", size), ca.SX.sym("y", ny), ca.SX.sym("xhat", nx)
    P, z = ca.SX.sym("P", nx, nx), ca.SX.sym("z", nz)
    nu = y - system.h(x)
    H = system.h_jac(x)
    S = ca.mtimes(ca.mtimes(H, P), H.T) + ca.diag(ca.DM(list(inflation.R)))
    r = ca.dot(nu, ca.solve(S, nu)) / ny
    a = inflation.weight(dt)
    m_next = (1 - a) * m[0] + (a / inflation.c) * r
    factor = ca.fmax(1.0, m_next)
    test = inflation.model
    if test is None:
        state = m_next
    else:
        if layout is None:
            raise ValueError("layout: expected where the model test's copy is in the latent, received None.")
        b, a2 = math.exp(-test.pole * dt), -math.expm1(-dt / test.time_constant)
        s = b * m[1:1 + ny] + (1 - b) * (y - system.h(_copy_state(layout, z, nx)))
        t = m[2 + ny] + dt
        q = ca.if_else(t > test.start - dt / 2, ca.sum1(s ** 2 / ca.DM(list(test.S))) / ny, 1.0)
        g = (1 - a2) * m[1 + ny] + a2 * q
        factor = factor * ca.fmax(1.0, 1 + test.gain * (g / m_next - test.threshold))
        state = ca.vertcat(m_next, s, g, t)
    inputs, names = [m, y, x, P, z], ["m", "y", "xhat", "P", "z"]
    if inflation.spread is not None:
        spread, a3 = ca.SX.sym("spread"), inflation.spread.weight(dt)
        h = (1 - a3) * m[size - 1] + (a3 / inflation.spread.S) * spread ** 2
        factor = factor * ca.fmax(1.0, 1 + inflation.spread.gain * (h - inflation.spread.threshold))
        state, inputs, names = ca.vertcat(state, h), [*inputs, spread], [*names, "spread"]
    return ca.Function("inflation", inputs, [state, factor * P], names, ["m_next", "P_inflated"])


def fold(step: ca.Function, name: str, n: int) -> ca.Function:
    """An observer's ``step`` or ``step_covariance`` folded over ``n`` steps (``mapaccum``): ``z`` and ``w`` (its
    first two inputs and outputs) carried from step to step, and the inflation's state ``m`` (a sixth input and
    fifth output, where the step has them: :attr:`kklcasadi.KKLObserver.step_covariance`)."""
    if step.n_in() == 6:
        return step.mapaccum(name, n, [0, 1, 5], [0, 1, 4])
    return step.mapaccum(name, n, [0, 1], [0, 1])
