"""Add the decoder-input domain monitor and ``fit_families`` to ``bank`` models trained without them.

    OMP_NUM_THREADS=1 python benchmarks/calibrate_monitors.py MODEL_DIR [MODEL_DIR ...]

For each model directory: re-simulate the decoder's fitting samples from the card's training record
(``training.config`` and ``training.seed``, through :func:`kklcasadi.train.operational.operational_data`,
the function that made them), check that they are those samples (the card's ``domain`` is their
componentwise state and latent range, bit for bit), calibrate the monitor on them with the training
hook's own function (:func:`kklcasadi.train.bank.bank_monitor`), and save the model again with the
monitor's arrays and card entry and the input families of the fit. The decoder's weights are
unchanged (the archive gains the ``monitor/*`` arrays, so its SHA-256 changes). A model trained
now gets both from ``kklcasadi train`` itself.
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
from kklcasadi.train.bank import bank_monitor
from kklcasadi.train.operational import RolloutConfig, fit_families, operational_data


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", type=Path, help="bank model directories of a shipped system")
    args = parser.parse_args()
    for directory in args.models:
        model = load_model(directory)
        training = model.card["training"]
        config, seed = training["config"], training["seed"]
        record = config["rollouts"]
        box = record["box_scale"]
        rollouts = RolloutConfig(**{**record, "kinds": tuple(record["kinds"]),
                                    "noise_range": tuple(record["noise_range"]),
                                    "box_scale": box if np.isscalar(box) else tuple(box)})
        plant = kc.systems.get(model.card["system"]["name"])
        rate = float(training["time_scale"])
        t0 = time.perf_counter()
        bank = FilterBank(model.spec.A, model.spec.B, np.asarray(model.arrays["bank/Bu"]),
                          np.asarray(model.arrays["bank/c"]))
        data = operational_data(plant, bank, rollouts, seed, dt=model.dt, measurement_std=training["measurement_std"],
                                process_std=np.asarray(training["process_std"], dtype=float), time_scale=rate)
        if Domain.of(data.x, data.z).to_card() != model.card["domain"]:
            raise SystemExit(f"{directory}: the re-simulated samples are not the fitting ones (their domain differs)")
        monitor = bank_monitor(data, seed,
                               source="the decoder's fitting runs, re-simulated by benchmarks/calibrate_monitors.py")
        card = {key: value for key, value in model.card.items() if key not in ("monitor", "fit_families")}
        card["monitor"] = monitor.spec.to_card()
        card["fit_families"] = {kind: {p: list(b) for p, b in ranges.items()}
                                for kind, ranges in fit_families(rollouts, rate).items()}
        arrays = {k: v for k, v in model.arrays.items() if not k.startswith("monitor/")}
        save_model(directory, {**arrays, **monitor.arrays()}, card, overwrite=True)
        print(f"{directory}: {data.record['runs']} runs re-simulated and checked, monitor threshold "
              f"{monitor.spec.threshold:.4g} ({monitor.spec.prototypes} prototypes), {time.perf_counter() - t0:.0f} s; "
              f"{json.dumps(card['fit_families'])}")


if __name__ == "__main__":
    main()
