"""Data-generation speed: one mapped CasADi call vs a Python loop over trials, per integrator."""

from __future__ import annotations

import numpy as np

from ...plant import signals as sig
from ...plant import systems
from ...plant.simulate import simulate, simulate_batch
from . import Timing, time_call

__all__ = ["bench_simulation"]


def bench_simulation(system: str = "duffing", n_trials: int = 32, T: float = 50.0, dt: float = 0.05,
                     repeat: int = 1) -> list[Timing]:
    """Trajectories per second: one mapped CasADi call vs a Python loop over trials, per integrator."""
    plant = systems.get(system)
    x0 = plant.sample_box(n_trials, 0)
    rng = np.random.default_rng(0)
    inputs = [sig.sample("square", rng) for _ in range(n_trials)]
    out = []
    for method in ("cvodes", "rk"):
        mapped = time_call(f"{system} {method}: mapped batch of {n_trials}",
                           lambda method=method: simulate_batch(plant, x0, inputs, T, dt, seed=0, method=method),
                           n_trials, repeat)
        looped = time_call(f"{system} {method}: Python loop over {n_trials}",
                           lambda method=method: [simulate(plant, x0[i], inputs[i], T, dt, seed=i, method=method)
                                    for i in range(n_trials)], n_trials, repeat)
        out += [mapped, looped]
        print(mapped)
        print(looped)
        print(f"{'':<44s} mapped / loop speed-up: {looped.seconds / mapped.seconds:.2f}x")
    return out
