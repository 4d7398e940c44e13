"""Plants built from a plant: the parameters as states (for the augmented EKF and the particle filter
over states and parameters) and effects outside a plant's declared family (for the robustness benchmark).

:func:`augmented` turns a family ``xdot = f(x, u, p)``, ``y = h(x, p)`` into a plant with the state
``[x; p]`` (and optionally ``[x; p; d]``, a constant input disturbance ``u + d``: the standard
offset-free construction) whose extra states are constant; a filter that adds a random walk to them
estimates the parameters. :func:`perturbed` writes a plant that no parameter value of the family
gives: unmodelled damping and an input gain error.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from ..validation import Text, error, finite_number, nonnegative_number
from .systems import System

__all__ = ["augmented", "perturbed", "forced_rows"]


def augmented(system: System, *, input_disturbance: bool = False, disturbance_box: Any = None) -> System:
    """The plant with its parameters (and an input disturbance) as constant states.

    Parameters
    ----------
    system : System
        A plant; its parameters (if any) become the states ``x[nx:nx + n_params]``.
    input_disturbance : bool
        Add ``d`` (nu,) with ``u`` replaced by ``u + d`` in the field, ``d' = 0``.
    disturbance_box : array_like, shape (nu, 2), optional
        The initial box of ``d`` (its prior); default ``[-1, 1]`` per input.

    Returns
    -------
    System
        Named ``<name>_augmented``, states ``[x; p; d]`` with box ``[x0_box; param_box; disturbance_box]``,
        no parameters; at ``p`` the nominal values and ``d = 0`` its first ``nx`` rows are the plant's.

    Raises
    ------
    ValueError
        A plant without parameters and no input disturbance (nothing to augment).
    """
    if not isinstance(system, System):
        raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
    if not system.n_params and not input_disturbance:
        raise error("system", "a plant with parameters, or input_disturbance=True",
                    Text(f"plant {system.name!r} without parameters"))
    x, u = system.x_sym, system.u_sym
    p = system.p_sym if system.n_params else ca.SX.zeros(0, 1)
    xdot = system.xdot_param_expr
    y = system.y_param_expr
    boxes = [system.x0_box] + ([system.param_box] if system.n_params else [])
    states = [x, p]
    if input_disturbance:
        d = ca.SX.sym("d", system.nu)
        xdot = ca.substitute(xdot, u, u + d)
        box = np.tile([-1.0, 1.0], (system.nu, 1)) if disturbance_box is None else np.asarray(disturbance_box, float)
        if box.shape != (system.nu, 2):
            raise error("disturbance_box", f"shape (nu, 2) = ({system.nu}, 2)", Text(f"shape {box.shape}"))
        boxes.append(box)
        states.append(d)
    elif disturbance_box is not None:
        raise error("disturbance_box", "None without input_disturbance=True", np.asarray(disturbance_box).tolist())
    n_extra = sum(s.size1() for s in states[1:])
    return System(f"{system.name}_augmented", ca.vertcat(*states), u, ca.vertcat(xdot, ca.SX.zeros(n_extra, 1)), y,
                  np.vstack(boxes), description=f"{system.name} with its parameters as states",
                  angle_states=system.angle_states, angle_outputs=system.angle_outputs, u_box=system.u_box)


def forced_rows(system: System) -> list[int]:
    """The rows of ``xdot`` the input enters (``df/du`` not structurally zero): the velocities of a mechanical plant."""
    jac = ca.jacobian(system.xdot_param_expr, system.u_sym)
    return [i for i in range(system.nx) if jac[i, :].nnz() > 0]


def perturbed(system: System, *, damping: float = 0.0, input_gain: float = 1.0) -> System:
    """A plant outside ``system``'s family: unmodelled damping and an input gain error.

    ``xdot_i = f_i(x, input_gain u, p) - damping x_i`` on the rows the input enters
    (:func:`forced_rows`), the others unchanged. The result keeps ``system``'s parameters (at their
    nominal values unless the simulation gives others), so that ``simulate(..., params=)`` combines both.

    Parameters
    ----------
    damping : float
        >= 0, on the forced rows.
    input_gain : float
        The factor the actuator really applies (1: none).
    """
    damping = nonnegative_number(damping, "damping")
    input_gain = finite_number(input_gain, "input_gain")
    x, u = system.x_sym, system.u_sym
    xdot = ca.substitute(system.xdot_param_expr, u, input_gain * u)
    rows = forced_rows(system)
    if damping and not rows:
        raise error("damping", "0 for a plant whose field the input does not enter", damping)
    for i in rows:
        xdot[i] = xdot[i] - damping * x[i]
    options: dict[str, Any] = {}
    if system.n_params:
        options = {"params": system.p_sym, "param_box": system.param_box, "param_nominal": system.param_nominal}
    return System(system.name, x, u, xdot, system.y_param_expr, system.x0_box, description=system.description,
                  paper_design=system.paper_design, angle_states=system.angle_states,
                  angle_outputs=system.angle_outputs, u_box=system.u_box, **options)
