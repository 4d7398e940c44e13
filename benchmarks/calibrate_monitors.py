"""One-off: add the decoder-input domain monitor and ``fit_families`` to the shipped ``bank`` models.

    OMP_NUM_THREADS=1 python benchmarks/calibrate_monitors.py [--systems duffing vdp rossler fhn]

For each ``models/<system>/bank``: re-simulate the decoder's fitting runs from the card's training
record (``training.rollouts`` and ``training.seed``: :func:`kklcasadi.train.operational.rollouts`,
the function that made them), check that they are those runs (the card's ``domain`` is their
componentwise state and latent range, bit for bit), calibrate the monitor on them with the
training hook's own function (:func:`kklcasadi.train.bank.bank_monitor`), and save the model
again with the monitor's arrays and card entry and the input families of the fit. The decoder's
weights are unchanged (the archive gains the ``monitor/*`` arrays, so its SHA-256 changes).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import kklcasadi as kc
from kklcasadi.model.files import Domain, load_model, save_model
from kklcasadi.model.variants.filterbank import FilterBank
from kklcasadi.plant import signals as sig
from kklcasadi.train.bank import bank_monitor
from kklcasadi.train.operational import RolloutConfig, rollouts

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--systems", nargs="+", default=["duffing", "vdp", "rossler", "fhn"])
    args = parser.parse_args()
    for name in args.systems:
        directory = ROOT / "models" / name / "bank"
        model = load_model(directory)
        record, seed = model.card["training"]["rollouts"], model.card["training"]["seed"]
        plant = kc.systems.get(name)
        t0 = time.perf_counter()
        runs = rollouts(plant, RolloutConfig(**{**record, "kinds": tuple(record["kinds"])}), seed)
        bank = FilterBank(model.spec.A, model.spec.B, np.asarray(model.arrays["bank/Bu"]),
                          np.asarray(model.arrays["bank/c"]))
        z = bank.run(runs.y, runs.u, model.dt)
        domain = Domain.of(runs.x.reshape(-1, plant.nx), z.reshape(-1, bank.nz)).to_card()
        if domain != model.card["domain"]:
            raise SystemExit(f"{directory}: the re-simulated runs are not the fitting runs (their domain differs)")
        monitor = bank_monitor(bank, runs, model.dt, seed,
                               source="the decoder's fitting runs, re-simulated by benchmarks/calibrate_monitors.py")
        card = {key: value for key, value in model.card.items() if key not in ("monitor", "fit_families")}
        card["monitor"] = monitor.spec.to_card()
        card["fit_families"] = {kind: {p: list(b) for p, b in sig.family_ranges(kind, record["regime"]).items()}
                                for kind in record["kinds"]}
        arrays = {k: v for k, v in model.arrays.items() if not k.startswith("monitor/")}
        save_model(directory, {**arrays, **monitor.arrays()}, card, overwrite=True)
        print(f"{name}: {len(runs)} runs re-simulated and checked, monitor threshold {monitor.spec.threshold:.4g} "
              f"({monitor.spec.prototypes} prototypes), {time.perf_counter() - t0:.0f} s; "
              f"{json.dumps(card['fit_families'])}")


if __name__ == "__main__":
    main()
