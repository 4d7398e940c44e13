"""The estimator comparison of docs/protocol.md: learned KKL observer, EKF, MHE and KKL-primed MHE.

:func:`compare_system` scores every estimator on the same protocol trials of one system (four
input regimes, noise off and on) and times each in the same run. The table (:func:`markdown_table`)
sets beside each other the mean SMAPE per cell and the computation time per sample.

Command line (``kklcasadi compare`` once registered, or ``python benchmarks/compare_estimators.py``)::

    kklcasadi compare --trials 100 --out results/estimators                 # full protocol
    kklcasadi compare --systems duffing vdp --trials 20 --out results/estimators

Each system's scores go to ``OUT/<system>.json``; the table of every system found in ``OUT`` is
rewritten to ``OUT/table.md`` after each system, so systems can run in separate processes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from . import metrics, systems
from .ekf import EKF
from .mhe import MHE, MHEStats, kkl_error_profile
from .observer import KKLObserver, load_observer
from .protocol import Protocol

__all__ = ["EstimatorCell", "SystemComparison", "compare_system", "markdown_table",
           "DEFAULT_METHODS", "cmd_compare", "add_compare_parser", "main"]

KINDS = ("zero", "constant", "sinusoid", "square")
#: The learned observer compared per system: the best noisy-protocol variant of the README's
#: results table (``results/<system>/``).
DEFAULT_METHODS = {"duffing": "bank", "vdp": "bank", "fhn": "bank", "rossler": "bank"}
#: RK4 steps per sample interval in the MHE model: FitzHugh-Nagumo is stiff at the box edge.
MHE_SUBSTEPS = {"fhn": 4}


@dataclass(frozen=True)
class EstimatorCell:
    """One estimator on one cell.

    Attributes
    ----------
    estimator : str
        Row label.
    kind : str
        Input regime.
    noisy : bool
    smape : list of float
        Per-trial SMAPE (%).
    seconds : float
        Wall time of the estimator over the whole cell.
    n_samples : int
        Trials x samples estimated.
    failed : int
        Failed solves (MHE; their estimate was the fallback); 0 for the others.
    solve_ms : float or None
        Mean wall time of one ipopt call (MHE), ms.
    """

    estimator: str
    kind: str
    noisy: bool
    smape: list
    seconds: float
    n_samples: int
    failed: int = 0
    solve_ms: Optional[float] = None

    @property
    def mean(self) -> float:
        return float(np.mean(self.smape))

    @property
    def ms_per_sample(self) -> float:
        return 1e3 * self.seconds / self.n_samples


@dataclass(frozen=True)
class SystemComparison:
    """All cells of one system, with the settings that produced them."""

    system: str
    method: str
    n_trials: int
    seed: int
    horizons: tuple
    primed_horizon: int
    calibration_trials: int
    cells: tuple = field(default_factory=tuple)

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> SystemComparison:
        cells = tuple(EstimatorCell(**c) for c in data["cells"])
        return cls(**{**data, "horizons": tuple(data["horizons"]), "cells": cells})

    @property
    def estimators(self) -> list[str]:
        seen: list[str] = []
        for cell in self.cells:
            if cell.estimator not in seen:
                seen.append(cell.estimator)
        return seen


def _timed(run: Callable[[], Any]) -> tuple[Any, float]:
    start = time.perf_counter()
    out = run()
    return out, time.perf_counter() - start


def compare_system(observer: KKLObserver, protocol: Protocol, *, horizons: Sequence[int] = (10, 30),
                   primed_horizon: int = 5, calibration_trials: int = 5,
                   kinds: Sequence[str] = KINDS, noise: Sequence[bool] = (False, True),
                   log: Optional[Callable[[str], None]] = None) -> SystemComparison:
    """Score the observer, the EKF, MHE (each horizon) and the KKL-primed MHE on one system.

    Every estimator sees the same trials (``protocol.trials``); noise-free cells use
    ``protocol.noise_free()``. The KKL-primed MHE is primed by ``observer``, with the error
    profile calibrated (:func:`kklcasadi.mhe.kkl_error_profile`) on ``calibration_trials`` runs
    per regime drawn with seed ``protocol.seed + 1`` (not the scored ones). Its time includes
    the observer's.

    Parameters
    ----------
    observer : KKLObserver
    protocol : Protocol
        Noise-on protocol (trials, horizon, seed).
    horizons : sequence of int
        MHE horizons ``N``.
    primed_horizon : int
        Horizon of the KKL-primed MHE.
    calibration_trials : int
    kinds : sequence of str
        Input regimes.
    noise : sequence of bool
        Noise settings to run (False: noise-free).
    log : callable, optional
        Progress lines (e.g. ``print``).

    Returns
    -------
    SystemComparison
    """
    if not isinstance(observer, KKLObserver):
        raise TypeError(f"observer: expected a KKLObserver, received {type(observer).__name__}.")
    if not isinstance(protocol, Protocol):
        raise TypeError(f"protocol: expected a kklcasadi.protocol.Protocol, received "
                        f"{type(protocol).__name__}.")
    plant, dt = observer.system, observer.dt
    if abs(protocol.dt - dt) > 1e-12:
        raise ValueError(f"protocol: its dt = {protocol.dt} differs from the observer's dt = {dt}.")
    say = log or (lambda _line: None)
    substeps = MHE_SUBSTEPS.get(plant.name, 1)
    ekf = EKF(plant, dt)
    kkl_label = f"KKL ({observer.method})"
    cells: list[EstimatorCell] = []
    for noisy in noise:
        prot = protocol if noisy else protocol.noise_free()
        noise_kw = {"process_std": prot.process_std, "measurement_std": prot.measurement_std}
        mhes = {n: MHE(plant, dt, n, substeps=substeps, **noise_kw) for n in horizons}
        primed = MHE(plant, dt, primed_horizon, substeps=substeps, **noise_kw)
        calibration = Protocol(n_trials=calibration_trials, T=prot.T, dt=dt,
                               process_std=prot.process_std,
                               measurement_std=prot.measurement_std, seed=prot.seed + 1,
                               regime=prot.regime)
        profile = kkl_error_profile(observer, calibration, kinds)
        for kind in kinds:
            batch = prot.trials(plant, kind)
            t, x, y, u = batch.t, batch.x[batch.ok], batch.y[batch.ok], batch.u[batch.ok]
            n_samples = int(y.shape[0] * y.shape[1])

            def cell(label: str, xhat: np.ndarray, seconds: float,
                     stats: Optional[MHEStats] = None) -> None:
                failed = 0 if stats is None else stats.n_failed
                solve_ms = None if stats is None else 1e3 * stats.mean_solve_time
                cells.append(EstimatorCell(label, kind, noisy, metrics.smape(x, xhat).tolist(),
                                           seconds, n_samples, failed, solve_ms))
                say(f"{plant.name:8s} {'noisy' if noisy else 'clean'} {kind:9s} {label:22s} "
                    f"SMAPE {cells[-1].mean:6.2f} %  {cells[-1].ms_per_sample:7.3f} ms/sample"
                    + (f"  failed {failed}" if stats is not None else ""))

            kkl, kkl_seconds = _timed(lambda: observer.simulate(t, y, u).xhat)
            cell(kkl_label, kkl, kkl_seconds)
            ekf_xhat, seconds = _timed(lambda: ekf.simulate(t, y, u).xhat)
            cell("EKF", ekf_xhat, seconds)
            for n, mhe in mhes.items():
                run, seconds = _timed(lambda: mhe.simulate(t, y, u))
                cell(f"MHE N={n}", run.xhat, seconds, run.stats)
            run, seconds = _timed(lambda: primed.simulate(t, y, u, guide=kkl,
                                                          guide_std=profile[:t.size]))
            cell(f"KKL-primed MHE N={primed_horizon}", run.xhat, seconds + kkl_seconds, run.stats)
    return SystemComparison(plant.name, observer.method, protocol.n_trials, protocol.seed,
                            tuple(horizons), int(primed_horizon), int(calibration_trials),
                            tuple(cells))


def markdown_table(comparisons: Sequence[SystemComparison], kinds: Sequence[str] = KINDS) -> str:
    """Mean SMAPE (%) per cell, noise-free then noisy, and the time per sample of each estimator.

    ``ms/sample`` is the estimator's wall time over all cells divided by the samples estimated:
    the KKL observer and the EKF run whole trajectories as one CasADi ``mapaccum`` call
    (threads over trials), the MHE one ipopt call per sample. ``ipopt ms`` is the mean time of
    one MHE solve. ``failed`` counts the MHE solves whose estimate was the fallback.
    """
    head = (["system", "estimator"] + [f"{k} clean" for k in kinds] + [f"{k} noisy" for k in kinds]
            + ["ms/sample", "ipopt ms", "failed"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for comp in comparisons:
        for label in comp.estimators:
            mine = [c for c in comp.cells if c.estimator == label]
            row = [f"{comp.system} ({comp.n_trials} trials)", label]
            for noisy in (False, True):
                for kind in kinds:
                    match = [c for c in mine if c.kind == kind and c.noisy == noisy]
                    row.append(f"{match[0].mean:.1f}" if match else "")
            seconds = sum(c.seconds for c in mine)
            samples = sum(c.n_samples for c in mine)
            solves = [c.solve_ms for c in mine if c.solve_ms is not None]
            row += [f"{1e3 * seconds / samples:.3f}",
                    f"{np.mean(solves):.2f}" if solves else "-",
                    str(sum(c.failed for c in mine)) if solves else "-"]
            lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------------- command line
def _model_dir(root: Optional[str], system: str, method: str) -> Path:
    roots = ([Path(root)] if root else
             [Path.cwd() / "models", Path(__file__).resolve().parent.parent / "models"])
    for base in roots:
        if (base / system / method / "card.json").exists():
            return base / system / method
    raise SystemExit(f"error: no model {system}/{method} under {' or '.join(map(str, roots))}; "
                     "pass --models-root DIR")


def _load_all(out: Path) -> list[SystemComparison]:
    found = []
    for name in list(DEFAULT_METHODS) + [n for n in systems.names() if n not in DEFAULT_METHODS]:
        path = out / f"{name}.json"
        if path.exists():
            found.append(SystemComparison.from_json(json.loads(path.read_text())))
    return found


def cmd_compare(args: argparse.Namespace) -> int:
    """Run :func:`compare_system` for each ``--systems`` entry; write JSON and the table."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    methods = dict(DEFAULT_METHODS)
    for item in args.method or []:
        system, _, method = item.partition("=")
        if not method:
            raise SystemExit(f"error: --method expects SYSTEM=METHOD, received {item!r}")
        methods[system] = method
    noise = {"on": (True,), "off": (False,), "both": (False, True)}[args.noise]
    for name in args.systems:
        if name not in methods:
            raise SystemExit(f"error: no learned model chosen for {name!r}; pass --method "
                             f"{name}=METHOD")
        observer = load_observer(_model_dir(args.models_root, name, methods[name]))
        protocol = Protocol(n_trials=args.trials, T=args.T, seed=args.seed)
        log = (lambda line: print(line, file=sys.stderr, flush=True)) if not args.quiet else None
        comparison = compare_system(observer, protocol, horizons=tuple(args.horizons),
                                    primed_horizon=args.primed_horizon,
                                    calibration_trials=args.calibration_trials,
                                    kinds=tuple(args.kinds), noise=noise, log=log)
        (out / f"{name}.json").write_text(json.dumps(comparison.to_json(), indent=1))
        table = markdown_table(_load_all(out), tuple(args.kinds))
        (out / "table.md").write_text(table + "\n")
        print(markdown_table([comparison], tuple(args.kinds)))
    print(f"wrote {out}/", file=sys.stderr)
    return 0


