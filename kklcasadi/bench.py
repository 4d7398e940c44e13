"""Benchmarks (``kklcasadi bench``): speed measured against the alternative in the same run.

Nothing here asserts a speed; each function prints and returns its measurements.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import signals as sig
from . import systems
from .simulate import simulate, simulate_batch

__all__ = ["Timing", "time_call", "bench_simulation"]


@dataclass(frozen=True)
class Timing:
    """Best-of-``repeat`` wall time of one call, and the work it did (``items``)."""

    label: str
    seconds: float
    items: int

    @property
    def rate(self) -> float:
        return self.items / self.seconds

    def __str__(self) -> str:
        return f"{self.label:<44s} {self.seconds * 1e3:10.2f} ms  {self.rate:12.1f} /s"


def time_call(label: str, fn: Callable[[], object], items: int = 1, repeat: int = 3) -> Timing:
    """Time ``fn()`` ``repeat`` times and keep the fastest (after one warm-up call)."""
    fn()
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return Timing(label, best, items)


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
                           lambda: simulate_batch(plant, x0, inputs, T, dt, seed=0, method=method),
                           n_trials, repeat)
        looped = time_call(f"{system} {method}: Python loop over {n_trials}",
                           lambda: [simulate(plant, x0[i], inputs[i], T, dt, seed=i, method=method)
                                    for i in range(n_trials)], n_trials, repeat)
        out += [mapped, looped]
        print(mapped)
        print(looped)
        print(f"{'':<44s} mapped / loop speed-up: {looped.seconds / mapped.seconds:.2f}x")
    return out
