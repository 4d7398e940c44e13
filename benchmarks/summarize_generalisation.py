"""Print the README's generalisation tables from results/generalisation/<system>_generalisation.json.

Usage: python benchmarks/summarize_generalisation.py [--model bank]
(after ``kklcasadi generalise models/<system>/bank --pf 1000 --out results/generalisation`` per system)

Table 1, noise 0.1 (the fitted level): mean SMAPE of the model, the EKF and the particle filter per
case that is not in distribution (the ood ranges of the three forced families, the held-out
families), with the ratio model / EKF; the in-distribution cases as one column (the worst ratio).
Table 2, the other noise levels: the worst and the mean ratio model / EKF over the in-distribution
families and over the others. Table 3, the domain monitor per group of cases.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

SYSTEMS = ("duffing", "vdp", "rossler", "fhn")
OFF = (("constant", "ood"), ("sinusoid", "ood"), ("square", "ood"), ("chirp", "held_out"), ("random", "held_out"),
       ("feedback", "held_out"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="bank", help="the model's label in the reports")
    args = parser.parse_args()
    root = Path(__file__).resolve().parent.parent / "results" / "generalisation"
    reports = {s: json.loads((root / f"{s}_generalisation.json").read_text()) for s in SYSTEMS
               if (root / f"{s}_generalisation.json").exists()}
    head = ["system, noise 0.1", "in distribution (worst of 4)"] + [f"{f} {r}" for f, r in OFF]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for system, data in reports.items():
        cases = {(c["family"], c["regime"], c["noise"]): c for c in data["cases"]}
        rows = {"model": [], "EKF": [], "PF": [], "ratio": []}
        fit = [c for c in data["cases"] if c["noise"] == 0.1 and c["models"][args.model]["category"] == "fit"]
        worst = max(fit, key=lambda c: c["models"][args.model]["ratio_ekf"])
        for case in [worst] + [cases[(f, r, 0.1)] for f, r in OFF]:
            m = case["models"][args.model]
            rows["model"].append(f"{m['smape_mean']:.2f}")
            rows["EKF"].append(f"{case['ekf']['smape_mean']:.2f}")
            rows["PF"].append(f"{case['pf']['smape_mean']:.2f}" if "pf" in case else "-")
            rows["ratio"].append(f"**{m['ratio_ekf']:.2f}x**" if m["ratio_ekf"] > 1.3 else f"{m['ratio_ekf']:.2f}x")
        rows["model"][0] += f" ({worst['family']})"
        label = f"{system} ({data['cases'][0]['trials']} trials) {args.model}"
        lines.append(f"| {label} | " + " | ".join(rows["model"]) + " |")
        lines.append("| EKF | " + " | ".join(rows["EKF"]) + " |")
        lines.append(f"| PF ({data['pf_particles']} particles) | " + " | ".join(rows["PF"]) + " |")
        lines.append(f"| {args.model} / EKF | " + " | ".join(rows["ratio"]) + " |")
    print("\n".join(lines) + "\n")

    head = ["system", "noise", "in distribution: worst / mean bank / EKF", "ood and held out: worst / mean"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for system, data in reports.items():
        for noise in (0.05, 0.1, 0.2):
            groups = {True: [], False: []}
            for c in data["cases"]:
                if c["noise"] == noise:
                    m = c["models"][args.model]
                    groups[m["category"] == "fit"].append(m["ratio_ekf"])
            cells = [f"{max(v):.2f}x / {sum(v) / len(v):.2f}x" if v else "-" for v in (groups[True], groups[False])]
            lines.append(f"| {system} | {noise:g} | " + " | ".join(cells) + " |")
    print("\n".join(lines) + "\n")

    head = ["system", "group of cases", "trials", "bad", "flagged", "precision", "recall",
            "flagged samples after 5 s: bad trials", "other trials", "in distribution: worst family"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for system, data in reports.items():
        fit = [c for c in data["cases"] if c["noise"] == data["models"][args.model]["fit_noise"]
               and c["models"][args.model]["category"] == "fit"]
        share = {c["family"]: sum(c["models"][args.model]["flagged_share"]) / c["trials"] for c in fit}
        worst = max(share, key=share.get)
        for g in data["models"][args.model]["monitor"]:
            cells = [system, g["group"], str(g["trials"]), str(g["bad"]), str(g["flagged"])]
            cells += ["-" if g[k] is None else f"{g[k]:.2f}" for k in ("precision", "recall")]
            cells += ["-" if g[k] is None else f"{g[k]:.3f}" for k in ("share_bad", "share_other")]
            cells.append(f"{share[worst]:.3f} ({worst})" if g["group"] == "in distribution" else "")
            lines.append("| " + " | ".join(cells) + " |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
