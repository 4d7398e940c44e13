"""Training hook of the ``bank`` variant: design the filter bank, simulate noisy operational runs,
fit the decoder on them (:mod:`kklcasadi.train.operational`), write the model."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace
from typing import Optional

import numpy as np

from ..model.files import Domain, Model
from ..model.monitor import FeatureMonitor, calibrate_runs
from ..model.variants import BankSpec
from ..model.variants import filterbank as fb
from ..nets.specs import DECODER, MLPSpec
from ..plant import signals as sig
from ..plant.design import Design
from ..plant.simulate import TrajectoryBatch
from ..plant.systems import System
from .config import LoopConfig
from .operational import DecoderConfig, RolloutConfig, config_record, fit_bank_decoder, rollouts
from .result import Trained

__all__ = ["BankConfig", "train_bank", "design_bank", "bank_model", "bank_monitor", "ASINH"]

#: Per-system output transforms: Roessler's x3 sits near 0.007 and spikes to 20-37, so its decoder
#: predicts ``asinh(x3 / 0.01)`` (per-state SMAPE weighs relative errors).
ASINH = {"rossler": (0.0, 0.0, 0.01)}


@dataclass(frozen=True)
class BankConfig:
    """The ``bank`` observer: the filter bank's design, the operational runs and the decoder fit.

    Attributes
    ----------
    y_poles, u_poles : tuple of float
        Speeds (rad/s) of the first-order filters of each output and input channel.
    y_resonators : tuple of (zeta, omega)
        Second-order filters of each output channel.
    clock : float or None
        Rate of the clock latent (None: none).
    rollouts : RolloutConfig
        The noisy training runs (noise level, input ranges, horizon; ``dt`` is the model's).
    decoder : DecoderConfig
        Architecture, loss and optimisation of the decoder.
    """

    y_poles: tuple = (0.2, 0.4, 0.8, 1.5, 3.0, 6.0, 12.0, 25.0)
    u_poles: tuple = (0.3, 1.0, 3.0)
    y_resonators: tuple = ()
    clock: Optional[float] = 0.2
    rollouts: RolloutConfig = field(default_factory=RolloutConfig)
    decoder: DecoderConfig = field(default_factory=lambda: DecoderConfig(
        loop=LoopConfig(epochs=40, batch_size=1024, lr=1e-3, schedule="cosine", val_fraction=0.05)))

    @classmethod
    def for_system(cls, system: str) -> BankConfig:
        """The defaults for the plant named ``system`` (:data:`ASINH` output transforms)."""
        config = cls()
        if system in ASINH:
            config = replace(config, decoder=replace(config.decoder, asinh_scale=ASINH[system]))
        return config


def design_bank(system: System, config: BankConfig) -> fb.FilterBank:
    """The filter bank of ``config`` for ``system``'s outputs and inputs."""
    return fb.FilterBank.design(system.ny, system.nu, config.y_poles, config.u_poles,
                                y_resonators=config.y_resonators, clock=config.clock)


def bank_model(system: System, bank: fb.FilterBank, config: BankConfig, decoder_arrays: dict,
               decoder_arch: dict, runs: TrajectoryBatch, dt: float) -> tuple[dict, BankSpec, Domain]:
    """The model file's arrays, spec and domain of a decoder fitted on ``runs`` through ``bank``.

    ``decoder_arrays`` and ``decoder_arch`` are a fit's ``arrays`` (any ``bank/*`` entries are
    replaced by the bank's own) and ``arch``; the domain is the runs' states and latents.
    """
    arrays = {name: value for name, value in decoder_arrays.items() if not name.startswith("bank/")}
    arrays.update({"bank/Bu": np.array(bank.Bu), "bank/c": np.array(bank.c)})
    params = {"y_poles": list(config.y_poles), "u_poles": list(config.u_poles),
              "y_resonators": [list(r) for r in config.y_resonators], "clock": config.clock}
    spec = BankSpec(MLPSpec.from_card(decoder_arch, "architecture", DECODER), bank.A, bank.By, dt, system.nu, params)
    z = bank.run(runs.y, runs.u, dt)
    return arrays, spec, Domain.of(runs.x.reshape(-1, system.nx), z.reshape(-1, bank.nz))


def bank_monitor(bank: fb.FilterBank, runs: TrajectoryBatch, dt: float, seed: int, *,
                 source: str = "the decoder's fitting runs") -> FeatureMonitor:
    """The decoder-input domain monitor calibrated on the fitting runs (:func:`kklcasadi.model.monitor.calibrate_runs`).

    The features are the decoder's input ``[z_k; y_k; u_k]`` along each run from ``z_0 = 0``;
    ``source`` is recorded in the card's ``monitor.calibration``.
    """
    z = bank.run(runs.y, runs.u, dt)
    return calibrate_runs(fb.decoder_features(z, runs.y, runs.u), runs.t, seed=seed, calibration={"source": source})


def train_bank(system: System, design: Design, base: Model | None, config: BankConfig, *, dt: float, seed: int,
               device: str, progress: bool, workdir: Path | None, resume: bool) -> Trained:
    """The training hook of ``bank`` (no base model; ``design`` is replaced by the bank's)."""
    if type(config) is not BankConfig:
        raise TypeError(f"config: expected a BankConfig for 'bank', received {type(config).__name__}.")
    bank = design_bank(system, config)
    runs = rollouts(system, replace(config.rollouts, dt=dt), seed)
    fit = fit_bank_decoder(bank, runs, config.decoder, seed=seed, progress=progress)
    arrays, spec, domain = bank_model(system, bank, config, fit.arrays, fit.arch, runs, dt)
    training = {"config": config, **config_record(config.rollouts, config.decoder), "decoder_fit": fit.fit.summary(),
                "samples": fit.n_samples, "state_percentiles": fit.domain}
    # the domain monitor and the input families of the fitting runs (read by kklcasadi.evaluation.generalisation)
    monitor = bank_monitor(bank, runs, dt, seed)
    arrays.update(monitor.arrays())
    families = {kind: sig.family_ranges(kind, config.rollouts.regime) for kind in config.rollouts.kinds}
    return Trained(arrays, spec, SimpleNamespace(A=bank.A, B=bank.By), training, {"decoder": fit.fit.history}, 1,
                   config.rollouts.measurement_std, domain, monitor.spec, families)
