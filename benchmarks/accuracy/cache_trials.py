"""Cache the docs/protocol.md benchmark trials (noise on and off, 100 per cell) and the EKF on them.

Writes ``<cache>/<system>_<noisy|clean>.npz`` with, per input regime ``k``: ``k/t`` (N,),
``k/x`` (M, N, nx), ``k/y`` (M, N, ny), ``k/u`` (M, N, nu), ``k/ok`` (M,) and ``k/ekf`` (M, N, nx),
the EKF estimate of :class:`kklcasadi.estimators.ekf.EKF` (the unchanged baseline) on the same trials.

Usage: ``python benchmarks/accuracy/cache_trials.py [--cache DIR] [--trials 100] [--regime ood] SYSTEM...``
"""

from __future__ import annotations

import argparse
import io
import time
from pathlib import Path

import numpy as np
from common import CACHE

import kklcasadi as kc
from kklcasadi.estimators.ekf import EKF
from kklcasadi.evaluation.protocol import Protocol
from kklcasadi.plant.signals import BENCHMARK_KINDS
from kklcasadi.writes import write_file


def cache_system(name: str, cache: Path, n_trials: int, regime: str = "id") -> None:
    """Simulate and store both noise settings of ``name`` (skips files that exist).

    ``regime="ood"`` stores the out-of-distribution cells as ``<system>_ood_<noisy|clean>.npz``.
    """
    system = kc.systems.get(name)
    base = Protocol(n_trials=n_trials, regime=regime)
    prefix = name if regime == "id" else f"{name}_{regime}"
    for label, protocol in (("noisy", base), ("clean", base.noise_free())):
        path = cache / f"{prefix}_{label}.npz"
        if path.exists():
            continue
        arrays = {}
        for kind in BENCHMARK_KINDS:
            t0 = time.time()
            batch = protocol.trials(system, kind)
            ekf = EKF(system, dt=protocol.dt).simulate(batch.t, batch.y, batch.u).xhat
            arrays.update({f"{kind}/t": batch.t, f"{kind}/x": batch.x, f"{kind}/y": batch.y, f"{kind}/u": batch.u,
                           f"{kind}/ok": batch.ok, f"{kind}/ekf": ekf})
            print(f"{name} {label} {kind}: {time.time() - t0:.0f} s, ok {batch.ok.sum()}/{len(batch)}, "
                  f"EKF SMAPE {np.mean(kc.metrics.smape(batch.x[batch.ok], ekf[batch.ok])):.2f}", flush=True)
        archive = io.BytesIO()
        np.savez(archive, **arrays)
        write_file(path, archive.getvalue(), overwrite=True, argument="cache")      # whole: never a truncated cache


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("systems", nargs="+")
    parser.add_argument("--cache", type=Path, default=CACHE, help=f"where the cells go (default {CACHE})")
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--regime", default="id", choices=("id", "ood"))
    args = parser.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    for name in args.systems:
        cache_system(name, args.cache, args.trials, args.regime)


if __name__ == "__main__":
    main()
