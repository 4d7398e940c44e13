"""Set the models of several ``kklcasadi generalise`` reports side by side: bank / EKF per case, and the
geometric mean over the cases.

    python benchmarks/compare_generalisation.py REPORT.json [REPORT.json ...] [--labels A,B,...] [--out TABLE.md]

The reports must hold the same cases on the same trials (the EKF's per-trial SMAPE agrees: one
``--seed``, ``--trials``, families, regimes and noise levels); each model's column is the ratio of its
mean SMAPE to the EKF's in a case, as ``kklcasadi generalise`` reports it. A model label that occurs in
two reports is an error: pass ``--labels`` to ``kklcasadi generalise``, or here one label per report
(each of them holding one model; for instance two reports of ``models/<system>/bank`` at two commits).
``--out`` is refused before anything is read where it exists (a report among them, too), and written whole.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from kklcasadi import provenance
from kklcasadi.writes import refuse_existing, write_file


def load(paths: list[Path], names: list[str] | None = None) -> tuple[list[tuple], dict[str, dict[tuple, float]]]:
    """The cases (family, regime, noise) in the first report's order and each model's ratios per case;
    ``names``: one label per report, each report of one model, in place of the reports' labels."""
    if names is not None and len(names) != len(paths):
        raise SystemExit(f"--labels: expected one label per report ({len(paths)}), received {len(names)}")
    cases: list[tuple] = []
    ekf: dict[tuple, list] = {}
    ratios: dict[str, dict[tuple, float]] = {}
    for i, path in enumerate(paths):
        report = json.loads(path.read_text())
        if names is not None:
            models = {label for case in report["cases"] for label in case["models"]}
            if len(models) != 1:
                raise SystemExit(f"--labels: expected one model in {path}, received {sorted(models)}")
            for case in report["cases"]:
                case["models"] = {names[i]: next(iter(case["models"].values()))}
        keys = [(c["family"], c["regime"], c["noise"]) for c in report["cases"]]
        if not cases:
            cases = keys
        if sorted(keys) != sorted(cases):
            raise SystemExit(f"{path}: expected the cases of {paths[0]}, received other ones")
        for key, case in zip(keys, report["cases"]):
            if ekf.setdefault(key, case["ekf"]["smape"]) != case["ekf"]["smape"]:
                raise SystemExit(f"{path}: the EKF's scores of case {key} differ from {paths[0]}'s: other trials")
            for label, model in case["models"].items():
                if key in ratios.get(label, {}):
                    raise SystemExit(f"{path}: model {label!r} is in an earlier report too; relabel one")
                ratios.setdefault(label, {})[key] = model["smape_mean"] / case["ekf"]["smape_mean"]
    return cases, ratios


def table(cases: list[tuple], ratios: dict[str, dict[tuple, float]]) -> str:
    """The markdown table: a row per case, a column per model, the geometric mean last."""
    labels = list(ratios)
    lines = ["| case | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels)]
    for key in cases:
        lines.append(f"| {key[0]} {key[1]} {key[2]} | " + " | ".join(f"{ratios[m][key]:.3f}x" for m in labels) + " |")
    means = [math.exp(sum(math.log(ratios[m][k]) for k in cases) / len(cases)) for m in labels]
    lines.append("| geometric mean | " + " | ".join(f"{g:.3f}" for g in means) + " |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", type=Path)
    parser.add_argument("--labels", help="comma-separated column labels, one per report of one model")
    parser.add_argument("--out", type=Path, help="write the table there too")
    args = parser.parse_args()
    if args.out:
        refuse_existing({args.out: "--out"})
    text = table(*load(args.reports, args.labels.split(",") if args.labels else None))
    print(text)
    if args.out:
        write_file(args.out, provenance.markdown(text + "\n", provenance.stamp()), argument="--out")
    return 0


if __name__ == "__main__":
    sys.exit(main())
