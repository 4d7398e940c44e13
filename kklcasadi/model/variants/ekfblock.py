"""The augmented EKF as a block of the ``bank`` observer's latent (torch-free): a learned correction of it.

Over a family of plants (``kc.System(..., params=P)``) constant-gain model copies cannot estimate the
parameters (at the reference point the parameters' columns of the linearisation vanish); the augmented
EKF (:class:`kklcasadi.estimators.AugmentedEKF`: the states and the parameters as random-walk states) can.
This block runs that filter inside the latent, stepped once per sample by the augmented EKF's own step
(:attr:`kklcasadi.estimators.EKF.step`, the Function :meth:`~kklcasadi.estimators.EKF.simulate` folds; no
second implementation), so that the decoder reads its state and parameter estimates and their covariance
beside the filters and the copies, and may fit the state's residual over its estimate (the decoder starts
from the augmented EKF and learns what it misses: docs/design.md, "Over a family").

The block's latents are ``[s; c]``: ``s = [xa; vec(P)]`` (``na + na^2``, ``na = nx + n_params``, ``P``
column-major) the augmented EKF's state after the sample, and ``c`` a start flag. The latent starts at 0, as
the filters' (``c = 0``); the first step takes the filter's start, the prior updated with ``y_0``
(:attr:`~kklcasadi.estimators.EKF.start`), in place of ``s`` and sets ``c = 1``:

    z_k+1 = [step(c_k ? s_k : start(y_k), [u_k; y_k+1]); 1]

so ``s_k`` is :meth:`AugmentedEKF.simulate`'s state at every sample ``k >= 1`` (bit for bit on the CasADi VM);
at ``k = 0`` the block is 0, not the start (the decoder reads it there as it reads the filters' zero start).

The block has no continuous-time field: only the exact step runs it (``KKLObserver(discretization="rk4")``
refuses such a model). Its rows of the card's ``design`` are ``A = -I / dt`` and ``B = 0`` (they size the latent
and keep ``A`` Hurwitz; checked on load). The card records its settings in ``architecture.bank.ekf``
(:meth:`EKFBlock.to_card`; docs/model-format.md); there is no array.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np

from ...nets.specs import field_error
from ...plant.systems import System
from ...validation import Text, error, is_int, is_number
from .copies import fold_step

__all__ = ["EKFBlock", "EKF_BLOCK", "EKF_KEYS", "register_filter"]

#: The key of ``architecture.bank`` that holds the block's settings.
EKF_BLOCK = "ekf"
#: Its keys.
EKF_KEYS = ("process_std", "measurement_std", "param_walk", "q_scale", "r_scale", "substeps")


#: The augmented EKF's class (:class:`kklcasadi.estimators.AugmentedEKF`), registered by its module on import: the
#: estimators sit above the model layer (their C code goes through the observer's), so this module names none.
_FILTER: list = []


def register_filter(cls: Any) -> None:
    """Register the augmented EKF's class (``cls(system, dt, process_std=, measurement_std=, param_walk=, q_scale=,
    r_scale=, substeps=)`` with the Functions ``step`` and ``start`` of :class:`kklcasadi.estimators.EKF`)."""
    _FILTER[:] = [cls]


def _augmented_ekf(system: System, dt: float, **options: Any) -> Any:
    """The registered augmented EKF of ``system`` (``import kklcasadi`` registers it)."""
    if not _FILTER:
        raise error("estimators", "kklcasadi.estimators.augmented imported (import kklcasadi does so)",
                    Text("nothing registered"))
    return _FILTER[0](system, dt, **options)


def _family(system: System) -> System:
    """``system`` where it has parameters, else the family it was fixed from (:attr:`System.family`)."""
    family = system if system.n_params else system.family
    if family is None:
        raise error("system", "a plant with parameters (kc.System(..., params=P, param_box=...)) or one fixed from "
                    "such a family, whose augmented EKF the block runs", Text(f"{system.name!r}, without parameters"),
                    "Train over a family (--param-spread or a --plant with params=).")
    return family


@dataclass(frozen=True, eq=False)
class EKFBlock:
    """The augmented EKF of ``system`` as a latent block (see the module docstring).

    Parameters
    ----------
    system : System
        A plant with parameters (``n_params >= 1``), or one fixed from such a family (its :attr:`System.family`, which
        the block then runs), without angle states or outputs.
    dt : float
        The sample period.
    process_std : sequence of float (nx,)
        The plant states' process-noise std (:class:`kklcasadi.estimators.AugmentedEKF`'s).
    measurement_std : float
    param_walk : float
        The parameters' random walk (a fraction of the box width per square-root second).
    q_scale, r_scale : float
        Factors of the process-noise std and of the measurement std.
    substeps : int
        RK4 steps per sample of the filter's prediction.
    """

    system: System
    dt: float
    process_std: tuple
    measurement_std: float
    param_walk: float
    q_scale: float = 1.0
    r_scale: float = 1.0
    substeps: int = 1
    ekf: Any = field(init=False, repr=False)

    def __post_init__(self) -> None:
        system = _family(self.system)
        object.__setattr__(self, "system", system)
        if system.angle_states or system.angle_outputs:
            raise error("system", "a plant without angle states or outputs (the block's estimate is not read on the "
                        "circle)", Text(f"{system.name!r}, with angles"), "Train without the EKF block.")
        if not (is_int(self.substeps) and self.substeps >= 1):
            raise error("substeps", "a positive integer (RK4 steps per sample)", self.substeps)
        ekf = _augmented_ekf(system, self.dt, process_std=list(self.process_std), measurement_std=self.measurement_std,
                           param_walk=self.param_walk, q_scale=self.q_scale, r_scale=self.r_scale,
                           substeps=int(self.substeps))
        object.__setattr__(self, "process_std", tuple(float(v) for v in np.broadcast_to(
            np.asarray(self.process_std, dtype=float), (system.nx,))))
        object.__setattr__(self, "ekf", ekf)

    @classmethod
    def design(cls, system: System, dt: float, *, process_std: Any, measurement_std: float, param_walk: float,
               q_scale: float = 1.0, r_scale: float = 1.0) -> EKFBlock:
        """The block with the augmented EKF's automatic RK4 substeps (:func:`kklcasadi.plant.rk4.stable_substeps`
        of the augmented plant)."""
        system = _family(system)
        probe = _augmented_ekf(system, dt, process_std=process_std, measurement_std=measurement_std,
                             param_walk=param_walk, q_scale=q_scale, r_scale=r_scale)
        return cls(system, dt, tuple(np.broadcast_to(np.asarray(process_std, dtype=float), (system.nx,))),
                   float(measurement_std), float(param_walk), float(q_scale), float(r_scale), probe.substeps)

    @property
    def na(self) -> int:
        """The augmented state's size, ``nx + n_params``."""
        return int(self.ekf.system.nx)

    @property
    def ns(self) -> int:
        """The filter's state ``[xa; vec(P)]``, ``na + na^2``."""
        return self.na + self.na * self.na

    @property
    def nz(self) -> int:
        """The block's latents, ``ns + 1`` (the start flag last)."""
        return self.ns + 1

    def to_card(self) -> dict:
        """``architecture.bank.ekf``: the settings the block is rebuilt from."""
        return {"process_std": list(self.process_std), "measurement_std": float(self.measurement_std),
                "param_walk": float(self.param_walk), "q_scale": float(self.q_scale), "r_scale": float(self.r_scale),
                "substeps": int(self.substeps)}

    @staticmethod
    def check_card(entry: Any, where: str, nx: int) -> dict:
        """``architecture.bank.ekf`` checked (a one-line error naming the field); returns it."""
        fix = ('Write "ekf" as {"process_std": [s_1, ..., s_nx] (>= 0), "measurement_std": s > 0, "param_walk": w '
               '>= 0, "q_scale": q > 0, "r_scale": r > 0, "substeps": n >= 1} (docs/model-format.md).')
        if not (isinstance(entry, Mapping) and set(entry) == set(EKF_KEYS)):
            raise field_error(where, "architecture.bank.ekf", f"an object with the keys {list(EKF_KEYS)}", entry, fix)

        def finite(v: Any) -> bool:
            return is_number(v) and math.isfinite(v)

        std = entry["process_std"]
        if not (isinstance(std, list) and len(std) == nx and all(finite(v) and v >= 0 for v in std)):
            raise field_error(where, "architecture.bank.ekf.process_std", f"nx = {nx} finite numbers >= 0", std, fix)
        for name, low, strict in (("measurement_std", 0, True), ("param_walk", 0, False), ("q_scale", 0, True),
                                  ("r_scale", 0, True)):
            v = entry[name]
            if not (finite(v) and (v > low if strict else v >= low)):
                raise field_error(where, f"architecture.bank.ekf.{name}",
                                  f"a finite number {'>' if strict else '>='} {low}", v, fix)
        if not (is_int(entry["substeps"]) and entry["substeps"] >= 1):
            raise field_error(where, "architecture.bank.ekf.substeps", "a positive integer (RK4 steps per sample)",
                              entry["substeps"], fix)
        return dict(entry)

    @classmethod
    def from_card(cls, entry: Mapping[str, Any], system: System, dt: float) -> EKFBlock:
        """The block of a checked ``architecture.bank.ekf`` (:meth:`check_card`) for ``system``."""
        return cls(system, dt, tuple(entry["process_std"]), entry["measurement_std"], entry["param_walk"],
                   entry["q_scale"], entry["r_scale"], entry["substeps"])

    def linear_part(self) -> tuple[np.ndarray, np.ndarray]:
        """The block's rows of the card's ``design``: ``A = -I / dt`` (nz, nz) and ``B = 0`` (nz, ny) (placeholders:
        the block is a discrete step; see the module docstring)."""
        return -np.eye(self.nz) / self.dt, np.zeros((self.nz, self.system.ny))

    def step_function(self, name: str = "ekf_block_step") -> ca.Function:
        """CasADi ``(z, y, y_next, u) -> z_next`` (nz,): the augmented EKF's step over one sample (module
        docstring)."""
        ekf, ns = self.ekf, self.ns
        z, u = ca.MX.sym("z", self.nz), ca.MX.sym("u", self.system.nu)
        y, y_next = ca.MX.sym("y", self.system.ny), ca.MX.sym("y_next", self.system.ny)
        s = ca.if_else(z[ns] > 0.5, z[:ns], ekf.start(y))
        z_next = ca.vertcat(ekf.step(s, ca.vertcat(u, y_next)), ca.DM(1.0))
        return ca.Function(name, [z, y, y_next, u], [z_next], ["z", "y", "y_next", "u"], ["z_next"])

    def run(self, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The block's latents from ``z_0 = 0`` for many trials: :meth:`step_function` folded over the samples
        (``mapaccum``) and mapped over the trials on threads.

        Parameters
        ----------
        y : numpy.ndarray, shape (M, N, ny)
        u : numpy.ndarray, shape (M, N, nu)

        Returns
        -------
        numpy.ndarray, shape (M, N, nz)
        """
        return fold_step(self.step_function(), y, u)

    def state_rows(self) -> Sequence[int]:
        """The block's latents that hold the plant states' estimate ``xhat`` (nx), relative to the block."""
        return range(self.system.nx)
