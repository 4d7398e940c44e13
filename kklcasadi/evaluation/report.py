"""Benchmark tables and plots: scores of observers (and the EKF) on the docs/protocol.md cells.

One result type, :class:`MethodScores` (an estimator's :class:`~kklcasadi.evaluation.protocol.CellResult`
per cell), and one table, :func:`markdown_table`, serve ``kklcasadi evaluate`` and ``kklcasadi compare``.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Optional, Sequence

import numpy as np
from tqdm.auto import tqdm

from .. import provenance
from ..plant import signals as sig
from ..plant.systems import System
from ..writes import write_file
from .protocol import BatchEstimator, CellResult, Profile, Protocol, evaluate_cells
from .trialcache import TrialCache

__all__ = ["MethodScores", "score", "markdown_table", "smape_boxplot", "estimates_plot", "estimates_figure",
           "save_scores"]


@dataclass(frozen=True, eq=False)
class MethodScores:
    """One method's cells: ``results[(noisy, kind)]``."""

    label: str
    system: str
    results: dict

    def cell(self, kind: str, noisy: bool) -> CellResult:
        return self.results[(noisy, kind)]

    @property
    def n_trials(self) -> int:
        """Trials per cell (of the first cell), scored and escaped."""
        return next(iter(self.results.values())).n_trials


def _cell_text(result: CellResult) -> str:
    """Mean SMAPE of a cell, with the trials whose state escaped (not scored) where there were any."""
    mean = f"{result.summary.mean:.1f}" if len(result.smape) else "-"
    return mean + (f" ({result.escaped} of {result.n_trials} escaped)" if result.escaped else "")


def score(label: str, estimator: BatchEstimator, system: System, protocol: Protocol, *,
          noise: Sequence[bool] = (False, True), kinds: Sequence[str] = sig.BENCHMARK_KINDS,
          trials: TrialCache | None = None, progress: bool = False,
          profile: Profile | None = None) -> MethodScores:
    """Evaluate ``estimator`` on the noise-free and/or noisy protocol.

    An estimator whose ``shares_inputs`` is True (a
    :class:`~kklcasadi.evaluation.compiled.CompiledEstimator` that does the work of trials with the
    same inputs once) gets the noise-free and noisy cells of a regime in one call (they share their
    inputs); any other gets one call per cell. The scores are the same either way.

    Parameters
    ----------
    label : str
        The method's row label.
    estimator : callable ``(t, y, u) -> xhat``
        See :func:`kklcasadi.evaluation.protocol.evaluate`.
    system : System
    protocol : Protocol
        The noisy protocol; its :meth:`~Protocol.noise_free` variant gives the clean cells.
    noise : sequence of bool
        Which columns: False noise-free, True noisy.
    kinds : sequence of str
        Input regimes.
    trials : TrialCache, optional
        The cells' trials, shared across methods and runs (default: simulated for this call).
    progress : bool
        A progress bar over the cells, labelled ``label``.
    profile : Profile, optional
        Records where the time goes (:func:`kklcasadi.evaluation.protocol.evaluate_cells`).

    Returns
    -------
    MethodScores
    """
    trials = TrialCache(None) if trials is None else trials
    cells = {(noisy, kind): (protocol if noisy else protocol.noise_free()).cell(kind)
             for noisy in noise for kind in kinds}
    together = getattr(estimator, "shares_inputs", False)
    calls = ([[(noisy, kind) for noisy in noise] for kind in kinds] if together
             else [[key] for key in cells])
    results: dict = {}
    with tqdm(total=len(cells), desc=label, unit="cell", disable=not progress) as bar:
        for keys in calls:
            scored = evaluate_cells(estimator, system, [cells[key] for key in keys], trials=trials, profile=profile)
            results.update(zip(keys, scored))
            bar.update(len(keys))
    return MethodScores(label, system.name, {key: results[key] for key in cells})


