"""Choose the covariance inflation's spread test of a shipped ``bank`` with a decoder ensemble (issue 49): its card.

    python benchmarks/spread_test.py MODEL --out DIR [--seed 49] [--trials 50] [--noise 0.2]
        [--time-constants 2.5 5] [--gains 0.05 0.1 0.2 0.5 1] [--thresholds 1.5 2 3 4]

MODEL is a bank with a decoder ensemble, a covariance head and its inflation (``fhn/bank``). Inputs that drive the
plant where the head was not fit leave the residual at the noise while the errors grow (FitzHugh-Nagumo's ``x1`` on
the ``ood`` sine and square waves at noise 0.2: 2-sigma coverage 89 %); the members of the decoder ensemble disagree
there. The spread test (:class:`kklcasadi.model.variants.inflation.SpreadTest`) averages the squared spread; its
constants are chosen on VALIDATION trials of seed ``--seed`` (never the scored 2026), ``--trials`` per case:

* ``S``: the mean squared spread on the protocol's four ``id`` input regimes at its noise (the in-distribution cells
  of ``kklcasadi evaluate --noise on``), so that the statistic averages 1 there;
* the time constant, the gain and the threshold: of the candidates (``--time-constants`` x ``--gains`` x
  ``--thresholds``), those whose 2-sigma coverage on those in-distribution trials stays at most 96.5 % per state and
  regime (half a point below the in-distribution target's top, 97 %), then the one whose worst 2-sigma coverage over
  the states of the generalisation's ``ood`` cases at process and measurement noise ``--noise`` (``kklcasadi
  generalise``'s constant, sine and square waves beyond the protocol's ranges) is nearest 95.45 %; where none keeps
  the in-distribution coverage, the one that comes nearest.

Every candidate's coverage goes to ``training.covariance.spread_test`` with the command and commit. DIR gets the model
with ``architecture.inflation.spread`` (MODEL's history copied); the script checks that its estimates are MODEL's bit
for bit and stops otherwise.
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import shutil
import time
from pathlib import Path

import numpy as np

from kklcasadi import consistency as cs
from kklcasadi import provenance
from kklcasadi.evaluation.compiled import CompiledRecord
from kklcasadi.evaluation.generalisation import Case, Settings
from kklcasadi.evaluation.protocol import Protocol
from kklcasadi.evaluation.trialcache import TrialCache
from kklcasadi.model.files import load_model, save_model
from kklcasadi.model.shipped import resolve
from kklcasadi.model.variants.inflation import INFLATION, MODEL, SPREAD, SpreadTest, spread_factor
from kklcasadi.observer.kkl import load_observer
from kklcasadi.plant import signals as sig

#: The in-distribution target's top less half a point (2-sigma coverage, %).
IN_DISTRIBUTION_TOP = 96.5
#: The generalisation's families with an ``ood`` range (``zero`` has none).
OOD_FAMILIES = ("constant", "sinusoid", "square")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", help="a bank model directory or a shipped name (fhn/bank)")
    p.add_argument("--out", required=True, type=Path, help="new directory for the model with the test")
    p.add_argument("--seed", type=int, default=49, help="seed of the validation trials")
    p.add_argument("--trials", type=int, default=50, help="validation trials per case")
    p.add_argument("--noise", type=float, default=0.2, help="process and measurement noise std of the ood cases")
    p.add_argument("--time-constants", type=float, nargs="+", default=[2.5, 5.0])
    p.add_argument("--gains", type=float, nargs="+", default=[0.05, 0.1, 0.2, 0.5, 1.0])
    p.add_argument("--thresholds", type=float, nargs="+", default=[1.5, 2.0, 3.0, 4.0])
    args = p.parse_args()
    if args.seed == Protocol.seed:
        p.error(f"--seed: expected a validation seed, not the scored seed {Protocol.seed}, received {args.seed}")
    start_time = time.perf_counter()
    source = resolve(args.model)
    model = load_model(source)
    card = copy.deepcopy(model.card)
    arch = card["architecture"]
    if INFLATION not in arch or MODEL in arch[INFLATION] or arch["bank"].get("members", 1) < 2:
        p.error("model: expected a bank with a decoder ensemble and the covariance inflation without a model test "
                "(architecture.inflation)")
    obs = load_observer(source)
    if obs.memory_shape != (obs.ny + obs.nu, 1):
        p.error(f"model: expected the bank's memory [y; u], received the shape {obs.memory_shape}")
    record, cache, dt = CompiledRecord(obs), TrialCache.default(), obs.dt

    def trials(cell) -> tuple:
        batch = cache.trials(obs.system, cell)
        ok = batch.ok
        y, u = batch.y[ok], batch.u[ok]
        xhat, z, P = record.record(batch.t, y, u)              # the shipped inflation's covariance
        spread = obs.spread_of(z, np.concatenate([y, u], axis=-1)[..., None])
        print(f"trials   {cell.label}: {int(ok.sum())} ({time.perf_counter() - start_time:.0f} s)", flush=True)
        return batch.x[ok], xhat, P, spread

    nominal = {kind: trials(Protocol(n_trials=args.trials, seed=args.seed, process_std=Protocol.process_std,
                                     measurement_std=Protocol.measurement_std).cell(kind))
               for kind in sig.BENCHMARK_KINDS}
    settings = Settings(n_trials=args.trials, seed=args.seed)
    ood = {Case(family, "ood", args.noise).label: trials(Case(family, "ood", args.noise).cell(settings))
           for family in OOD_FAMILIES}
    S = float(np.mean(np.concatenate([run[3].ravel() ** 2 for run in nominal.values()])))
    target = 100 * cs.GAUSSIAN_COVERAGE[cs.SIGMA_LEVELS.index(2.0)]
    table = []
    for tau, gain, threshold in itertools.product(args.time_constants, args.gains, args.thresholds):
        test = SpreadTest(S, tau, gain, threshold)
        row: dict = {"time_constant": tau, "gain": gain, "threshold": threshold, "coverage_2sigma": {}}
        for name, (x, xhat, P, spread) in {**nominal, **ood}.items():
            var = np.diagonal(P, axis1=-2, axis2=-1) * spread_factor(test, dt, spread)[..., None]
            row["coverage_2sigma"][name] = [round(float(v), 2) for v in
                                            100 * np.mean((x - xhat) ** 2 <= 4 * var, axis=(0, 1))]
        cover = row["coverage_2sigma"]
        row["in_distribution_max"] = max(max(cover[kind]) for kind in nominal)
        row["ood_worst"] = max(abs(v - target) for name in ood for v in cover[name])
        print(f"time constant {tau:g} s, gain {gain:g}, threshold {threshold:g}: in distribution max "
              f"{row['in_distribution_max']:.1f} %, ood " + "; ".join(f"{n} {cover[n]}" for n in ood), flush=True)
        table.append(row)
    allowed = [r for r in table if r["in_distribution_max"] <= IN_DISTRIBUTION_TOP]
    best = (min(allowed, key=lambda r: r["ood_worst"]) if allowed
            else min(table, key=lambda r: r["in_distribution_max"]))
    entry = SpreadTest(S, best["time_constant"], best["gain"], best["threshold"])
    print(f"spread test {json.dumps(entry.to_card())}: {best['coverage_2sigma']}", flush=True)

    arch[INFLATION][SPREAD] = entry.to_card()
    stamp = provenance.stamp(seeds={"validation": args.seed})
    card["training"]["covariance"]["spread_test"] = {
        "command": stamp.command, "commit": stamp.commit,
        "how": f"S: the decoder ensemble's mean squared spread on the protocol's id regimes at its noise; time "
               f"constant, gain and threshold: among the candidates whose 2-sigma coverage there is at most "
               f"{IN_DISTRIBUTION_TOP:g} % per state and regime, the one whose worst 2-sigma coverage over the states "
               f"of the generalisation's ood cases at noise {args.noise:g} is nearest {target:.2f} %",
        "validation_seed": args.seed, "trials_per_case": args.trials, "cases": [*nominal, *ood],
        "candidates": table, "wall_time_s": round(time.perf_counter() - start_time, 1)}
    out = save_model(args.out, dict(model.arrays), card)
    history = Path(source) / "history.json"
    if history.exists():
        shutil.copyfile(history, out / "history.json")
    check = cache.trials(obs.system, Case("square", "ood", args.noise).cell(settings))
    y, u = check.y[check.ok][:4], check.u[check.ok][:4]
    a, b = obs.simulate(check.t, y, u), load_observer(out).simulate(check.t, y, u)
    if not (np.array_equal(a.xhat, b.xhat) and np.array_equal(a.z, b.z)):
        raise SystemExit(f"{out}: the estimates differ from {source}'s")
    print(f"wrote {out} ({time.perf_counter() - start_time:.0f} s)")


if __name__ == "__main__":
    main()
