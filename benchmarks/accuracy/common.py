"""Shared helpers of the accuracy drivers: cached protocol trials and rollouts, scoring, tables.

The protocol trials come from ``cache_trials.py`` (``<cache>/<system>_<noisy|clean>.npz``); the
operational rollouts (train ranges, seeds disjoint from the protocol's) are cached per
``(system, n_traj, seed)`` so that decoder experiments share them.
"""

from __future__ import annotations

import io
from typing import Callable

import numpy as np

import kklcasadi as kc
from kklcasadi.evaluation.trialcache import cache_root
from kklcasadi.plant.signals import BENCHMARK_KINDS
from kklcasadi.plant.simulate import TrajectoryBatch
from kklcasadi.writes import write_file

#: The accuracy study's cached trials and rollouts, under kklcasadi's cache (``$KKLCASADI_CACHE``).
CACHE = cache_root() / "accuracy"
#: RK4 substeps per sample for the rollouts (checked against CVODES: SMAPE difference < 0.1 %).
SUBSTEPS = {"fhn": 8}
Estimator = Callable[[np.ndarray, np.ndarray], np.ndarray]


def protocol_trials(system: str, label: str) -> dict[str, dict[str, np.ndarray]]:
    """``{kind: {"x", "y", "u", "ekf", "ok"}}`` of the cached protocol cell (label: noisy/clean)."""
    path = CACHE / f"{system}_{label}.npz"
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing: run benchmarks/accuracy/cache_trials.py {system}")
    with np.load(path) as f:
        return {k: {n: f[f"{k}/{n}"] for n in ("t", "x", "y", "u", "ekf", "ok")} for k in BENCHMARK_KINDS}


def cached_rollouts(system: str, n_traj: int, seed: int, **overrides: object) -> TrajectoryBatch:
    """Operational rollouts of :func:`kklcasadi.plant.runs.rollouts`, cached on disk."""
    from kklcasadi.plant.runs import RolloutConfig, rollouts

    tag = "_".join(f"{k}{v}" for k, v in sorted(overrides.items()))
    path = CACHE / f"roll_{system}_{n_traj}_{seed}{'_' + tag if tag else ''}.npz"
    if path.exists():
        with np.load(path) as f:
            return TrajectoryBatch(f["t"], f["x"], f["u"], f["y"], f["ok"])
    cfg = RolloutConfig(n_traj=n_traj, substeps=SUBSTEPS.get(system, 4), **overrides)
    batch = rollouts(kc.systems.get(system), cfg, seed)
    archive = io.BytesIO()
    np.savez(archive, t=batch.t, x=batch.x, u=batch.u, y=batch.y, ok=batch.ok)
    write_file(path, archive.getvalue(), overwrite=True, argument="cache")      # whole: never a truncated cache
    return batch


def kind_of_rollouts(n: int) -> np.ndarray:
    """Input kind of each rollout (round-robin over the benchmark kinds)."""
    return np.array([BENCHMARK_KINDS[i % len(BENCHMARK_KINDS)] for i in range(n)])


def score(system: str, label: str, estimator: Estimator) -> dict[str, dict[str, float]]:
    """Mean SMAPE of ``estimator`` and of the EKF per regime on the cached protocol trials."""
    out = {}
    for kind, cell in protocol_trials(system, label).items():
        ok = cell["ok"]
        xhat = estimator(cell["y"][ok], cell["u"][ok])
        ours = kc.metrics.smape(cell["x"][ok], xhat)
        ekf = kc.metrics.smape(cell["x"][ok], cell["ekf"][ok])
        out[kind] = {"ours": float(np.mean(ours)), "ekf": float(np.mean(ekf)),
                     "ours_per_state": np.mean(kc.metrics.smape(cell["x"][ok], xhat, per_state=True), axis=0).tolist(),
                     "ekf_per_state": np.mean(kc.metrics.smape(cell["x"][ok], cell["ekf"][ok], per_state=True),
                                              axis=0).tolist(),
                     "wins": int(np.sum(ours < ekf)), "n": int(ok.sum()),
                     "ours_trials": ours.tolist(), "ekf_trials": ekf.tolist()}
    return out


def table_row(scores: dict[str, dict[str, float]], key: str = "ours") -> str:
    """``zero | constant | sinusoid | square`` of one method, with ratios to the EKF for ``ours``."""
    cells = []
    for kind in BENCHMARK_KINDS:
        s = scores[kind]
        cells.append(f"{s[key]:.2f}" + (f" ({s['ours'] / s['ekf']:.2f}x)" if key == "ours" else ""))
    return " | ".join(cells)
