"""A plant kklcasadi does not ship, for ``kklcasadi tune`` (README, "Design searches"): two masses on
springs, the first with a stiffening (Duffing) spring and the input, coupled by a spring to the second,
whose position alone is measured (not where the input acts)::

    q1' = p1,  p1' = -q1 - q1^3 - 0.2 p1 + 0.5 (q2 - q1) + u
    q2' = p2,  p2' = -2 q2 - 0.2 p2 + 0.5 (q1 - q2)
    y = q2,    x = (q1, q2, p1, p2) in [-1, 1]^4

Use it as ``--plant examples/two_masses.py:make_plant``.
"""

from __future__ import annotations

import casadi as ca

import kklcasadi as kc


def make_plant() -> kc.System:
    """The two-mass plant above."""
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u")
    q1, q2, p1, p2 = x[0], x[1], x[2], x[3]
    xdot = [p1, p2, -q1 - q1 ** 3 - 0.2 * p1 + 0.5 * (q2 - q1) + u, -2 * q2 - 0.2 * p2 + 0.5 * (q1 - q2)]
    return kc.System("two_masses", x, u, xdot, q2, [[-1.0, 1.0]] * 4,
                     description="two coupled masses, a Duffing spring and the input on the first, y = q2")


if __name__ == "__main__":
    plant = make_plant()
    print(plant, plant.fingerprint)
