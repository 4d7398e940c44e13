"""What a design search shows: the summary table of its best trials and the plot of its progress and of what
mattered."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ... import provenance
from ...writes import write_file
from .storage import complete_trials, optuna_module, public_url

__all__ = ["summary_table", "search_plot"]


def summary_table(study: Any, url: str, top: int = 10) -> str:
    """Markdown: the study's state, its baseline and its best trials with their parameters."""
    optuna = optuna_module()
    states = {state.name.lower(): 0 for state in optuna.trial.TrialState}
    for trial in study.get_trials(deepcopy=False):
        states[trial.state.name.lower()] += 1
    lines = [f"# study {study.study_name}", "", f"storage: {public_url(url)}",
             "trials: " + ", ".join(f"{n} {state}" for state, n in states.items() if n), ""]
    baseline = study.user_attrs.get("baseline")
    record = study.user_attrs.get("record", {})
    objective = record.get("objective", {})
    if objective:
        lines += [f"score: {objective['score']} (1 = the EKF); cells: "
                  + ", ".join(f"{c['name']} ({c['n_trials']} trials, seed {c['seed']})" for c in objective["cells"]),
                  ""]
    if baseline is not None:
        lines += [f"baseline (the recipe at the budget caps): {baseline['value']:.4f}, trained in "
                  f"{baseline['train_s']} s", ""]
    complete = sorted(complete_trials(study), key=lambda t: t.value)[:top]
    if not complete:
        return "\n".join(lines + ["no complete trial yet"])
    names = sorted({name for trial in complete for name in trial.params})
    cells = sorted({name for trial in complete for name in trial.user_attrs.get("cells", {})})
    lines.append("| trial | score | " + " | ".join(cells) + " | train (s) | " + " | ".join(names) + " | retry of |")
    lines.append("|---" * (4 + len(cells) + len(names)) + "|")
    for trial in complete:
        retry = trial.system_attrs.get("failed_trial")
        values = [_short(trial.params.get(name, "-")) for name in names]
        smape = [f"{trial.user_attrs.get('cells', {}).get(c, float('nan')):.2f}" for c in cells]
        lines.append(f"| {trial.number} | {trial.value:.4f} | " + " | ".join(smape) + f" | "
                     f"{trial.user_attrs.get('train_s', '-')} | " + " | ".join(values) + f" | "
                     f"{'-' if retry is None else retry} |")
    lines += ["", "cells: the observer's mean SMAPE % per validation cell"]
    return "\n".join(lines)


def _short(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def search_plot(study: Any, path: Path, *, stamp: Optional[provenance.Stamp] = None) -> Path:
    """PNG of the search: the score of every complete trial against its number (with the best so
    far and the baseline), and Optuna's parameter importances; ``stamp`` (default this process's) in its
    metadata."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    optuna = optuna_module()
    complete = sorted(complete_trials(study), key=lambda t: t.number)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4))
    if complete:
        numbers = [t.number for t in complete]
        values = [t.value for t in complete]
        ax.plot(numbers, values, "o", ms=4, label="trial")
        ax.step(numbers, np.minimum.accumulate(values), where="post", label="best so far")
    baseline = study.user_attrs.get("baseline")
    if baseline is not None:
        ax.axhline(baseline["value"], color="k", ls="--", lw=1, label="recipe (baseline)")
    ax.axhline(1.0, color="gray", ls=":", lw=1, label="EKF")
    ax.set(xlabel="trial", ylabel="validation score (SMAPE / EKF's)", title=study.study_name)
    ax.legend(fontsize=8)
    if len(complete) >= 4:
        importances = optuna.importance.get_param_importances(study)
        names = list(importances)[::-1]
        bx.barh(names, [importances[n] for n in names])
        bx.set(xlabel="importance (Optuna, PED-ANOVA)", title="what mattered")
    else:
        bx.text(0.5, 0.5, f"importances need 4 complete trials ({len(complete)} so far)", ha="center")
        bx.set_axis_off()
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110, metadata=provenance.png_metadata(stamp or provenance.stamp()))
    plt.close(fig)
    return write_file(path, buffer.getvalue(), overwrite=True, argument="path")
