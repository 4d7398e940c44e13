"""Score ``bank`` models beside the EKF on input families and noise levels they may not have been fit on.

A stand-in for the generalisation benchmark of issue 18 (the official one is ``gen18``'s), on seeds
that no model was fit or chosen on: use ``--seed 3030`` to choose and ``--seed 4040`` to report.
Cells (noise std 0.1 on process and measurement unless named, T = 50 s, dt = 0.05 s, CVODES, x0
from the X0 box):

* ``id-<kind>``: the protocol's four regimes on these seeds (the in-distribution check);
* ``ood-<kind>``: docs/protocol.md's out-of-distribution ranges of the three forced families;
* ``chirp``: a swept sine, amplitude U[0.1, 1], from U[0.2, 1] to U[3, 6] rad/s over the 50 s;
* ``steps``: random steps, level U[-a, a] with a ~ U[0.5, 2], held U[0.5, 5] s;
* ``pd-loop``: a PD controller on the first output around a set point redrawn every 10 s (gains
  kp U[0.5, 3], kd U[0.1, 1] on a filtered difference, |u| <= 2), simulated in closed loop;
* ``noise-0.05``, ``noise-0.2``: the square regime at those noise levels (the EKF told the level;
  the EKF left at the benchmark's 0.1 is printed beside it).

The EKF is the toolbox's (``kc.EKF``, Q = (std dt)^2 I, R = std^2 at the cell's noise). Mean SMAPE %
over the trials, and each model's ratio to the EKF.

Usage::

    PYTHONPATH=. python benchmarks/accuracy/generalisation.py duffing models/duffing/bank /tmp/m2 --seed 3030

Writes ``results/accuracy/generalisation/<system>_<seed>_<tag>.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import kklcasadi as kc
from kklcasadi.evaluation.protocol import Protocol
from kklcasadi.model.files import load_model
from kklcasadi.model.variants import filterbank as fb
from kklcasadi.plant import signals as sig
from kklcasadi.plant.runs import _closed_loop
from kklcasadi.plant.simulate import simulate_batch, time_grid

CACHE = Path("/tmp/acc_gen")
OUT = Path("results/accuracy/generalisation")
CELLS = ("id-zero", "id-constant", "id-sinusoid", "id-square", "ood-constant", "ood-sinusoid", "ood-square",
         "chirp", "steps", "pd-loop", "noise-0.05", "noise-0.2")
T, DT = 50.0, 0.05


class PD:
    """``u = clip(kp (r - y) - kd ydot_f, -2, 2)`` on the first output, ``ydot_f`` a filtered difference."""

    def __init__(self, rng: np.random.Generator, y_lo: float, y_hi: float, nu: int) -> None:
        self.kp, self.kd = rng.uniform(0.5, 3.0), rng.uniform(0.1, 1.0)
        self.scale = max(0.5 * (y_hi - y_lo), 1e-9)
        self.levels = rng.uniform(y_lo, y_hi, size=int(T / 10.0) + 1)
        self.nu, self.prev, self.rate = nu, None, 0.0

    def __call__(self, t: float, y: np.ndarray) -> np.ndarray:
        if self.prev is not None:
            self.rate += 0.3 * ((y[0] - self.prev) / DT - self.rate)
        self.prev = y[0]
        r = self.levels[int(t // 10.0)]
        u = self.kp * (r - y[0]) / self.scale - self.kd * self.rate / self.scale
        return np.full(self.nu, np.clip(u, -2.0, 2.0))


def simulate(system: kc.System, cell: str, n: int, seed: int) -> dict[str, np.ndarray]:
    """The trials of ``cell`` and the EKF on them (cached on disk)."""
    path = CACHE / f"{system.name}_{cell}_{seed}_{n}_v2.npz"
    if path.exists():
        with np.load(path) as f:
            return {k: f[k] for k in f.files}
    std = float(cell.split("-")[1]) if cell.startswith("noise-") else 0.1
    if cell.startswith(("id-", "ood-")):
        regime, kind = cell.split("-")
        batch = Protocol(n_trials=n, seed=seed, regime=regime).trials(system, kind)
    else:
        rng = np.random.default_rng([seed, CELLS.index(cell)])
        x0 = system.sample_box(n, seed)
        seeds = np.random.SeedSequence([seed, CELLS.index(cell)]).spawn(n)
        if cell == "pd-loop":
            lo, hi = np.quantile(system.h_batch(system.sample_box(256, seed + 1))[:, 0], [0.05, 0.95])
            laws = [PD(rng, lo, hi, system.nu) for _ in range(n)]
            v = rng.normal(0.0, std, (n, int(round(T / DT)), system.ny))
            batch = _closed_loop(system, x0, laws, time_grid(T, DT), np.full(system.nx, std), seeds, v, "cvodes", 1)
        else:
            if cell == "chirp":
                inputs = [sig.make("chirp", amplitude=rng.uniform(0.1, 1.0, system.nu), omega0=rng.uniform(0.2, 1.0),
                                   omega1=rng.uniform(3.0, 6.0), duration=T, phase=rng.uniform(0, 2 * np.pi))
                          for _ in range(n)]
            elif cell == "steps":
                inputs = [sig.make("random", amplitude=rng.uniform(0.5, 2.0, system.nu), hold=rng.uniform(0.5, 5.0),
                                   seed=int(rng.integers(2 ** 31)), horizon=T) for _ in range(n)]
            else:
                inputs = Protocol(n_trials=n, seed=seed).signals(system, "square")
            batch = simulate_batch(system, x0, inputs, T, DT, process_std=std, measurement_std=std, seed=seeds)
    ok = np.asarray(batch.ok)
    x, y, u = (np.asarray(a)[ok] for a in (batch.x, batch.y, batch.u))
    ekf = kc.EKF(system, DT, Q=np.eye(system.nx) * (std * DT) ** 2, R=np.eye(system.ny) * std ** 2)
    arrays = {"x": x, "y": y, "u": u, "ekf": ekf.simulate(batch.t, y, u).xhat, "failed": np.array(int((~ok).sum()))}
    if std != 0.1:          # also the EKF left at the benchmark's level, as a user who does not know it would
        arrays["ekf_at_0.1"] = kc.EKF(system, DT).simulate(batch.t, y, u).xhat
    CACHE.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return arrays


def estimator(path: str):
    model = load_model(path)
    spec = model.spec.architecture
    arrays = spec.filter_arrays(model.arrays)
    arch = model.card["architecture"]["decoder"]
    copies = spec.model_copies(model.arrays, kc.systems.get(model.card["system"]["name"]))

    def est(y: np.ndarray, u: np.ndarray) -> np.ndarray:
        return fb.estimate(arrays, arch, y, u, model.dt, angles=spec.angles, copies=copies)

    return est


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("system")
    p.add_argument("models", nargs="+")
    p.add_argument("--seed", type=int, default=3030)
    p.add_argument("--trials", type=int, default=20)
    p.add_argument("--cells", default=",".join(CELLS))
    p.add_argument("--tag", default="run")
    args = p.parse_args()
    system = kc.systems.get(args.system)
    ests = {m: estimator(m) for m in args.models}
    record: dict = {"system": args.system, "seed": args.seed, "trials": args.trials, "cells": {}}
    print(f"{args.system}, seed {args.seed}, {args.trials} trials: mean SMAPE % (ratio to the EKF)")
    print(f"{'cell':14s}{'EKF':>8s}" + "".join(f"{Path(m).name[-18:]:>20s}" for m in args.models))
    for cell in args.cells.split(","):
        t0 = time.time()
        data = simulate(system, cell, args.trials, args.seed)
        ekf = float(np.mean(kc.metrics.smape(data["x"], data["ekf"])))
        row = {"ekf": ekf, "failed": int(data["failed"]), "models": {}}
        for m, est in ests.items():
            row["models"][m] = float(np.mean(kc.metrics.smape(data["x"], est(data["y"], data["u"]))))
        record["cells"][cell] = row
        note = ""
        if "ekf_at_0.1" in data:
            row["ekf_at_0.1"] = float(np.mean(kc.metrics.smape(data["x"], data["ekf_at_0.1"])))
            note = f", EKF told 0.1: {row['ekf_at_0.1']:.2f}"
        print(f"{cell:14s}{ekf:8.2f}" + "".join(f"{v:12.2f} ({v / ekf:4.2f}x)" for v in row["models"].values())
              + f"   [{time.time() - t0:.0f} s{', failed ' + str(row['failed']) if row['failed'] else ''}{note}]",
              flush=True)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{args.system}_{args.seed}_{args.tag}.json").write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
