"""Write docs/results/robustness.md, the robust observers beside the bank and the baselines, from results/robustness/.

    python benchmarks/summarize_robustness.py [--check | --print]

(after ``kklcasadi robustness models/<system>/bank models/<system>/robust --pf 1000 [--pf-trials 30] --out
results/robustness/<system>`` per system: the scored trials, seed 2026, tuning trials seed 4242, 100 and 40
per case; the page names each report's command). Per system one table: each case's mean SMAPE of the EKF,
the EKF tuned on the tuning trials, the augmented EKF, the particle filter over states and parameters, the
shipped ``bank`` and the ``robust`` observer; the robust observer's ratio to the tuned and to the augmented
EKF; the issue's targets and whether it meets them; the share of trials its domain monitor flags. Then where
it loses, and by how much, and which observer to pick when.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from pages import ROOT, header, publish

from kklcasadi import provenance

RESULTS = ROOT / "results" / "robustness"
SYSTEMS = ("duffing", "vdp")


def scored() -> list[str]:
    """The systems of :data:`SYSTEMS` whose scored report is stored (a system's run lands when it ends)."""
    return [s for s in SYSTEMS if (RESULTS / s / f"{s}_robustness.json").is_file()]
COMMAND = "python benchmarks/summarize_robustness.py"
TITLES = {"ekf": "EKF", "tuned": "tuned EKF", "augmented": "augmented EKF", "pf": "PF (x, p)"}


def _pf_text(report: dict) -> str:
    """How the particle filter ran: its particles, and on how many of each case's trials where not all."""
    if not report.get("pf_particles"):
        return ""
    some = report.get("pf_trials")
    return (f"; the particle filter with {report['pf_particles']} particles"
            + (f" on the first {some} trials of each case (its column and the ratios to it on those)" if some else ""))


def _report(system: str) -> tuple[Path, dict, provenance.Stamp]:
    path = RESULTS / system / f"{system}_robustness.json"
    return path, provenance.json_payload(json.loads(path.read_text())), provenance.read(path)


def _mean(case: dict, label: str) -> float:
    return case["models"][label]["smape_mean"] if label in case["models"] else case["baselines"][label]["smape_mean"]


def _table(report: dict) -> tuple[str, list[str]]:
    """The system's table, and the lines that say where the robust observer misses a target."""
    names = [b for b in TITLES if b in report["cases"][0]["baselines"]]
    head = ["case", "kind"] + [TITLES[b] for b in names] + ["bank", "robust", "robust / tuned EKF",
                                                            "robust / augmented EKF", "targets", "flagged"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    misses = []
    for case in report["cases"]:
        robust = case["models"]["robust"]
        checks = robust["targets"]
        text = "; ".join(f"{TITLES[c['baseline']]} <= {c['target']:g}x: {'met' if c['met'] else 'missed'}"
                         for c in checks)
        if case["case"]["kind"] == "outside":
            text += f"; flagged >= 0.5: {'met' if (robust['flagged_trials'] or 0.0) >= 0.5 else 'missed'}"
        row = [case["case"]["name"], case["case"]["kind"]] + [f"{_mean(case, b):.2f}" for b in names] + \
            [f"{_mean(case, 'bank'):.2f}", f"**{robust['smape_mean']:.2f}**",
             f"{robust['ratios']['tuned']:.2f}x", f"{robust['ratios']['augmented']:.2f}x",
             text,
             "-" if robust["flagged_trials"] is None else f"{robust['flagged_trials']:.2f}"]
        lines.append("| " + " | ".join(row) + " |")
        for c in checks:
            if not c["met"]:
                misses.append(f"{case['case']['name']}: {c['ratio']:.2f}x the {TITLES[c['baseline']]} (target "
                              f"{c['target']:g}x)")
        if case["case"]["kind"] == "outside" and (robust["flagged_trials"] or 0.0) < 0.5:
            misses.append(f"{case['case']['name']}: the monitor flags {robust['flagged_trials'] or 0.0:.2f} of the "
                          "trials (target: at least half)")
    return "\n".join(lines) + "\n", misses


#: The estimators a user picks among, in the order of the ranking's ties.
CANDIDATES = {"bank": "`bank`", "robust": "`robust`", "tuned": "tuned EKF", "augmented": "augmented EKF"}
KINDS = {"exact": "the exact model", "corner": "the box's corners", "inside": "inside the box",
         "outside": "effects outside the family", "noise": "heavy tails, outliers, quantisation"}


def _pick(reports: dict) -> str:
    """Per kind of case and system, the estimators ranked by their mean SMAPE averaged over the kind's cases."""
    lines = ["| cases | " + " | ".join(reports) + " |", "|" + "---|" * (len(reports) + 1)]
    for kind, title in KINDS.items():
        row = [title]
        for report in reports.values():
            cases = [c for c in report["cases"] if c["case"]["kind"] == kind]
            means = {name: sum(_mean(c, name) for c in cases) / len(cases) for name in CANDIDATES}
            row.append(", ".join(f"{CANDIDATES[n]} {means[n]:.2f}" for n in sorted(means, key=means.get)))
        lines.append("| " + " | ".join(row) + " |")
    return ("\n## Which to pick\n\nPer kind of case, the four estimators a user picks among (the particle filter "
            "is the reference) ranked by their mean SMAPE % over the kind's cases, best first:\n\n"
            + "\n".join(lines) + "\n")


def page() -> str:
    parts = [header("Results: robust observers where the EKF's model or noise is wrong", COMMAND,
                    "`results/robustness/<system>/<system>_robustness.json`"),
             "\nThe robustness benchmark (docs/protocol.md, \"Robustness\"): the plant's coefficients at the corners "
             "of a +-30 % box and inside it, effects outside that family, heavy-tailed noise, outliers and "
             "quantisation; mean SMAPE % over the scored trials, every estimator on the same trials. `robust` is "
             "`models/<system>/robust`, a `bank` fit over the family with Gaussian and Student-t (nu = 3) "
             "measurement noise, its latent holding a model copy of the plant at each corner of the box beside the "
             "nominal ones, and the augmented EKF itself, whose state estimate its decoder corrects (`kklcasadi train "
             "--ekf-block`); `bank` the shipped observer of the nominal plant. The tuned and the "
             "augmented EKF "
             "chose their settings on the tuning trials of each case; the particle filter (over states and "
             "parameters, the box as its prior, the case's noise model as its likelihood) would be the Bayes "
             "reference inside the family with particles enough; where the augmented EKF beats it, its particles "
             "were too few.\n"]
    for system in scored():
        path, report, stamp = _report(system)
        table, misses = _table(report)
        s = report["settings"]
        parts.append(f"\n## {system}\n\nFrom `{path.relative_to(ROOT)}`, written by `{stamp.command}` at commit "
                     f"`{stamp.commit[:12]}` ({s['n_trials']} scored trials per case, seed {s['seed']}; "
                     f"{s['n_tuning']} tuning trials, seed {s['tuning_seed']}"
                     + _pf_text(report) + "):\n\n")
        parts.append(table)
        parts.append("\nWhere `robust` misses a target: " + ("; ".join(misses) if misses else "nowhere") + ".\n")
    for system in [s for s in SYSTEMS if s not in scored()]:
        parts.append(f"\n## {system}\n\nNo scored run is stored: `models/{system}/robust` ships unscored here "
                     f"(`kklcasadi robustness models/{system}/bank models/{system}/robust --pf 1000 --out "
                     f"results/robustness/{system}` writes it).\n")
    parts.append(_pick({system: _report(system)[1] for system in scored()}))
    return "".join(parts)


def main(argv: list[str] | None = None) -> int:
    return publish("robustness.md", page, argv, description=__doc__.splitlines()[0])


if __name__ == "__main__":
    sys.exit(main())