def markdown_table(scores: Iterable[MethodScores], kinds: Sequence[str] = sig.BENCHMARK_KINDS, *,
                   timing: bool = False) -> str:
    """Mean SMAPE (%) per cell, noise-free then noisy columns, one row per method.

    A cell with trials whose state escaped (the plant ran away; they are not scored) says how many,
    e.g. ``12.3 (9 of 10 escaped)``; ``-`` where every trial escaped.

    With ``timing`` (the estimator comparison) every noise column is shown, the row names the
    system with its trials and the estimator, and three columns follow: ``ms/sample`` (the
    estimator's wall time over all cells divided by the samples estimated), ``ipopt ms`` (the
    mean solver call, MHE) and ``failed`` (solves whose estimate was the fallback).
    """
    scores = list(scores)
    noises = (False, True) if timing else sorted({noisy for s in scores for noisy, _ in s.results})
    head = ((["system", "estimator"] if timing else ["method"])
            + [f"{k} {'noisy' if n else 'clean'}" for n in noises for k in kinds]
            + (["ms/sample", "ipopt ms", "failed"] if timing else []))
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in scores:
        row = [f"{s.system} ({s.n_trials} trials)", s.label] if timing else [f"{s.system} {s.label}"]
        for n in noises:
            for k in kinds:
                r = s.results.get((n, k))
                row.append(_cell_text(r) if r is not None else "")
        if timing:
            cells = list(s.results.values())
            seconds = sum(c.seconds for c in cells)
            samples = sum(c.n_samples for c in cells)
            solves = [c.solve_ms for c in cells if c.solve_ms is not None]
            row += [f"{1e3 * seconds / samples:.3f}", f"{np.mean(solves):.2f}" if solves else "-",
                    str(sum(c.failed for c in cells)) if solves else "-"]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def save_scores(scores: Iterable[MethodScores], path: str | Path, *,
                stamp: Optional[provenance.Stamp] = None, overwrite: bool = False) -> None:
    """Per-trial SMAPE and RMSE-after-settle of every cell, and the trials that escaped, as JSON
    (the summary statistics are null where every trial escaped): ``{"provenance": stamp, "records":
    [one per cell]}`` (:func:`kklcasadi.provenance.json_payload` gives the list back); ``stamp``
    defaults to this process's. Written atomically, over an existing file only with ``overwrite``
    (:func:`kklcasadi.writes.write_file`)."""
    out = []
    for s in scores:
        for (noisy, kind), r in s.results.items():
            summ = r.summary if len(r.smape) else None
            stats = {name: None if summ is None else getattr(summ, field)
                     for name, field in (("smape_mean", "mean"), ("smape_median", "median"), ("smape_q25", "q25"),
                                         ("smape_q75", "q75"))}
            out.append({"method": s.label, "system": s.system, "kind": kind, "noisy": noisy, **stats,
                        "rmse_after_mean": float(np.nanmean(r.rmse_after)) if len(r.rmse_after) else None,
                        "escaped": r.escaped, "smape": r.smape.tolist()})
    write_file(path, json.dumps(provenance.json_record(out, stamp or provenance.stamp()), indent=1) + "\n",
               overwrite=overwrite)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def smape_boxplot(scores: Sequence[MethodScores], path: str | Path, *, noisy: bool = True,
                  kinds: Sequence[str] = sig.BENCHMARK_KINDS, stamp: Optional[provenance.Stamp] = None,
                  overwrite: bool = False) -> Path:
    """Box plots of per-trial SMAPE, one group per input regime, one box per method (PNG, with ``stamp``,
    default this process's, in its metadata; atomically, over an existing file only with ``overwrite``).

    A method without cells in this noise column (the particle filter's noise-free one) is left out.
    """
    plt = _pyplot()
    system = scores[0].system
    scores = [s for s in scores if any((noisy, k) in s.results for k in kinds)]
    fig, ax = plt.subplots(figsize=(2.2 * len(kinds) * max(1, len(scores)) / 2 + 3, 4))
    width = 0.8 / max(1, len(scores))
    for i, s in enumerate(scores):
        present = [j for j, k in enumerate(kinds) if (noisy, k) in s.results]
        data = [s.results[(noisy, kinds[j])].smape if len(s.results[(noisy, kinds[j])].smape) else [np.nan]
                for j in present]
        pos = [j + (i - (len(scores) - 1) / 2) * width for j in present]
        bp = ax.boxplot(data, positions=pos, widths=width * 0.9, patch_artist=True, showfliers=False)
        for patch in bp["boxes"]:
            patch.set_facecolor(f"C{i}")
        ax.plot([], [], color=f"C{i}", lw=6, label=s.label)
    ax.set_xticks(range(len(kinds)), kinds)
    ax.set_ylabel("SMAPE (%)")
    ax.set_title(f"{system}: {'with' if noisy else 'without'} noise")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _write_png(fig, path, stamp, overwrite)


def _write_png(fig: Any, path: str | Path, stamp: Optional[provenance.Stamp], overwrite: bool) -> Path:
    """``fig`` closed and written to ``path`` as a PNG with ``stamp`` (default this process's): atomically, over an
    existing file only with ``overwrite`` (:func:`kklcasadi.writes.write_file`)."""
    png = io.BytesIO()
    try:
        fig.savefig(png, format="png", dpi=110, metadata=provenance.png_metadata(stamp or provenance.stamp()))
    finally:
        _pyplot().close(fig)
    return write_file(path, png.getvalue(), overwrite=overwrite)


#: Line styles of the states in the error panels.
STYLES = ("-", "--", ":", "-.")


def estimates_plot(t: np.ndarray, x: np.ndarray, y: np.ndarray, estimates: dict, path: str | Path, *,
                   u: np.ndarray | None = None, in_domain: np.ndarray | None = None, title: str = "",
                   stamp: Optional[provenance.Stamp] = None, overwrite: bool = False) -> Path:
    """:func:`estimates_figure` written to ``path`` (PNG, ``stamp``, default this process's, in its metadata;
    atomically, over an existing file only with ``overwrite``)."""
    fig = estimates_figure(t, x, y, estimates, u=u, in_domain=in_domain, title=title)
    return _write_png(fig, path, stamp, overwrite)


