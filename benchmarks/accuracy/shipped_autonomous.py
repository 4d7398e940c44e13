"""Score the shipped ``autonomous`` observers on the cached 100-trial protocol cells (numpy, exact FOH).

Their latent is linear (``zdot = A z + B y``), so the exact FOH recursion of
:class:`kklcasadi.model.variants.filterbank.FilterBank` (with no input or constant drive) and the decoder in numpy
reproduce ``KKLObserver.simulate`` (checked on one trial against the CasADi observer).
Writes ``results/accuracy/shipped_autonomous.json``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from common import protocol_trials, score, table_row

import kklcasadi as kc
from kklcasadi.model.files import load_model
from kklcasadi.model.variants import filterbank as fb
from kklcasadi.nets.numpy_mlp import mlp_numpy
from kklcasadi.nets.specs import DECODER, MLPSpec


def estimator(system: str):
    model = load_model(f"models/{system}/autonomous")
    bank = fb.FilterBank(model.A, model.B, np.zeros((model.A.shape[0], 1)), np.zeros(model.A.shape[0]))
    spec = MLPSpec.from_card(model.card["architecture"][DECODER])

    def est(y: np.ndarray, u: np.ndarray) -> np.ndarray:
        return mlp_numpy(spec, model.arrays, DECODER, bank.run(y, u, model.dt))

    return est


def main() -> None:
    out = {}
    for system in ("duffing", "vdp", "fhn", "rossler"):
        est = estimator(system)
        cell = protocol_trials(system, "noisy")["square"]
        obs = kc.load_observer(f"models/{system}/autonomous")
        ref = obs.simulate(cell["t"], cell["y"][0], cell["u"][0]).xhat
        gap = float(np.max(np.abs(ref - est(cell["y"][:1], cell["u"][:1])[0])))
        out[system] = {"noisy": score(system, "noisy", est), "clean": score(system, "clean", est), "check": gap}
        print(f"{system} (numpy vs CasADi observer: {gap:.1e})\n  noisy {table_row(out[system]['noisy'])}\n"
              f"  clean {table_row(out[system]['clean'], 'ours')}")
    Path("results/accuracy/shipped_autonomous.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
