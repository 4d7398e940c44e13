"""One compiled ipopt solve, checked: the options every ``Opti`` problem of the estimators and the controller
uses, the call of a Function made by ``Opti.to_function`` and the record of its outcome (ipopt's status,
iterations, wall time; a solve counts only where ipopt succeeded and the solution is finite). The MHE
(:mod:`kklcasadi.estimators.mhe`) and the NMPC (:mod:`kklcasadi.estimators.nmpc`) share it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Sequence

import casadi as ca
import numpy as np

from ..validation import positive_int

__all__ = ["SolveRecord", "solve_compiled", "ipopt_options"]

#: ipopt return statuses that count as a solved problem.
_SOLVED = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


def ipopt_options(max_iter: int = 50, **extra: Any) -> dict:
    """Options of ``Opti.solver("ipopt", ...)``: silent, exact Hessian, expanded to SX.

    Parameters
    ----------
    max_iter : int
        Iteration limit per solve.
    **extra
        More ipopt options (e.g. ``tol``, ``mu_init``), passed under ``"ipopt"``.

    Returns
    -------
    dict
        ``{"plugin": {...}, "ipopt": {...}}``: the two option dictionaries of ``Opti.solver``.
    """
    positive_int(max_iter, "max_iter")
    ipopt = {"print_level": 0, "sb": "yes", "max_iter": int(max_iter),
             "hessian_approximation": "exact", **extra}
    plugin = {"expand": True, "print_time": False, "error_on_fail": False}
    return {"plugin": plugin, "ipopt": ipopt}


@dataclass(frozen=True)
class SolveRecord:
    """The outcome of one compiled ``Opti`` solve.

    Attributes
    ----------
    success : bool
        ipopt's ``success`` and a finite solution.
    status : str
        ipopt's ``return_status`` (``"NonFinite_Solution"`` when ipopt succeeded but the solution
        holds a NaN/inf).
    iterations : int
    seconds : float
        Wall time of the call.
    """

    success: bool
    status: str
    iterations: int
    seconds: float


def solve_compiled(function: ca.Function, args: Sequence[Any]) -> tuple[list[np.ndarray], SolveRecord]:
    """Call a Function made by ``Opti.to_function`` and read ipopt's statistics of the call.

    Parameters
    ----------
    function : casadi.Function
        From ``opti.to_function(...)`` (its ``stats()`` are those of the embedded ipopt call).
    args : sequence
        Its inputs, in order.

    Returns
    -------
    outputs : list of numpy.ndarray
        The Function's outputs (dense).
    record : SolveRecord
    """
    start = time.perf_counter()
    outputs = function.call(list(args))
    seconds = time.perf_counter() - start
    stats = function.stats()
    arrays = [np.asarray(ca.DM(out)) for out in outputs]
    status = str(stats.get("return_status", "unknown"))
    success = bool(stats.get("success", False)) and status in _SOLVED
    if success and not all(np.all(np.isfinite(a)) for a in arrays):
        success, status = False, "NonFinite_Solution"
    return arrays, SolveRecord(success, status, int(stats.get("iter_count", -1)), seconds)
