"""Package the final ``bank`` decoders fitted by ``probe.py`` as shipped model directories.

``benchmarks/accuracy/train_final.sh`` fits the four final decoders with ``probe.py --recipe --seed 11
--save WEIGHTS`` (the recipe is :class:`kklcasadi.train.bank.BankConfig`'s defaults; the script
checks that, and that the latent matrices are the recipe's filter bank). This script writes each one
as ``models/<system>/bank`` with the card ``kklcasadi train --method bank --seed 11`` writes: the
filter-bank spec, the noise level and input ranges of the fit, and the domain (states and latents
of the operational runs, regenerated from the same seed). The weights are copied unchanged.

Usage: ``python benchmarks/accuracy/ship_bank.py WEIGHTS [SYSTEM ...] [--out models] [--overwrite]``
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from kklcasadi.model.files import make_card, save_model
from kklcasadi.model.variants import filterbank as fb
from kklcasadi.plant import systems
from kklcasadi.train.bank import BankConfig, bank_model, design_bank
from kklcasadi.train.operational import config_record, rollouts

SEED = 11
DT = 0.05


def ship(system: str, weights: Path, out: Path, overwrite: bool) -> Path:
    record = json.loads((weights / f"{system}_bank.json").read_text())
    with np.load(weights / f"{system}_bank.npz", allow_pickle=False) as npz:
        fitted = {name: np.array(npz[name], dtype=float) for name in npz.files}
    plant = systems.get(system)
    config = BankConfig.for_system(system)
    if json.loads(json.dumps(config_record(config.rollouts, config.decoder))) != record["config"]:
        raise SystemExit(f"{system}: the fit's configuration is not BankConfig.for_system({system!r})")
    bank = design_bank(plant, config)
    for name, value in fb.bank_arrays(bank).items():
        if not np.array_equal(fitted[name], value):
            raise SystemExit(f"{system}: {name} is not the recipe's filter bank")
    runs = rollouts(plant, replace(config.rollouts, dt=DT), SEED)
    arrays, spec, domain = bank_model(plant, bank, config, fitted, record["arch"], runs, DT)
    history = record["history"]
    best = int(np.argmin(history["val"]))
    training = {**record["config"], "decoder_fit": {"epochs": len(history["val"]), "best_epoch": best,
                                                    "best_val": history["val"][best],
                                                    "wall_time_s": round(record["fit_seconds"], 1)},
                "samples": record["n_samples"], "state_percentiles": record["domain"], "seed": SEED,
                "device": "cpu", "made_by": "benchmarks/accuracy/probe.py --recipe --seed 11 (train_final.sh), "
                "packaged by benchmarks/accuracy/ship_bank.py"}
    card = make_card(plant, SimpleNamespace(A=bank.A, B=bank.By), "bank", spec, dt=DT, window=1, training=training,
                     measurement_std=config.rollouts.measurement_std, domain=domain)
    path = save_model(out / system / "bank", arrays, card, overwrite=overwrite)
    (path / "history.json").write_text(json.dumps({"decoder": history}))
    return path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("weights", type=Path, help="the --save directory of probe.py")
    p.add_argument("systems", nargs="*", default=["duffing", "vdp", "fhn", "rossler"])
    p.add_argument("--out", type=Path, default=Path("models"))
    p.add_argument("--overwrite", action="store_true")
    args = p.parse_args()
    for system in args.systems:
        print(f"{system}: wrote {ship(system, args.weights, args.out, args.overwrite)}", flush=True)


if __name__ == "__main__":
    main()