def add_compare_parser(sub: Any) -> argparse.ArgumentParser:
    """Add the ``compare`` subcommand to a ``kklcasadi`` subparsers object; returns its parser."""
    c = sub.add_parser("compare", help="KKL observer vs EKF vs MHE vs KKL-primed MHE on the "
                                       "docs/protocol.md benchmark (SMAPE and time per sample)")
    c.add_argument("--systems", nargs="+", default=list(DEFAULT_METHODS), choices=systems.names())
    c.add_argument("--method", action="append", metavar="SYSTEM=METHOD",
                   help="learned observer per system (default: "
                        + ", ".join(f"{k}={v}" for k, v in DEFAULT_METHODS.items()) + ")")
    c.add_argument("--models-root", help="directory holding SYSTEM/METHOD model directories "
                                         "(default: ./models, else the source tree's)")
    c.add_argument("--trials", type=int, default=100)
    c.add_argument("--T", type=float, default=50.0, help="horizon in seconds (docs/protocol.md: 50)")
    c.add_argument("--seed", type=int, default=2026)
    c.add_argument("--noise", default="both", choices=("on", "off", "both"))
    c.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    c.add_argument("--horizons", nargs="+", type=int, default=[10, 30], help="MHE horizons N")
    c.add_argument("--primed-horizon", type=int, default=5, help="KKL-primed MHE horizon")
    c.add_argument("--calibration-trials", type=int, default=5,
                   help="runs per regime (seed + 1) calibrating the KKL error profile")
    c.add_argument("--out", default="results/estimators")
    c.add_argument("--quiet", action="store_true")
    c.set_defaults(func=cmd_compare)
    return c


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m kklcasadi.pipelines ...``: the ``compare`` subcommand on its own."""
    parser = argparse.ArgumentParser(prog="kklcasadi")
    add_compare_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
