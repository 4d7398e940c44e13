"""The EMPS positioning axis as a kklcasadi plant: the benchmark's direct dynamic model (``data/README.md``).

State ``x = (q, q_dot)`` (load position, m; velocity, m/s), input ``u`` (the drive's control voltage, V),
output ``y = q`` (the motor encoder). The model of the benchmark (Janot, Gautier, Brunot, 2019):

    M q_ddot = g_tau u - Fv q_dot - Fc sign(q_dot) - offset

with the published least-squares (IDIM-LS) estimates ``M = 95.11 kg``, ``Fv = 203.5 N s/m``,
``Fc = 20.39 N``, ``offset = -3.165 N`` and the drive gain ``g_tau = 35.15 N/V``. ``sign`` is smoothed
to ``tanh(q_dot / 0.005)`` (an ODE needs a continuous right-hand side; 0.005 m/s is 4 % of the rig's
velocity range, the smoothing of the data's README).

The box is where the rig lives: the travel of the development run (0 to 0.2465 m) and its
velocities (+-0.137 m/s), rounded out. ``u_box`` is the drive's range the rig is run at: the development
run reaches 4.3 V, other runs of the rig more than 6 V (after averaging over 10 ms); the drive
saturates at 10 V. ``make_plant_free`` is the same plant without ``u_box`` (training then uses the
benchmark's input ranges, ``|u| <= 2``, and says so).

    kklcasadi train --plant examples/emps/emps_plant.py:make_plant --dt 0.01 --measurement-std 1e-6 --out DIR
"""

from __future__ import annotations

import casadi as ca

import kklcasadi as kc

#: The benchmark's published model (data/README.md): kg, N s/m, N, N, N/V.
PARAMETERS = {"M": 95.11, "Fv": 203.5, "Fc": 20.39, "offset": -3.165, "g_tau": 35.15}
#: The Coulomb friction's sign smoothed to tanh(q_dot / VELOCITY_SCALE), m/s.
VELOCITY_SCALE = 0.005
#: Where the rig lives: position (m) and velocity (m/s).
BOX = ((-0.01, 0.26), (-0.2, 0.2))
#: The drive voltage the rig is run at (V).
U_BOX = ((-7.0, 7.0),)
#: State names, in order.
STATES = ("q", "q_dot")


def emps_rhs(x: ca.SX, u: ca.SX) -> ca.SX:
    """``xdot = f(x, u)`` of the model above, shape (2, 1)."""
    p = PARAMETERS
    q_dot = x[1]
    force = p["g_tau"] * u - p["Fv"] * q_dot - p["Fc"] * ca.tanh(q_dot / VELOCITY_SCALE) - p["offset"]
    return ca.vertcat(q_dot, force / p["M"])


def _plant(u_box: object) -> kc.System:
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    return kc.System("emps", x, u, emps_rhs(x, u), x[0], BOX, u_box=u_box,
                     description="EMPS positioning axis (benchmark model), y = q")


def make_plant() -> kc.System:
    """The EMPS axis with the drive's range declared (``u_box``)."""
    return _plant(U_BOX)


def make_plant_free() -> kc.System:
    """The same plant without ``u_box``."""
    return _plant(None)
