"""Compare two ``kklcasadi evaluate --out`` score files trial by trial (before/after a speed change).

    python benchmarks/compare_scores.py results/before/duffing_scores.json results/after/duffing_scores.json

Prints, per method and cell, the largest difference of the per-trial SMAPE and of the cell's summary
numbers, and exits with status 1 when a method or cell is missing on one side, or when a difference
exceeds ``--tolerance`` (relative to 1 + |before|; default 0: bitwise equal).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

SUMMARY = ("smape_mean", "smape_median", "smape_q25", "smape_q75", "rmse_after_mean")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before")
    parser.add_argument("after")
    parser.add_argument("--tolerance", type=float, default=0.0,
                        help="largest |after - before| / (1 + |before|) accepted (default 0: bitwise)")
    args = parser.parse_args()
    cells = []
    for path in (args.before, args.after):
        with open(path) as handle:
            cells.append({(c["method"], c["kind"], c["noisy"]): c for c in json.load(handle)})
    before, after = cells
    bad = sorted(set(before) ^ set(after))
    for key in bad:
        print(f"{key}: only in {'the first' if key in before else 'the second'} file")
    worst = 0.0
    for key in sorted(set(before) & set(after)):
        b, a = before[key], after[key]
        pairs = [(np.asarray(b["smape"], float), np.asarray(a["smape"], float))]
        pairs += [(np.asarray([b[name]], float), np.asarray([a[name]], float)) for name in SUMMARY]
        if any(x.shape != y.shape for x, y in pairs):
            print(f"{key}: {len(b['smape'])} trials before, {len(a['smape'])} after")
            bad.append(key)
            continue
        diff = max(float(np.max(np.abs(y - x) / (1 + np.abs(x)), initial=0.0)) for x, y in pairs)
        worst = max(worst, diff)
        if diff > args.tolerance:
            bad.append(key)
        print(f"{key[0]:>14s} {key[1]:>9s} {'noisy' if key[2] else 'clean'}: max relative difference {diff:.1e}"
              f"{'' if diff <= args.tolerance else '  > tolerance'}")
    print(f"{len(set(before) & set(after))} cells compared; largest relative difference {worst:.1e}; "
          f"{'all within' if not bad else f'{len(bad)} cells beyond'} the tolerance {args.tolerance:g}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
