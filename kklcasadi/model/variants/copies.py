"""Model copies: constant-gain observers of the plant inside the ``bank`` observer's latent.

Copy ``i`` runs ``xhat_i' = f(xhat_i, u) + L_i (y - h(xhat_i))`` from ``xhat_i(0) = r`` (the centre of
the plant's X0 box); its latents are ``z_i = xhat_i - r`` (0 at the start, as the filters'). The gain
is the Kalman-Bucy gain of the plant linearised at ``(r, u = 0)``: ``L_i = P_i H^T`` with ``P_i`` the
stabilising solution of ``F P + P F^T - P H^T H P + w_i I = 0`` (process intensity ``w_i I`` against unit
measurement intensity; the protocol's EKF, ``Q = (sigma dt)^2 I`` per sample and ``R = sigma^2 I``, is
``w = 1``). A larger ``w`` gives a faster copy that trusts the measurement more.

The copies carry what a filter bank of the signals cannot: the plant's own response to the input,
for any input, from the exact model. The decoder reads them beside the filters, so the estimate is
a learned correction of the model-based ones (docs/design.md, "Model copies").

Between samples ``y`` is held first-order and ``u`` held, and each interval takes ``substeps`` RK4
steps; after each sample a copy's state is clipped to ``r +- bound`` (the box scaled by
``BOUND_SCALE`` about its centre), so a copy that an input throws off the plant's range comes back
instead of blowing up. The latent's linear part goes in the card's ``(A, B)`` (rows
``F - L_i H`` and ``L_i``, :meth:`ModelCopies.linear_part`) and the remainder
``f(r + z_i, u) - L_i h(r + z_i) - (F - L_i H) z_i`` is the observer's input term on those rows, so
``A z + B y + input_term`` is the copies' field.

A copy carries only the states the plant's equations read (:func:`read_states`): a state that neither ``xdot``
nor ``y`` depends on (an integrator read by nothing, such as a rotary pendulum's arm angle measured by the pendulum
encoder alone) is left out, since its linearisation keeps an eigenvalue at 0 that no gain moves. The copy then runs
the plant on the ``nk`` states it carries, the others held at 0 (nothing reads them), and its gain is designed on
that reduced linearisation; where it carries every state it is the copy above, bit for bit.

Arrays ``copies/gains`` (m, nk, ny), ``copies/reference`` (nk,) and ``copies/bound`` (nk,) (``nk = nx`` where a copy
carries every state); the card's ``architecture.bank.copies`` records the weights, the substeps and, where a copy
carries fewer than ``nx``, the ``states`` it carries (docs/model-format.md).

A copy may run the plant at parameter values of its own (a plant of a family, ``kc.System(..., params=P)``):
copy ``i`` then observes the plant ``system.at(params_i)``, its gain and linear part that plant's at ``(r, u = 0)``.
Copies of one observer at several points of the parameter box are a multiple-model estimator whose innovations
tell the decoder which plant it is looking at (docs/design.md, "Over a family"). Without ``params`` every copy
runs the plant's nominal ``f`` and ``h``; the card records each copy's parameter values where they are their own
(``params``, docs/model-format.md).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional, Sequence

import casadi as ca
import numpy as np
import scipy.linalg

from ...plant.rk4 import rk4_step
from ...plant.systems import System, read_states
from ...validation import Text, error

__all__ = ["ModelCopies", "BOUND_SCALE", "COPY_ARRAYS", "copy_count", "read_states", "copy_plants", "copies_plant",
           "fold_step"]

#: Half-width of the clip box of a copy's state, in half-widths of the plant's X0 box (the escape box of
#: the operational runs, :attr:`kklcasadi.plant.runs.RolloutConfig.escape_scale`).
BOUND_SCALE = 10.0
#: The arrays of the copies in a model file.
COPY_ARRAYS = ("copies/gains", "copies/reference", "copies/bound")


def copy_count(arrays: Mapping[str, Any]) -> int:
    """Latents of the model copies in ``arrays`` (``m nk``; 0 where there are none)."""
    gains = arrays.get("copies/gains")
    return 0 if gains is None else int(np.prod(np.shape(gains)[:2]))


def fold_step(step: ca.Function, y: np.ndarray, u: np.ndarray, sym: Any = ca.MX) -> np.ndarray:
    """A latent block's trajectories from ``z_0 = 0`` for many trials: its step ``(z, y, y_next, u) -> z_next`` folded
    over the samples (``mapaccum``) and mapped over the trials on threads (``sym``: the symbols it is packed with).

    Parameters
    ----------
    step : casadi.Function
    y : numpy.ndarray, shape (M, N, ny)
    u : numpy.ndarray, shape (M, N, nu)

    Returns
    -------
    numpy.ndarray, shape (M, N, nz)
    """
    (M, N, ny), nz = y.shape, step.size1_in(0)
    z = np.zeros((M, N, nz))
    if N < 2:
        return z
    zs, p = sym.sym("z", nz), sym.sym("p", 2 * ny + u.shape[2])                    # p = [y_k; y_k+1; u_k]
    packed = ca.Function(f"{step.name()}_packed", [zs, p], [step(zs, p[:ny], p[ny:2 * ny], p[2 * ny:])])
    runs = packed.mapaccum(f"{step.name()}_run", N - 1).map(M, "thread", min(os.cpu_count() or 1, M))
    params = np.concatenate([y[:, :-1], y[:, 1:], u[:, :-1]], axis=2).reshape(M * (N - 1), -1)
    z[:, 1:] = np.asarray(runs(np.zeros((nz, M)), params.T)).T.reshape(M, N - 1, nz)
    return z


def copy_plants(system: System, params: Any, m: int) -> list[System]:
    """The plant each of ``m`` copies runs: ``system`` itself (``params`` None), or ``family.at(params[i])``, the
    family ``system`` itself where it has parameters, else the one it was fixed from (:attr:`System.family`).

    Raises
    ------
    ValueError
        Where ``params`` is not ``m`` finite rows of the plant's ``n_params`` values, or the plant has none.
    """
    if params is None:
        return [system] * m
    family = system if system.n_params else system.family
    if family is None:
        raise error("params", f"None for plant {system.name!r}, which declares no parameters",
                    Text("parameter values per model copy"), "Give the family: kc.System(..., params=P, "
                    "param_box=...) or its .at(values) (load_observer(path, system=family) does so).")
    p = np.asarray(params, dtype=float)
    if p.shape != (m, family.n_params) or not np.all(np.isfinite(p)):
        raise error("params", f"finite parameter values of shape (m = {m} copies, n_params = {family.n_params})",
                    Text(f"shape {p.shape}") if p.size > 20 or p.shape != (m, family.n_params) else p.tolist())
    return [family.at(row) for row in p]


def copies_plant(card: Mapping[str, Any], where: Any) -> Optional[System]:
    """The nominal plant, fixed from its family (:attr:`System.family`), of a card whose model copies run at
    parameter values of their own (``architecture.bank.copies.params``) or whose latent holds the augmented EKF
    block (``architecture.bank.ekf``); None where neither. The family is the
    shipped one of the card's ``system.name``, its box the one the card's runs drew from (``training.runs.params``).

    Raises
    ------
    ValueError
        Where kklcasadi ships no family of that name, or the card does not record the box (``where``: the card).
    """
    from ...plant import systems

    bank = card["architecture"].get("bank", {})
    if "params" in bank.get("copies", {}):
        field, what = "architecture.bank.copies.params", "model copies at parameter values"
    elif "ekf" in bank:
        field, what = "architecture.bank.ekf", "the augmented EKF block over the parameters"
    else:
        return None
    name, record = card["system"]["name"], card.get("training", {}).get("runs", {}).get("params")
    if name not in systems.families() or not isinstance(record, Mapping):
        raise ValueError(f"{where}: '{field}': {what} of {name!r}'s family, which kklcasadi cannot rebuild (a shipped "
                         "family, the box in the card's training.runs.params). Pass the family: load_observer(path, "
                         "system=kc.System(..., params=P, param_box=...)).")
    box, nominal = np.asarray(record["box"], dtype=float), np.asarray(record["nominal"], dtype=float)
    family = systems.get(name, param_spread=float(np.max(0.5 * (box[:, 1] - box[:, 0]) / np.abs(nominal))))
    return family.at(family.param_nominal)


def _jacobians(system: System, x: Any, states: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``F = df_K/dx_K`` and ``H = dh/dx_K`` at ``(x, u = 0)`` (``K`` = ``states``)."""
    F, _ = system.f_jac(x, np.zeros(system.nu))
    F, H = np.array(F, dtype=float), np.array(system.h_jac(x), dtype=float)
    if len(states) == system.nx:
        return F, H
    return F[np.ix_(states, states)], H[:, states]


