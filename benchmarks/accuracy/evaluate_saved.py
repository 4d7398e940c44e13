"""Score the saved final bank observers on every cached protocol cell and check the CasADi step.

For each system with ``results/accuracy/weights/<system>_bank.{npz,json}``: the protocol's
in-distribution cells (noise on and off) and, where cached (``cache_trials.py --regime ood``),
the out-of-distribution ones; one trial is re-run through the CasADi ``observer_step`` and
compared with the numpy reference. Writes ``results/accuracy/<system>_bank_scores.json``
(per-trial SMAPE of the bank and the EKF) and prints the tables.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from common import CACHE, protocol_trials, score, table_row

from kklcasadi.model.variants import filterbank as fb

WEIGHTS = Path("results/accuracy/weights")


def main() -> None:
    for system in ("duffing", "vdp", "fhn", "rossler"):
        path = WEIGHTS / f"{system}_bank.npz"
        if not path.exists():
            continue
        arrays = dict(np.load(path))
        arch = json.loads((WEIGHTS / f"{system}_bank.json").read_text())["arch"]

        def est(y: np.ndarray, u: np.ndarray) -> np.ndarray:
            return fb.estimate(arrays, arch, y, u, 0.05)

        cell = protocol_trials(system, "noisy")["square"]
        step = fb.observer_step(arrays, arch, 0.05).mapaccum("traj", cell["t"].size - 1, 2)
        y, u = cell["y"][0], cell["u"][0]
        _, _, xc = step(np.zeros(arrays["bank/A"].shape[0]), u[0], y[:-1].T, y[1:].T, u[1:].T)
        gap = float(np.max(np.abs(np.asarray(xc).T - est(y[None], u[None])[0, 1:])))
        out = {"casadi_vs_numpy_max_abs": gap}
        print(f"{system}: CasADi step vs numpy estimate, max |difference| {gap:.1e}")
        for label in ("noisy", "clean", "ood_noisy", "ood_clean"):
            if not (CACHE / f"{system}_{label}.npz").exists():
                continue
            s = score(system, label, est)
            out[label] = s
            print(f"  {label:9s} bank {table_row(s)}\n  {label:9s} EKF  {table_row(s, 'ekf')}")
        (Path("results/accuracy") / f"{system}_bank_scores.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
