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


def bench_training(system: str = "duffing", *, device: str = "cpu") -> list[Timing]:
    """Training throughput (samples/s) of each stage with the default architectures, on a short run."""
    import tempfile
    from dataclasses import replace

    from .modelfile import load_model
    from .train import LoopConfig, Phase2DataConfig, default_config, train_observer

    loop = LoopConfig(epochs=1, batch_size=512, samples_per_epoch=4096, schedule="cosine")
    stages = []
    with tempfile.TemporaryDirectory() as tmp:
        base = f"{tmp}/autonomous"
        p1 = default_config(system, "autonomous", n_traj=40, n_pde=2000, encoder=replace(loop, batch_size=1024),
                            decoder=replace(loop, batch_size=1024))
        train_observer(system, "autonomous", base, config=p1, device=device, progress=False)
        training = load_model(base).card["training"]
        stages += [(f"phase 1 {k} (width {p1.width})", training[k]) for k in ("encoder", "decoder")]
        data = Phase2DataConfig(n_traj=4, n_signals=4, T=20.0)
        for method in ("obs", "dyn"):
            cfg = default_config(system, method, data=data, loop=loop)
            train_observer(system, method, f"{tmp}/{method}", config=cfg, base=base, device=device, progress=False)
            stages.append((f"phase 2 {method} (window {data.window})",
                           load_model(f"{tmp}/{method}").card["training"][method]))
    out = [Timing(label, summary["wall_time_s"], int(summary["samples_per_s"] * summary["wall_time_s"]))
           for label, summary in stages]
    for timing in out:
        print(f"{timing.label:<44s} {timing.rate:12.0f} samples/s ({device})")
    return out
