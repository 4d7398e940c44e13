"""Add the decoder-input domain monitor and ``fit_families`` to ``bank`` models trained without them.

    OMP_NUM_THREADS=1 python benchmarks/calibrate_monitors.py MODEL_DIR [MODEL_DIR ...]

For each model directory: re-simulate the decoder's fitting samples from the card's training record
(``training.config`` and ``training.seed``, through :func:`kklcasadi.model.operational.operational_data`,
the function that made them), check that they are those samples (the card's ``domain`` is their
componentwise state and latent range, bit for bit), calibrate the monitor on them with the training
hook's own function (:func:`kklcasadi.model.operational.bank_monitor`; with the members' spread test for
a decoder ensemble, its threshold from runs of the card's recipe at its nominal noise,
:func:`kklcasadi.model.operational.nominal_runs`, as training sets it), and save the model again with the
monitor's arrays and card entry and the input families of the fit. The decoder's weights are
unchanged (the archive gains the ``monitor/*`` arrays, so its SHA-256 changes). A model trained now
gets both from ``kklcasadi train`` itself.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import kklcasadi as kc
from kklcasadi.model.card import Domain, parse_card
from kklcasadi.model.files import Model, load_model, save_model
from kklcasadi.model.operational import (
    MonitorConfig,
    OperationalData,
    bank_monitor,
    member_spread,
    nominal_runs,
    operational_data,
)
from kklcasadi.model.variants import filterbank as fb
from kklcasadi.model.variants.filterbank import FilterBank
from kklcasadi.plant.runs import RolloutConfig, fit_families


def rollouts_of(model: Model) -> RolloutConfig:
    """The operational runs' configuration recorded in a bank model's card (``training.config.rollouts``, or
    the older record ``training.rollouts`` of a fixed noise level)."""
    training = model.card["training"]
    if "config" not in training:
        r = training["rollouts"]
        return RolloutConfig(n_traj=r["n_traj"], T=r["T"], kinds=tuple(r["kinds"]), regime=r["regime"],
                             noise_range=(1.0, 1.0), method=r["method"], substeps=r["substeps"],
                             box_scale=r["box_scale"])
    record = training["config"]["rollouts"]
    box = record["box_scale"]
    tuples = {name: tuple(record[name]) for name in ("kinds", "noise_range", "noise_models") if name in record}
    return RolloutConfig(**{**record, **tuples, "box_scale": box if np.isscalar(box) else tuple(box)})


def noise_of(model: Model) -> tuple[float, np.ndarray, float]:
    """Measurement std, process std per state and time scale of a bank model's runs (either card record)."""
    training = model.card["training"]
    if "config" not in training:
        r = training["rollouts"]
        return float(r["measurement_std"]), np.full(model.spec.system.nx, float(r["process_std"])), 1.0
    return (float(training["measurement_std"]), np.asarray(training["process_std"], dtype=float),
            float(training["time_scale"]))


def model_plant(model: Model) -> kc.System:
    """The shipped plant a model's card names."""
    return kc.systems.get(model.card["system"]["name"])


def resimulate(directory: Path, *, fresh: bool = False) -> tuple[Model, FilterBank, OperationalData]:
    """A bank model, its filter bank and its decoder's fitting samples, re-simulated and checked against the
    card's domain (SystemExit where they differ). ``fresh``: runs of the card's recipe as the current code
    simulates them, not checked (a card from before the current runs: its decoder's own runs cannot be
    remade)."""
    model = load_model(directory)
    plant = model_plant(model)
    spec = model.spec.architecture
    bank = fb.bank_from_arrays(spec.filter_arrays(model.arrays))
    measurement, process, rate = noise_of(model)
    data = operational_data(plant, bank, rollouts_of(model), model.card["training"]["seed"], dt=model.dt,
                            measurement_std=measurement, process_std=process, time_scale=rate,
                            copies=spec.model_copies(model.arrays, plant))
    if not fresh and Domain.of(data.x, data.z).to_card() != model.card["domain"]:
        raise SystemExit(f"{directory}: the re-simulated samples are not the fitting ones (their domain differs)")
    return model, bank, data


