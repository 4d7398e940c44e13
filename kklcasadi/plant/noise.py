"""Measurement noise as it is: Gaussian, heavy-tailed, with outliers, quantised (issue 46.3).

A :class:`NoiseModel` is written as a string, ``--noise-model`` on the command line:

==========================  =====================================================================
``gauss``                   ``v = sigma n``, ``n ~ N(0, 1)`` (the protocol's noise; the default)
``student-t:NU``            ``v = sigma t``, ``t`` Student-t with ``NU > 0`` degrees of freedom
                            (``sigma`` is its scale; its variance ``sigma^2 NU / (NU - 2)`` is
                            infinite for ``NU <= 2``)
``outliers:P,K``            each sample's noise is, with probability ``P``, ``K`` times its draw
                            (``K sigma n``: a mixture of two Gaussians, or of two Student-t)
``quantised:STEP``          the measurement is rounded to the grid ``STEP k``:
                            ``y = STEP round((h(x) + v) / STEP)`` (half away from the grid cell's
                            centre, as ``floor(. + 1/2)``), after the noise
==========================  =====================================================================

and combined with ``+`` (one base distribution, ``gauss`` unless ``student-t`` is given):
``student-t:3+outliers:0.05,10+quantised:0.2``. ``sigma`` is the run's ``measurement_std``.

Random draws (what makes runs reproducible): per trial, after the process noise, the base draws
``(N, ny)`` (``normal(0, 1)`` or ``standard_t``), then, with outliers, ``(N, ny)`` uniforms;
the Gaussian model draws exactly what the simulator drew before noise models existed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import casadi as ca
import numpy as np

from ..validation import Text, error

__all__ = ["NoiseModel", "GAUSS", "noise_model"]

#: The spelling of each part of a noise model.
PARTS = {"gauss": "gauss", "student-t": "student-t:NU", "outliers": "outliers:P,K", "quantised": "quantised:STEP"}


@dataclass(frozen=True)
class NoiseModel:
    """The measurement noise of a run: ``y_k = q(h(x_k) + v_k)``.

    Attributes
    ----------
    nu : float or None
        Degrees of freedom of a Student-t base distribution (> 0); None: Gaussian.
    outlier_p : float
        Probability that a sample's noise is scaled by ``outlier_k`` (0 <= p < 1).
    outlier_k : float
        The outliers' scale (>= 1).
    step : float
        Quantisation step of the measurement (0: none).
    """

    nu: Optional[float] = None
    outlier_p: float = 0.0
    outlier_k: float = 1.0
    step: float = 0.0

    def __post_init__(self) -> None:
        if self.nu is not None and not (math.isfinite(self.nu) and self.nu > 0):
            raise error("noise_model", "student-t:NU with NU > 0", Text(f"NU = {self.nu}"))
        if not 0.0 <= self.outlier_p < 1.0 or not (math.isfinite(self.outlier_k) and self.outlier_k >= 1.0):
            raise error("noise_model", "outliers:P,K with 0 <= P < 1 and K >= 1",
                        Text(f"P = {self.outlier_p}, K = {self.outlier_k}"))
        if not (math.isfinite(self.step) and self.step >= 0.0):
            raise error("noise_model", "quantised:STEP with STEP > 0", Text(f"STEP = {self.step}"))

    @property
    def gaussian(self) -> bool:
        """Whether this is the plain Gaussian model."""
        return self == GAUSS

    def __str__(self) -> str:
        parts = ["gauss" if self.nu is None else f"student-t:{self.nu:g}"]
        if self.outlier_p > 0:
            parts.append(f"outliers:{self.outlier_p:g},{self.outlier_k:g}")
        if self.step > 0:
            parts.append(f"quantised:{self.step:g}")
        return "+".join(parts)

    def sample(self, rng: np.random.Generator, shape: tuple[int, ...], std: float) -> np.ndarray:
        """Additive noise ``v`` of the given shape and scale ``std`` (the draws of the module docstring)."""
        base = rng.normal(0.0, 1.0, shape) if self.nu is None else rng.standard_t(self.nu, shape)
        if self.outlier_p > 0:
            base = np.where(rng.random(shape) < self.outlier_p, self.outlier_k * base, base)
        return base * std

    def measure(self, y: Any) -> Any:
        """The measurement of a noisy output ``h(x) + v``: quantised when the model says so.

        ``y`` is a numpy array or a CasADi expression (the closed loop's measured output).
        """
        if self.step == 0:
            return y
        floor = ca.floor if isinstance(y, (ca.SX, ca.MX, ca.DM)) else np.floor
        return self.step * floor(y / self.step + 0.5)

    def log_density(self, v: Any, std: float) -> Any:
        """``log p(v)`` of the additive noise per entry, up to a constant (numpy or CasADi), before quantisation.

        Gaussian: ``-v^2 / (2 sigma^2)``; Student-t: ``-(nu + 1) / 2 log(1 + v^2 / (nu sigma^2))``; with
        outliers the log of the two-component mixture (constants kept between the components).
        """
        if isinstance(v, (ca.SX, ca.MX, ca.DM)):
            log, exp = ca.log, ca.exp
        else:
            log, exp = np.log, np.exp

        def component(scale: float) -> Any:
            z2 = (v / scale) ** 2
            if self.nu is None:
                return -0.5 * z2 - math.log(scale)
            return -0.5 * (self.nu + 1.0) * log(1.0 + z2 / self.nu) - math.log(scale)

        if self.outlier_p == 0:
            return component(std)
        a = component(std) + math.log(1.0 - self.outlier_p)
        b = component(self.outlier_k * std) + math.log(self.outlier_p)
        top = ca.fmax(a, b) if isinstance(v, (ca.SX, ca.MX, ca.DM)) else np.maximum(a, b)
        return top + log(exp(a - top) + exp(b - top))


    def log_likelihood(self, y: Any, h: Any, std: float) -> Any:
        """``log p(y | h)`` per output entry, up to a constant (CasADi or numpy): what a particle filter weighs by.

        Without quantisation :meth:`log_density` of ``y - h``. With it, the probability of the
        measured cell ``[y - STEP/2, y + STEP/2)``: a difference of ``erf`` for a Gaussian base (with
        outliers the mixture of the two; to about 1e-16 absolute, so below that the logarithm is
        floored at ``log 1e-300``: weights nobody resamples), and for a Student-t base its density at
        the cell's centre times the step (an approximation, good when ``STEP`` is below the scale).
        """
        if self.step == 0 or self.nu is not None:
            return self.log_density(y - h, std)
        symbolic = isinstance(y, (ca.SX, ca.MX, ca.DM)) or isinstance(h, (ca.SX, ca.MX, ca.DM))
        if symbolic:
            erf, log, fmax = ca.erf, ca.log, ca.fmax
        else:
            from scipy.special import erf

            log, fmax = np.log, np.maximum

        def cell(scale: float) -> Any:
            a = (y - h + 0.5 * self.step) / (math.sqrt(2.0) * scale)
            b = (y - h - 0.5 * self.step) / (math.sqrt(2.0) * scale)
            return 0.5 * (erf(a) - erf(b))

        probability = cell(std)
        if self.outlier_p > 0:
            probability = (1.0 - self.outlier_p) * probability + self.outlier_p * cell(self.outlier_k * std)
        return log(fmax(probability, 1e-300))


#: The protocol's Gaussian measurement noise.
GAUSS = NoiseModel()


def _numbers(text: str, count: int, part: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count:
        raise error("noise_model", f"{PARTS[part]} ({count} number{'s' if count > 1 else ''} after ':')",
                    Text(f"{part}:{text}"))
    return values


def noise_model(spec: Any) -> NoiseModel:
    """A :class:`NoiseModel` from its string (``"student-t:2+quantised:0.1"``), or the model itself; None: Gaussian.

    Raises
    ------
    ValueError
        Naming ``noise_model``, the part that is wrong and how to write it.
    """
    if spec is None:
        return GAUSS
    if isinstance(spec, NoiseModel):
        return spec
    if not isinstance(spec, str) or not spec.strip():
        raise error("noise_model", "a string such as 'gauss', 'student-t:2', 'outliers:0.05,10', 'quantised:0.2' "
                    "or a combination with '+'", spec, kind=TypeError if not isinstance(spec, str) else ValueError)
    options: dict[str, Any] = {}
    seen: set[str] = set()
    for item in spec.strip().split("+"):
        name, _, args = item.strip().partition(":")
        if name not in PARTS:
            raise error("noise_model", f"parts among {list(PARTS.values())} joined with '+'", Text(item))
        if name in seen or (name in ("gauss", "student-t") and seen & {"gauss", "student-t"}):
            raise error("noise_model", "each part once and one base distribution (gauss or student-t)", Text(spec))
        seen.add(name)
        if name == "gauss":
            if args:
                raise error("noise_model", "'gauss' without arguments (its scale is measurement_std)", Text(item))
        elif name == "student-t":
            (options["nu"],) = _numbers(args, 1, name)
        elif name == "outliers":
            options["outlier_p"], options["outlier_k"] = _numbers(args, 2, name)
        else:
            (options["step"],) = _numbers(args, 1, name)
            if options["step"] <= 0:
                raise error("noise_model", "quantised:STEP with STEP > 0", Text(item))
    return NoiseModel(**options)
