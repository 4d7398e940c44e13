"""Print the README's summary table from results/<system>/<system>_scores.json.

Usage: python benchmarks/summarize.py   (after benchmarks/evaluate_models.sh)
"""

import json
from pathlib import Path

KINDS = ("zero", "constant", "sinusoid", "square")
#: PROTOCOL.md: the paper's best method per cell (noise-free) and the EKF with noise.
PAPER_BEST = {"duffing": (5.6, 21.1, 22.7, 21.3), "vdp": (5.0, 26.0, 15.5, 17.9),
              "rossler": (52.7, 55.4, 53.5, 54.0), "fhn": (9.8, 42.1, 30.9, 32.5)}


def main() -> None:
    root = Path(__file__).resolve().parent.parent / "results"
    rows = ["| system | | " + " | ".join(KINDS) + " |", "|---|---|" + "---|" * len(KINDS)]
    for system in PAPER_BEST:
        path = root / system / f"{system}_scores.json"
        if not path.exists():
            continue
        cells = json.loads(path.read_text())
        trials = len(cells[0]["smape"])

        def best(noisy: bool, exclude: tuple = ("EKF",), cells: list = cells) -> list[str]:
            out = []
            for kind in KINDS:
                c = [r for r in cells if r["kind"] == kind and r["noisy"] is noisy and r["method"] not in exclude]
                low = min(r["smape_mean"] for r in c)
                tied = [r["method"] for r in c if round(r["smape_mean"], 1) == round(low, 1)]
                # at u = 0 inject, obs and dyn collapse to the autonomous observer
                name = "autonomous" if "autonomous" in tied else "/".join(tied)
                out.append(f"{low:.1f} ({name})")
            return out

        ekf = [next(r for r in cells if r["kind"] == k and r["noisy"] and r["method"] == "EKF")["smape_mean"]
               for k in KINDS]
        rows.append(f"| {system} | paper's best, noise-free | " + " | ".join(f"{v:.1f}" for v in PAPER_BEST[system])
                    + " |")
        rows.append(f"| | ours, noise-free ({trials} trials) | " + " | ".join(best(False)) + " |")
        rows.append("| | ours, noise on | " + " | ".join(best(True)) + " |")
        rows.append("| | EKF, noise on | " + " | ".join(f"{v:.1f}" for v in ekf) + " |")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