def calibration_source(script: str, fresh: bool) -> str:
    """The card's ``monitor.calibration.source`` of a monitor that ``script`` calibrated on re-simulated runs."""
    return (f"runs of the card's recipe simulated by {script} --fresh" if fresh
            else f"the decoder's fitting runs, re-simulated by {script}")


def recalibrate(directory: Path, model: Model, bank: FilterBank, data: OperationalData, arrays: dict, card: dict,
                source: str, *, monitor: MonitorConfig | None = None, overwrite: bool = False) -> dict:
    """Save ``arrays`` and ``card`` (a bank model of ``data``) to ``directory`` with the monitor calibrated on
    ``data`` as ``monitor`` says (:func:`kklcasadi.model.operational.bank_monitor`; the spread threshold of an ensemble
    from ``monitor.spread_runs`` runs at the card's nominal noise) and the card's ``fit_families``; returns the
    card written. A model already in ``directory`` is replaced (in one step) only with ``overwrite``."""
    monitor = MonitorConfig() if monitor is None else monitor
    spec = parse_card(card, str(directory), require_sha=False).architecture
    spread = member_spread(arrays, bank, spec)
    seed = model.card["training"]["seed"]
    spread_data, spread_source = None, ""
    if spread is not None and monitor.spread_runs:
        measurement, process, rate = noise_of(model)
        spread_data, spread_source = nominal_runs(model_plant(model), bank, rollouts_of(model), monitor.spread_runs,
                                                  seed, dt=model.dt, measurement_std=measurement, process_std=process,
                                                  time_scale=rate, copies=spec.model_copies(arrays, model_plant(model)))
    calibrated = bank_monitor(data, seed, source=source, spread=spread, spread_data=spread_data,
                              spread_source=spread_source, quantile=monitor.quantile,
                              spread_quantile=monitor.spread_quantile)
    card = {key: value for key, value in card.items() if key not in ("monitor", "fit_families")}
    card["monitor"] = calibrated.spec.to_card()
    card["fit_families"] = {kind: {p: list(b) for p, b in ranges.items()}
                            for kind, ranges in fit_families(rollouts_of(model), noise_of(model)[2]).items()}
    arrays = {k: v for k, v in arrays.items() if not k.startswith("monitor/")}
    save_model(directory, {**arrays, **calibrated.arrays()}, card, overwrite=overwrite)
    return card


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", type=Path, help="bank model directories of a shipped system")
    default = MonitorConfig()
    parser.add_argument("--quantile", type=float, default=default.quantile,
                        help=f"share of validation samples inside the prototype threshold (default {default.quantile})")
    parser.add_argument("--spread-quantile", type=float, default=default.spread_quantile,
                        help="share of the spread-calibration samples inside the ensemble's spread threshold "
                             f"(default {default.spread_quantile})")
    parser.add_argument("--spread-runs", type=int, default=default.spread_runs,
                        help="runs of the card's recipe at its nominal noise that set the spread threshold (0: the "
                             f"validation samples of the fitting runs; default {default.spread_runs})")
    parser.add_argument("--fresh", action="store_true",
                        help="calibrate on fresh runs of the card's recipe (a card that predates the current "
                             "simulator)")
    args = parser.parse_args()
    for directory in args.models:
        t0 = time.perf_counter()
        model, bank, data = resimulate(directory, fresh=args.fresh)
        source = calibration_source("benchmarks/calibrate_monitors.py", args.fresh)
        monitor = MonitorConfig(args.quantile, args.spread_quantile, args.spread_runs)
        card = recalibrate(directory, model, bank, data, dict(model.arrays), model.card, source, monitor=monitor,
                           overwrite=True)                      # the model it read, saved again in one step
        print(f"{directory}: {data.record['runs']} runs re-simulated and checked, monitor threshold "
              f"{card['monitor']['threshold']:.4g} ({card['monitor']['prototypes']} prototypes), "
              f"{time.perf_counter() - t0:.0f} s; {json.dumps(card['fit_families'])}")


if __name__ == "__main__":
    main()
