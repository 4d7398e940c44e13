"""The Quanser Qube Servo 2 rotary pendulum as a kklcasadi plant (model of ``data/README.md``).

State ``x = (theta, alpha, theta_dot, alpha_dot)`` (arm angle, pendulum angle, their velocities;
rad, rad/s), input ``Vm`` (motor voltage, V), ``alpha = 0`` upright and ``alpha = pi`` hanging.
Both angles are marked as angles (``angle_states``, ``angle_outputs``), so errors on them are
compared modulo ``2 pi``. The parameters are those identified on the hardware by the data's
authors (``data/README.md``; note their pendulum damping ``Dp`` is negative).

Use it from the command line or Python::

    kklcasadi train --plant examples/qube/qube_plant.py:make_plant ...
    kc.systems.load_plant("examples/qube/qube_plant.py:make_plant_alpha")
"""

from __future__ import annotations

import math

import casadi as ca

import kklcasadi as kc

#: The model's parameters (data/README.md).
PARAMETERS = {"mr": 0.095, "Lr": 0.085, "mp": 0.024, "Lp": 0.129, "Rm": 14.0, "km": 0.01, "Dr": 0.0005,
              "Dp": -3e-5, "g": 9.81}
#: The state box: the ranges of the six logged runs (data/README.md) with a margin; alpha about
#: hanging (pi), velocities covering their Savitzky-Golay references (14.4 and 28.6 rad/s at most).
BOX = ((-1.6, 1.6), (math.pi - 2.8, math.pi + 2.8), (-15.0, 15.0), (-30.0, 30.0))
#: State names, in order.
STATES = ("theta", "alpha", "theta_dot", "alpha_dot")


def qube_rhs(x: ca.SX, vm: ca.SX) -> ca.SX:
    """``xdot = f(x, Vm)``, the equations of data/README.md written as they are there.

    Parameters
    ----------
    x : casadi.SX, shape (4, 1)
    vm : casadi.SX, shape (1, 1)

    Returns
    -------
    casadi.SX, shape (4, 1)
    """
    p = PARAMETERS
    mr, Lr, mp, Lp = p["mr"], p["Lr"], p["mp"], p["Lp"]
    Rm, km, Dr, Dp, g = p["Rm"], p["km"], p["Dr"], p["Dp"], p["g"]
    Jr = mr * Lr ** 2 / 12
    Jp = mp * Lp ** 2 / 12
    alpha, theta_dot, alpha_dot = x[1], x[2], x[3]
    tau = -km * (vm - km * theta_dot) / Rm
    den = (4 * Lp ** 2 * Lr ** 2 * mp ** 2 * ca.cos(alpha) ** 2
           - (4 * Jp + Lp ** 2 * mp) * (4 * Jr + Lp ** 2 * mp * ca.sin(alpha) ** 2 + 4 * Lr ** 2 * mp))
    a = -8 * Dp * alpha_dot + Lp ** 2 * mp * theta_dot ** 2 * ca.sin(2 * alpha) + 4 * Lp * g * mp * ca.sin(alpha)
    b = (4 * Dr * theta_dot + Lp ** 2 * mp * alpha_dot * theta_dot * ca.sin(2 * alpha)
         + 2 * Lp * Lr * mp * alpha_dot ** 2 * ca.sin(alpha) - 4 * tau)
    theta_ddot = (-Lp * Lr * mp * a * ca.cos(alpha) + (4 * Jp + Lp ** 2 * mp) * b) / den
    alpha_ddot = (2 * Lp * Lr * mp * b * ca.cos(alpha)
                  - 0.5 * (4 * Jr + Lp ** 2 * mp * ca.sin(alpha) ** 2 + 4 * Lr ** 2 * mp) * a) / den
    return ca.vertcat(theta_dot, alpha_dot, theta_ddot, alpha_ddot)


def _plant(name: str, outputs: tuple[int, ...], description: str) -> kc.System:
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 1)
    return kc.System(name, x, u, qube_rhs(x, u), ca.vertcat(*[x[i] for i in outputs]), BOX,
                     description=description, angle_states=(0, 1), angle_outputs=tuple(range(len(outputs))))


def make_plant() -> kc.System:
    """The Qube measured by both encoders: ``y = (theta, alpha)``."""
    return _plant("qube", (0, 1), "Quanser Qube Servo 2 rotary pendulum, y = (theta, alpha)")


def make_plant_alpha() -> kc.System:
    """The Qube measured by the pendulum encoder only: ``y = alpha``."""
    return _plant("qube_alpha", (1,), "Quanser Qube Servo 2 rotary pendulum, y = alpha")
