"""Benchmarks (``kklcasadi bench``): speed measured against the alternative in the same run.

Nothing here asserts a speed; each function prints and returns its measurements.

* :func:`kklcasadi.evaluation.bench.simulation.bench_simulation` -- data generation, mapped vs looped;
* :func:`kklcasadi.evaluation.bench.observer_step.bench_observer_step` -- one observer step: generated C, a
  hand-written C limit, the CasADi VM and torch at its best;
* :func:`kklcasadi.evaluation.bench.training.bench_training` -- training throughput per stage;
* :func:`kklcasadi.evaluation.bench.protocol.bench_protocol` -- the full benchmark protocol of one system.

The benchmarks sit beside the deploy side, not in it: those that time torch import it inside their
functions, and nothing of the deploy side imports this package.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

__all__ = ["Timing", "time_call"]


@dataclass(frozen=True)
class Timing:
    """Best-of-``repeat`` wall time of one call, the work it did (``items``) and, where counted, the instructions
    per item (valgrind's callgrind)."""

    label: str
    seconds: float
    items: int
    instructions: Optional[float] = None

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
