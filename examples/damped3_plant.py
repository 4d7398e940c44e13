"""A damped 3-state plant that is not input-affine and has a nonlinear output (issue 17's second case).

``x1' = x2``, ``x2' = -x1 - x1^3 - 0.5 x2 + x3``, ``x3' = -x3 + 2 tanh(u) - 0.5 x2 x3``,
``y = x1 + 0.3 x1 x3``, box ``[-1, 1]^3``. The input enters through ``tanh`` (not affinely), the
output mixes ``x1`` and ``x3``, and every state is damped. Use it as
``kklcasadi train --plant examples/damped3_plant.py:make_plant --method bank --out DIR``.
"""

from __future__ import annotations

import casadi as ca

import kklcasadi as kc


def make_plant() -> kc.System:
    """The plant, ``x = (x1, x2, x3)``, ``u`` scalar, ``y = x1 + 0.3 x1 x3``."""
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 1)
    xdot = ca.vertcat(x[1], -x[0] - x[0] ** 3 - 0.5 * x[1] + x[2], -x[2] + 2.0 * ca.tanh(u) - 0.5 * x[1] * x[2])
    return kc.System("damped3", x, u, xdot, x[0] + 0.3 * x[0] * x[2], [[-1.0, 1.0]] * 3,
                     description="damped 3-state plant, tanh input, y = x1 + 0.3 x1 x3")