def estimates_figure(t: np.ndarray, x: np.ndarray, y: np.ndarray, estimates: dict, *, u: np.ndarray | None = None,
                     in_domain: np.ndarray | None = None, title: str = "") -> Any:
    """One run and its estimates: what an estimator saw and how far off it was (a matplotlib Figure).

    Panels, top to bottom: the measured outputs ``y``; each state, true (black) and estimated, the first
    estimator of ``estimates`` drawn above the others; each estimator's error ``xhat - x`` per state on its
    own panel (the error panels share their scale); the input ``u``. Samples the domain monitor flags
    (``in_domain`` False) are shaded on every panel. The legend sits above the panels, off the data.

    Parameters
    ----------
    t : array_like, shape (N,)
        Times, seconds.
    x : array_like, shape (N, nx)
        True states.
    y : array_like, shape (N, ny)
        Measured outputs.
    estimates : dict {label: array_like (N, nx)}
        Estimates in drawing priority: the first is drawn on top.
    u : array_like, shape (N, nu), optional
    in_domain : array_like of bool, shape (N,), optional
        The domain monitor's flags of the first estimator.
    title : str
    """
    plt = _pyplot()
    import matplotlib.lines

    t, x, y = np.asarray(t), np.atleast_2d(np.asarray(x)), np.asarray(y).reshape(len(t), -1)
    nx, ny, labels = x.shape[1], y.shape[1], list(estimates)
    rows = 1 + nx + len(labels) + (u is not None)
    fig, axes = plt.subplots(rows, 1, figsize=(9, 1.7 * rows + 0.8), sharex=True, squeeze=False)
    axes = axes[:, 0]
    for j in range(ny):
        axes[0].plot(t, y[:, j], ".", ms=1.5, color=f"C{7 + j}", label="measured y" if j == 0 else None)
    axes[0].set_ylabel("y (measured)" if ny == 1 else f"y1..y{ny} (measured)")
    for i in range(nx):
        ax = axes[1 + i]
        ax.plot(t, x[:, i], "k", lw=1.6, zorder=2, label="true state" if i == 0 else None)
        for k, label in enumerate(labels):                      # the first estimator on top
            ax.plot(t, np.asarray(estimates[label])[:, i], color=f"C{k}", lw=1.1, zorder=3 + len(labels) - k,
                    label=label if i == 0 else None)
        ax.set_ylabel(f"x{i + 1}")
    errors = axes[1 + nx:1 + nx + len(labels)]
    for k, (label, ax) in enumerate(zip(labels, errors)):
        error = np.asarray(estimates[label]) - x
        for i in range(nx):
            ax.plot(t, error[:, i], color=f"C{k}", lw=0.9, ls=STYLES[i % len(STYLES)])
        ax.axhline(0.0, color="0.6", lw=0.6)
        ax.set_ylabel(f"{label}\nerror")
    if len(errors) > 1:                                          # one scale: the panels compare at a glance
        low = min(ax.get_ylim()[0] for ax in errors)
        high = max(ax.get_ylim()[1] for ax in errors)
        for ax in errors:
            ax.set_ylim(low, high)
    if u is not None:
        axes[-1].plot(t, np.asarray(u).reshape(len(t), -1), color="C9", lw=1, label="input u")
        axes[-1].set_ylabel("u")
    if in_domain is not None and not np.all(in_domain):
        flagged = ~np.asarray(in_domain, dtype=bool)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], flagged.astype(int), [0]])))
        for ax in axes:
            for start, stop in zip(edges[::2], edges[1::2]):
                ax.axvspan(t[start], t[min(stop, len(t) - 1)], color="C3", alpha=0.15, lw=0,
                           label=f"outside the trained domain ({int(flagged.sum())} samples)"
                           if ax is axes[0] and start == edges[0] else None)
    axes[-1].set_xlabel("t (s)")
    handles = {h_label: handle for ax in axes for handle, h_label in zip(*ax.get_legend_handles_labels())}
    for i in range(nx):                                          # the error panels' line styles, in neutral grey
        handles[f"error of x{i + 1}"] = matplotlib.lines.Line2D([], [], color="0.4", lw=0.9,
                                                                 ls=STYLES[i % len(STYLES)])
    height = fig.get_figheight()
    fig.suptitle(title, y=1 - 0.1 / height)
    fig.legend(handles.values(), handles.keys(), loc="upper center", ncol=min(len(handles), 4), fontsize=8,
               bbox_to_anchor=(0.5, 1 - 0.35 / height), frameon=False)
    fig.tight_layout()
    fig.subplots_adjust(top=1 - (0.5 + 0.18 * np.ceil(len(handles) / 4)) / height)   # room for title and legend
    return fig
