"""Print the README's results tables from results/protocol/<system>/<system>_scores.json.

Usage: python benchmarks/summarize.py   (after benchmarks/evaluate_models.sh)

Noise on: the ``bank`` observer (the one fit for noisy measurements), the best of the other shipped
observers, and the EKF, with the ratio bank / EKF. Noise-free: the paper's best, bank, the best of
the other shipped observers (which one), and the EKF.
"""

import json
from pathlib import Path

from kklcasadi.provenance import json_payload

KINDS = ("zero", "constant", "sinusoid", "square")
#: docs/protocol.md: the paper's best method per cell (noise-free).
PAPER_BEST = {"duffing": (5.6, 21.1, 22.7, 21.3), "vdp": (5.0, 26.0, 15.5, 17.9),
              "rossler": (52.7, 55.4, 53.5, 54.0), "fhn": (9.8, 42.1, 30.9, 32.5)}
NOISY = "bank"


def _cell(cells: list, method: str, kind: str, noisy: bool) -> float:
    return next(r for r in cells if r["method"] == method and r["kind"] == kind and r["noisy"] is noisy)["smape_mean"]


def _best(cells: list, kind: str, noisy: bool, exclude: tuple) -> tuple[float, str]:
    candidates = [r for r in cells if r["kind"] == kind and r["noisy"] is noisy and r["method"] not in exclude]
    low = min(r["smape_mean"] for r in candidates)
    tied = [r["method"] for r in candidates if round(r["smape_mean"], 1) == round(low, 1)]
    # at u = 0 inject, obs and dyn collapse to the autonomous observer
    return low, "autonomous" if "autonomous" in tied else "/".join(tied)


def main() -> None:
    root = Path(__file__).resolve().parent.parent / "results"
    noisy = ["| system | noise on | " + " | ".join(KINDS) + " |", "|---|---|" + "---|" * len(KINDS)]
    clean = ["| system | noise-free | " + " | ".join(KINDS) + " |", "|---|---|" + "---|" * len(KINDS)]
    for system in PAPER_BEST:
        path = root / "protocol" / system / f"{system}_scores.json"
        if not path.exists():
            continue
        cells = json_payload(json.loads(path.read_text()))
        trials = len(cells[0]["smape"])
        bank = [_cell(cells, NOISY, k, True) for k in KINDS]
        ekf = [_cell(cells, "EKF", k, True) for k in KINDS]
        others = [_best(cells, k, True, ("EKF", NOISY)) for k in KINDS]
        noisy.append(f"| {system} ({trials} trials) | **bank** | " + " | ".join(f"**{v:.2f}**" for v in bank) + " |")
        noisy.append("| | EKF | " + " | ".join(f"{v:.2f}" for v in ekf) + " |")
        noisy.append("| | ratio bank / EKF | " + " | ".join(f"{b / e:.2f}x" for b, e in zip(bank, ekf)) + " |")
        noisy.append("| | best other shipped | " + " | ".join(f"{v:.1f} ({m})" for v, m in others) + " |")
        others = [_best(cells, k, False, ("EKF", NOISY)) for k in KINDS]
        clean.append(f"| {system} ({trials} trials) | paper's best | "
                     + " | ".join(f"{v:.1f}" for v in PAPER_BEST[system]) + " |")
        clean.append("| | **bank** | " + " | ".join(f"**{_cell(cells, NOISY, k, False):.1f}**" for k in KINDS) + " |")
        clean.append("| | best other shipped | " + " | ".join(f"{v:.1f} ({m})" for v, m in others) + " |")
        clean.append("| | EKF | " + " | ".join(f"{_cell(cells, 'EKF', k, False):.1f}" for k in KINDS) + " |")
    print("\n".join(noisy) + "\n\n" + "\n".join(clean))


if __name__ == "__main__":
    main()
