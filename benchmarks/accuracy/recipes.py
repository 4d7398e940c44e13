"""The final ``bank`` recipe per system (flags of ``probe.py``) and the paper's anchor."""

from __future__ import annotations

#: The paper's best noise-free SMAPE per cell (docs/protocol.md Table I), zero/constant/sinusoid/square.
PAPER_BEST = {"duffing": [5.6, 21.1, 22.7, 21.3], "vdp": [5.0, 26.0, 15.5, 17.9],
              "rossler": [52.7, 55.4, 53.5, 54.0], "fhn": [9.8, 42.1, 30.9, 32.5]}

#: Filter bank shared by every system: 8 output filters 0.2-25 rad/s, 3 input filters, a clock.
GENERAL = {"y_poles": "0.2,0.4,0.8,1.5,3,6,12,25", "u_poles": "0.3,1,3", "clock": 0.2}

RECIPES = {
    "duffing": {**GENERAL, "n_traj": 2000, "epochs": 40},
    "vdp": {**GENERAL, "n_traj": 2000, "epochs": 40},
    "fhn": {**GENERAL, "n_traj": 2000, "epochs": 40},
    "rossler": {**GENERAL, "n_traj": 2000, "epochs": 40, "asinh": "0,0,0.01"},
}
