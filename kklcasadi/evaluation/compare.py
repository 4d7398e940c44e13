"""The estimator comparison of docs/protocol.md: learned KKL observer, EKF, MHE and KKL-primed MHE.

:func:`compare_system` scores every estimator on the same protocol trials of one system (four
input regimes, noise off and on) and times each in the same run; the table is
:func:`kklcasadi.evaluation.report.markdown_table` with ``timing=True``: the mean SMAPE per cell and
the computation time per sample.

Command line: ``kklcasadi compare --systems duffing vdp --trials 20 --out results/estimators/all``.
Each system's scores go to ``OUT/<system>.json``; the table of every system found in ``OUT`` is
rewritten to ``OUT/table.md`` after each system, so systems can run in separate processes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence

import numpy as np

from .. import metrics, provenance
from ..estimators.ekf import EKF
from ..estimators.kkl_mhe import kkl_error_profile
from ..estimators.mhe import MHE, MHEStats
from ..observer.kkl import KKLObserver
from ..plant import signals as sig
from ..plant.rk4 import substeps_for
from .protocol import CellResult, Protocol
from .report import MethodScores

__all__ = ["SystemComparison", "compare_system", "MHE_SUBSTEPS"]

#: RK4 steps per sample interval in the MHE model on the paper's plants (the others get the stable count,
#: :func:`kklcasadi.plant.rk4.substeps_for`): FitzHugh-Nagumo is stiff at the box edge.
MHE_SUBSTEPS = {"fhn": 4}


@dataclass(frozen=True)
class SystemComparison:
    """All estimators on one system, with the settings that produced them.

    ``scores`` holds one :class:`~kklcasadi.evaluation.report.MethodScores` per estimator, in
    table order; every cell is timed (``seconds``, ``n_samples``; MHE: ``failed``, ``solve_ms``).
    """

    system: str
    method: str
    n_trials: int
    seed: int
    horizons: tuple
    primed_horizon: int
    calibration_trials: int
    scores: tuple = ()

    def to_json(self) -> dict:
        settings = {name: getattr(self, name) for name in ("system", "method", "n_trials", "seed", "primed_horizon",
                                                             "calibration_trials")}
        cells = [{"estimator": s.label, "kind": kind, "noisy": noisy, "smape": c.smape.tolist(),
                  "rmse_after": c.rmse_after.tolist(), "seconds": c.seconds, "n_samples": c.n_samples,
                  "failed": c.failed, "solve_ms": c.solve_ms, "escaped": c.escaped}
                 for s in self.scores for (noisy, kind), c in s.results.items()]
        return {**settings, "horizons": list(self.horizons), "cells": cells}

    @classmethod
    def from_json(cls, data: dict) -> SystemComparison:
        """Read :meth:`to_json`'s record, stamped (``kklcasadi compare``'s file) or not (records written before
        ``rmse_after`` was kept read as NaN, before ``escaped`` was kept as 0)."""
        data = provenance.json_payload(data)
        results: dict[str, dict] = {}
        for c in data["cells"]:
            smape = np.asarray(c["smape"], dtype=float)
            rmse = np.asarray(c.get("rmse_after", np.full(smape.shape, np.nan)), dtype=float)
            results.setdefault(c["estimator"], {})[(c["noisy"], c["kind"])] = CellResult(
                data["system"], c["kind"], c["noisy"], smape, rmse, c["seconds"], c["n_samples"], c["failed"],
                c["solve_ms"], c.get("escaped", 0))
        scores = tuple(MethodScores(label, data["system"], cells) for label, cells in results.items())
        settings = {k: v for k, v in data.items() if k not in ("cells", "horizons")}
        return cls(**settings, horizons=tuple(data["horizons"]), scores=scores)


def _timed(run: Callable[[], Any]) -> tuple[Any, float]:
    start = time.perf_counter()
    out = run()
    return out, time.perf_counter() - start


def compare_system(observer: KKLObserver, protocol: Protocol, *, horizons: Sequence[int] = (10, 30),
                   primed_horizon: int = 5, calibration_trials: int = 5,
                   kinds: Sequence[str] = sig.BENCHMARK_KINDS, noise: Sequence[bool] = (False, True),
                   log: Optional[Callable[[str], None]] = None, ekf: Optional[EKF] = None) -> SystemComparison:
    """Score the observer, the EKF, MHE (each horizon) and the KKL-primed MHE on one system.

    Every estimator sees the same trials (``protocol.trials``); noise-free cells use
    ``protocol.noise_free()``. The KKL-primed MHE is primed by ``observer``, with the error
    profile calibrated (:func:`kklcasadi.estimators.kkl_mhe.kkl_error_profile`) on ``calibration_trials`` runs
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
    ekf : EKF, optional
        The EKF beside the observer; default ``EKF(system, dt)`` (docs/protocol.md's noise levels).

    Returns
    -------
    SystemComparison
    """
    if not isinstance(observer, KKLObserver):
        raise TypeError(f"observer: expected a KKLObserver, received {type(observer).__name__}.")
    if not isinstance(protocol, Protocol):
        raise TypeError(f"protocol: expected a kklcasadi.evaluation.protocol.Protocol, received "
                        f"{type(protocol).__name__}.")
    plant, dt = observer.system, observer.dt
    if abs(protocol.dt - dt) > 1e-12:
        raise ValueError(f"protocol: its dt = {protocol.dt} differs from the observer's dt = {dt}.")
    say = log or (lambda _line: None)
    substeps = substeps_for(plant, dt, MHE_SUBSTEPS)
    ekf = EKF(plant, dt) if ekf is None else ekf
    kkl_label = f"KKL ({observer.method})"
    results: dict[str, dict] = {}
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
                rmse = (metrics.rmse_after(t, x, xhat, prot.t_settle) if t[-1] >= prot.t_settle
                        else np.full(x.shape[0], np.nan))              # a run shorter than the settle time
                result = CellResult(plant.name, kind, noisy, metrics.smape(x, xhat), rmse, seconds, n_samples,
                                    failed, solve_ms, int((~batch.ok).sum()))
                results.setdefault(label, {})[(noisy, kind)] = result
                say(f"{plant.name:8s} {'noisy' if noisy else 'clean'} {kind:9s} {label:22s} "
                    f"SMAPE {result.summary.mean:6.2f} %  {1e3 * seconds / n_samples:7.3f} ms/sample"
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
                            tuple(MethodScores(label, plant.name, cells) for label, cells in results.items()))
