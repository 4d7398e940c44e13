"""Score a study's best model and its baseline again on fresh validation trials (another seed than the
study's, same families), beside the EKF: the check that the best trial's edge is not selection noise.

Usage: python benchmarks/tune/confirm.py OUT --plant FILE.py:NAME [--seed S] [--trials N]   (writes OUT/confirm.md,
refused before any work where it exists)
"""

from __future__ import annotations

import argparse
from pathlib import Path

from kklcasadi import provenance
from kklcasadi.evaluation import tune as tn
from kklcasadi.evaluation.trialcache import TrialCache
from kklcasadi.observer.kkl import load_observer
from kklcasadi.plant.systems import load_plant
from kklcasadi.writes import refuse_existing, write_file


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--plant", required=True)
    parser.add_argument("--seed", type=int, default=tn.VALIDATION_SEED + 1000)
    parser.add_argument("--trials", type=int, default=50)
    args = parser.parse_args()
    refuse_existing({args.out / "confirm.md": "OUT"})
    plant = load_plant(args.plant)
    models = {name: load_observer(args.out / name, system=plant) for name in (tn.BEST_DIR, tn.BASELINE_DIR)}
    search = models[tn.BEST_DIR].model.spec.search
    cells = [tn.ValidationCell(c["name"], c["kind"], tuple(tuple(r) for r in c["ranges"]), args.trials, c["T"],
                               c["dt"], c["process_std"], c["measurement_std"], args.seed, c["index"])
             for c in search.objective["cells"]]
    validation = tn.Validation.build(plant, cells, trials=TrialCache(args.out / "cache"))
    scores = {name: tn.score(obs, validation) for name, obs in models.items()}
    names = [c.name for c in cells]
    lines = [f"study {search.study}: best trial {search.trial} (validation {search.value:.4f}, baseline "
             f"{search.baseline:.4f}); fresh trials: seed {args.seed}, {args.trials} per cell", "",
             "| model | score (SMAPE / EKF's) | " + " | ".join(names) + " |", "|---" * (len(names) + 2) + "|"]
    for name, (value, per_cell) in scores.items():
        lines.append(f"| {name} | {value:.4f} | " + " | ".join(f"{per_cell[n]:.2f}" for n in names) + " |")
    lines.append("| EKF | 1 | " + " | ".join(f"{validation.ekf[n]:.2f}" for n in names) + " |")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    write_file(args.out / "confirm.md", provenance.markdown(text, provenance.stamp(seeds={"trials": args.seed})),
               argument="OUT")
    print(f"wrote {args.out / 'confirm.md'}")


if __name__ == "__main__":
    main()