def _held(system: System, xk: Any, states: tuple[int, ...]) -> Any:
    """The plant state whose ``states`` are ``xk`` (numbers or a CasADi column) and the others 0."""
    if len(states) == system.nx:
        return xk
    if isinstance(xk, np.ndarray):
        x = np.zeros(system.nx)
        x[list(states)] = xk
        return x
    at = {i: k for k, i in enumerate(states)}
    return ca.vertcat(*[xk[at[i]] if i in at else 0 for i in range(system.nx)])


def _over(system: System, states: tuple[int, ...]) -> str:
    """`` over the states ...`` where a copy leaves states out, for its messages."""
    return "" if len(states) == system.nx else f" over the states its equations read {list(states)}"


@dataclass(frozen=True, eq=False)
class ModelCopies:
    """Constant-gain observers of ``system`` (see the module docstring).

    Parameters
    ----------
    system : System
        The plant (its ``f`` and ``h``). A copy's angle state follows the unwrapped measurement (the plant's
        field periodic in it) and is clipped as any state: a plant that turns more than ``bound`` from ``r``
        (``BOUND_SCALE`` half-widths of its box) leaves the copy behind.
    gains : array_like, shape (m, nk, ny)
        ``L_i``.
    reference : array_like, shape (nk,)
        ``r``: every copy's initial state (of the states it carries), and the latents' origin.
    bound : array_like, shape (nk,)
        Half-widths (> 0) of the box about ``r`` each copy's state is clipped to after each sample.
    substeps : int
        RK4 steps per sample interval.
    states : sequence of int or None
        The ``nk`` states a copy carries, ascending (None: all ``nx``); every other state must be one the plant's
        equations do not read (:func:`read_states`). The others are held at 0.
    params : array_like, shape (m, n_params), optional
        Each copy's parameter values (a plant with ``params``): copy ``i`` runs ``system.at(params[i])``.
        None: every copy runs the plant's nominal ``f`` and ``h``.
    """

    system: System
    gains: np.ndarray
    reference: np.ndarray
    bound: np.ndarray
    substeps: int = 2
    states: tuple[int, ...] = None  # type: ignore[assignment]     # None: all nx (set in __post_init__)
    params: Optional[np.ndarray] = None
    _plants: list = field(init=False, repr=False)

    def __post_init__(self) -> None:
        nx, ny = self.system.nx, self.system.ny
        states = tuple(range(nx)) if self.states is None else self.states
        if not (isinstance(states, (tuple, list)) and states and all(
                isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in states)
                and list(states) == sorted(set(states)) and 0 <= states[0] and states[-1] < nx):
            raise error("states", f"ascending distinct state indices in [0, nx = {nx}), at least one", self.states)
        states = tuple(int(i) for i in states)
        if len(states) < nx:
            unread = set(range(nx)) - set(read_states(self.system))
            left = [i for i in range(nx) if i not in states and i not in unread]
            if left:
                raise error("states", f"every state {self.system.name}'s equations read (a copy leaves out only the "
                            f"states that neither xdot nor y depends on: {sorted(unread)})",
                            Text(f"{list(states)}, without {left}"))
        object.__setattr__(self, "states", states)
        nk = len(states)
        gains = np.asarray(self.gains, dtype=float)
        if gains.ndim != 3 or gains.shape[1:] != (nk, ny) or gains.shape[0] < 1 or not np.all(np.isfinite(gains)):
            raise error("gains", f"finite gains of shape (m >= 1, nk = {nk}, ny = {ny})", gains.shape)
        for name, value in (("reference", self.reference), ("bound", self.bound)):
            arr = np.asarray(value, dtype=float)
            if arr.shape != (nk,) or not np.all(np.isfinite(arr)):
                raise error(name, f"nk = {nk} finite numbers (one per state a copy carries)",
                            arr.tolist() if arr.size < 10 else arr.shape)
            object.__setattr__(self, name, arr)
        if np.any(self.bound <= 0):
            raise error("bound", "half-widths > 0", self.bound.tolist())
        if isinstance(self.substeps, bool) or not isinstance(self.substeps, (int, np.integer)) or self.substeps < 1:
            raise error("substeps", "a positive integer (RK4 steps per sample)", self.substeps)
        object.__setattr__(self, "gains", gains)
        object.__setattr__(self, "substeps", int(self.substeps))
        object.__setattr__(self, "_plants", copy_plants(self.system, self.params, gains.shape[0]))
        if self.params is not None:
            object.__setattr__(self, "params", np.array(self.params, dtype=float))

    @classmethod
    def design(cls, system: System, weights: Sequence[Any], *, substeps: int = 2,
               bound_scale: float = BOUND_SCALE, params: Any = None) -> ModelCopies:
        """Copies with the Kalman-Bucy gains of ``system`` linearised at its box centre, over the states its
        equations read (:func:`read_states`; the others are left out of the copies).

        Parameters
        ----------
        system : System
        weights : sequence of float or of array_like (nx,)
            Process intensities, one entry per copy, against unit measurement intensity: ``w_i > 0`` (``w_i I``)
            or ``nx`` intensities ``>= 0``, not all 0 (a diagonal: a rig's noise per state, where a force acts).
        substeps : int
            RK4 steps per sample interval.
        bound_scale : float
            The clip box: the X0 box scaled by this about its centre.
        params : array_like, shape (m, n_params), optional
            Each copy's parameter values (see the class); None: the nominal plant.

        Raises
        ------
        ValueError
            Where a weight is neither, or the linearisation is not detectable from ``y``.
        """
        if isinstance(weights, (str, bytes)) or not isinstance(weights, (list, tuple, np.ndarray)) or not len(weights):
            raise error("weights", "one or more finite process intensities > 0, one per copy", weights)
        intensities = []
        for wi in weights:
            q = np.asarray(wi, dtype=float)
            if not (q.ndim == 0 or q.shape == (system.nx,)) or not np.all(np.isfinite(q)) or np.any(q < 0) \
                    or not np.any(q > 0) or (q.ndim == 0 and q <= 0):
                raise error("weights", "one or more finite process intensities > 0, one per copy (or per copy "
                            f"nx = {system.nx} of them >= 0, not all 0)", list(weights))
            intensities.append(np.diag(np.broadcast_to(q, (system.nx,)).astype(float)))
        if not (np.isfinite(bound_scale) and bound_scale > 0):
            raise error("bound_scale", "a finite number > 0", bound_scale)
        states = read_states(system)
        box = np.asarray(system.x0_box, dtype=float)[list(states)]
        r = box.mean(axis=1)
        gains = []
        for wi, Q, plant in zip(weights, intensities, copy_plants(system, params, len(weights))):
            F, H = _jacobians(plant, _held(system, r, states), states)
            Q = Q[np.ix_(states, states)]
            wi = f"{float(wi):g}" if np.ndim(wi) == 0 else "(" + ", ".join(f"{float(v):g}" for v in wi) + ")"
            try:
                P = scipy.linalg.solve_continuous_are(F.T, H.T, Q, np.eye(system.ny))
            except (np.linalg.LinAlgError, ValueError) as exc:
                raise error("weights", "weights with a stabilising Kalman-Bucy gain", Text(
                    f"{wi}, with no stabilising Kalman-Bucy gain: {system.name} linearised at its box centre "
                    f"{r.tolist()}{_over(system, states)} is not detectable from y ({exc})"),
                    "Train without model copies.") from exc
            L = P @ H.T
            if np.max(np.linalg.eigvals(F - L @ H).real) >= 0:
                raise error("weights", "weights with a stabilising Kalman-Bucy gain", Text(
                    f"{wi}, whose gain does not stabilise {system.name} linearised at its box centre"
                    f"{_over(system, states)}"),
                    "Train without model copies.")
            gains.append(L)
        return cls(system, np.stack(gains), r, 0.5 * (box[:, 1] - box[:, 0]) * bound_scale, substeps, states,
                   params)

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any], system: System, substeps: int,
                    states: Optional[Sequence[int]] = None, params: Any = None) -> ModelCopies:
        """The copies of a model's arrays (:meth:`arrays`) for ``system``, carrying ``states`` (None: all), each at
        ``params`` (the card's; None: the nominal plant)."""
        missing = [k for k in COPY_ARRAYS if k not in arrays]
        if missing:
            raise error("arrays", f"the model copies' arrays {list(COPY_ARRAYS)}", f"none of {missing}")
        return cls(system, np.asarray(arrays["copies/gains"]), np.asarray(arrays["copies/reference"]),
                   np.asarray(arrays["copies/bound"]), substeps,
                   tuple(range(system.nx)) if states is None else tuple(states), params)

    @property
    def carries_all(self) -> bool:
        """Whether a copy carries every state of the plant (the card then records no ``states``)."""
        return len(self.states) == self.system.nx

    def arrays(self) -> dict[str, np.ndarray]:
        """``copies/gains`` (m, nk, ny), ``copies/reference`` (nk,), ``copies/bound`` (nk,)."""
        return {"copies/gains": self.gains.copy(), "copies/reference": self.reference.copy(),
                "copies/bound": self.bound.copy()}

    @property
    def m(self) -> int:
        """Number of copies."""
        return self.gains.shape[0]

    @property
    def nk(self) -> int:
        """States a copy carries (``nx`` where it carries every one)."""
        return len(self.states)

    @property
    def nz(self) -> int:
        """Latents of the copies, ``m nk``."""
        return self.m * self.nk

    def linear_part(self) -> tuple[np.ndarray, np.ndarray]:
        """The latent's linear part on the copies' rows: ``A`` (nz, nz) block diagonal ``F - L_i H`` and
        ``B`` (nz, ny) the stacked ``L_i`` (``F``, ``H`` the Jacobians of the carried states' field and of ``h``
        with respect to them, at ``(r, u = 0)``, of copy ``i``'s plant)."""
        blocks = []
        for L, plant in zip(self.gains, self._plants):
            F, H = _jacobians(plant, _held(self.system, self.reference, self.states), self.states)
            blocks.append(F - L @ H)
        A = scipy.linalg.block_diag(*blocks)
        return A, np.vstack(list(self.gains))

    def _split(self, z: Any) -> list:
        nk = self.nk
        return [z[i * nk:(i + 1) * nk] for i in range(self.m)]

    def _plant(self, zi: Any, u: Any, plant: System) -> tuple[Any, Any]:
        """The carried states' field and the output, ``(f_K(x, u), h(x))`` of the copy's ``plant``, at the plant
        state ``x`` of a copy's latents ``zi`` (``x_K = r + zi``, the other states held at 0)."""
        r = ca.DM(self.reference)                       # r + zi twice: the graph of a full copy as it always was
        f = plant.f(_held(self.system, r + zi, self.states), u)
        return ((f if self.carries_all else ca.vertcat(*[f[i] for i in self.states])),
                plant.h(_held(self.system, r + zi, self.states)))

    def field(self, z: Any, y: Any, u: Any) -> Any:
        """The copies' field ``f_K(x_i, u) + L_i (y - h(x_i))`` (nz, 1) at CasADi column vectors, ``x_i`` the plant
        state with ``x_K = r + z_i`` (:attr:`states` ``K``; the others held at 0)."""
        parts = []
        for zi, L, plant in zip(self._split(z), self.gains, self._plants):
            f, h = self._plant(zi, u, plant)
            parts.append(f + ca.mtimes(ca.DM(L), y - h))
        return ca.vertcat(*parts)

    def remainder(self, z: Any, u: Any) -> Any:
        """The field less its linear part, ``field - A z - B y`` (nz, 1): independent of ``y``."""
        A, _ = self.linear_part()
        parts = []
        for zi, L, plant in zip(self._split(z), self.gains, self._plants):
            f, h = self._plant(zi, u, plant)
            parts.append(f - ca.mtimes(ca.DM(L), h))
        return ca.vertcat(*parts) - ca.mtimes(ca.DM(A), z)

    def step_function(self, dt: float, name: str = "copies_step") -> ca.Function:
        """CasADi ``(z, y, y_next, u) -> z_next`` (nz,): ``substeps`` RK4 steps of :meth:`field` over one
        sample interval (``y`` first-order hold, ``u`` held), then the clip to ``+- bound``."""
        z, u = ca.SX.sym("z", self.nz), ca.SX.sym("u", self.system.nu)
        y, y_next = ca.SX.sym("y", self.system.ny), ca.SX.sym("y_next", self.system.ny)
        z_next = rk4_step(lambda s, zz: self.field(zz, y + s * (y_next - y), u), z, float(dt), self.substeps)
        hi = ca.DM(np.tile(self.bound, self.m))
        z_next = ca.fmin(ca.fmax(z_next, -hi), hi)
        return ca.Function(name, [z, y, y_next, u], [z_next], ["z", "y", "y_next", "u"], ["z_next"])

    def run(self, y: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """The copies' latents from ``z_0 = 0`` for many trials at once: the step of :meth:`step_function`
        folded over the samples (``mapaccum``) and mapped over the trials on threads.

        Parameters
        ----------
        y : numpy.ndarray, shape (M, N, ny)
        u : numpy.ndarray, shape (M, N, nu)
        dt : float

        Returns
        -------
        numpy.ndarray, shape (M, N, nz)
        """
        return fold_step(self.step_function(dt), y, u, ca.SX)

