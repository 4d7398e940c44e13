"""The ``bank`` decoder's samples of the operational runs, and what is calibrated on them (no torch).

The observer runs on the noisy operational runs of :mod:`kklcasadi.plant.runs` (``z(0) = 0`` as in the
benchmark), and the decoder is fitted to the true states along those runs (:mod:`kklcasadi.train.decoder`).
For the linear filter-bank latent of :mod:`kklcasadi.model.variants.filterbank` the latent trajectory does
not depend on the decoder, so one pass suffices. The latent is run over each chunk of runs at the model's
``dt``, and the decoder keeps samples at fixed times (every ``dense_period`` seconds over the first
``dense_time``, every ``sample_period`` after), so the data and the fit cost about the same at any sample
time. None of a cut run's samples from its escape on is used, and the record counts the cut runs.

* :func:`operational_data` -- the decoder's samples of the noisy runs (CasADi and numpy).
* :func:`nominal_runs` -- the runs at the nominal noise that set an ensemble's spread threshold.
* :func:`bank_monitor` -- the decoder-input domain monitor calibrated on the samples.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Callable, Optional, Sequence

import numpy as np

from ..plant.runs import RolloutConfig, _chunks, _horizon, _keep, drifting_states, resolved
from ..plant.simulate import TrajectoryBatch, time_grid
from ..plant.systems import System
from ..validation import Text, error, nonnegative_int, positive_int
from .monitor import DEFAULT_QUANTILE, DEFAULT_SPREAD_QUANTILE, FeatureMonitor, calibrate, with_spread
from .variants import BankSpec
from .variants import bankdecoder as bd
from .variants import filterbank as fb
from .variants.copies import ModelCopies
from .variants.ekfblock import EKFBlock

__all__ = ["OperationalData", "operational_data", "MonitorConfig", "bank_monitor", "member_spread", "nominal_runs",
           "SPREAD_SEED_OFFSET"]

#: Added to the training seed for the runs that set the spread threshold (:func:`nominal_runs`), so that
#: none of their draws is a fitting run's.
SPREAD_SEED_OFFSET = 7919


@dataclass(frozen=True)
class MonitorConfig:
    """How a ``bank``'s decoder-input domain monitor is calibrated (:func:`bank_monitor`).

    Attributes
    ----------
    quantile : float
        Share of the fitting runs' validation samples (after the settle time) inside the prototype
        threshold.
    spread_quantile : float
        Share of the spread-calibration samples inside the ensemble's spread threshold (a decoder
        ensemble only).
    spread_runs : int
        Runs of the recipe at the card's nominal noise (:func:`nominal_runs`) whose samples after the
        settle time set the spread threshold; 0: the fitting runs' validation samples, whose noise
        levels range over ``rollouts.noise_range``. The members disagree more on noisier runs, so a
        threshold from the broad noise range sits above the spread of the nominal level and flags
        less of what the observer does badly at it (docs/design.md, "Ensembles").
    """

    quantile: float = DEFAULT_QUANTILE
    spread_quantile: float = DEFAULT_SPREAD_QUANTILE
    spread_runs: int = 400

    def __post_init__(self) -> None:
        for name in ("quantile", "spread_quantile"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 < value < 1):
                raise error(name, "a share in (0, 1)", value)
        nonnegative_int(self.spread_runs, "spread_runs", "Give the runs at the nominal noise that set the spread "
                        "threshold, or 0 for the fitting runs' validation samples.")


@dataclass(frozen=True, eq=False)
class OperationalData:
    """The decoder's samples of the operational runs.

    Attributes
    ----------
    z : numpy.ndarray, shape (S, nz)
        The bank's latent at the kept samples (from ``z = 0`` at each run's start).
    y : numpy.ndarray, shape (S, ny)
    u : numpy.ndarray, shape (S, nu)
    x : numpy.ndarray, shape (S, nx)
        The true states there.
    t : numpy.ndarray, shape (S,)
        Each sample's time from its run's start (seconds).
    run : numpy.ndarray, shape (S,)
        Each sample's run (int, ascending: the samples are ordered run by run).
    record : dict
        ``runs`` simulated, ``cut`` (runs that escaped and were cut there), ``failed`` (of them, the
        ones that blew up or that the integrator failed on), ``samples`` kept, ``simulated_s`` (seconds simulated), the
        per-run noise factors' range, ``substeps`` and ``seconds`` (wall time).
    """

    z: np.ndarray
    y: np.ndarray
    u: np.ndarray
    x: np.ndarray
    t: np.ndarray
    run: np.ndarray
    record: dict

    def __len__(self) -> int:
        return len(self.x)

    @classmethod
    def from_runs(cls, bank: fb.FilterBank, runs: TrajectoryBatch, config: RolloutConfig, *,
                  copies: ModelCopies | None = None, ekf: EKFBlock | None = None) -> OperationalData:
        """The samples of given runs (all of each run valid), kept at ``config``'s sample times; ``copies``
        (the latent's model copies, if any) follow the filters in ``z``, then ``ekf`` (its augmented EKF block)."""
        dt = float(runs.t[1] - runs.t[0])
        keep = _keep(runs.t.size, dt, config)
        z = fb.latent_run(bank, runs.y, runs.u, dt, copies=copies, ekf=ekf)[:, keep]
        nz, ny, nu, nx = z.shape[2], runs.y.shape[2], runs.u.shape[2], runs.x.shape[2]
        record = {"runs": len(runs), "cut": 0, "failed": 0, "samples": int(keep.sum() * len(runs)),
                  "simulated_s": float(len(runs) * runs.t.size * dt)}
        shape = (len(runs), int(keep.sum()))
        return cls(z.reshape(-1, nz), runs.y[:, keep].reshape(-1, ny), runs.u[:, keep].reshape(-1, nu),
                   runs.x[:, keep].reshape(-1, nx), np.broadcast_to(runs.t[keep], shape).ravel(),
                   np.broadcast_to(np.arange(len(runs))[:, None], shape).ravel(), record)


def operational_data(system: System, bank: fb.FilterBank, config: RolloutConfig, seed: int, *, dt: float,
                     measurement_std: float, process_std: float | Sequence[float] = 0.0, time_scale: float = 1.0,
                     copies: ModelCopies | None = None, ekf: EKFBlock | None = None,
                     progress: bool = False) -> OperationalData:
    """Simulate the operational runs and keep the decoder's samples of them.

    Parameters
    ----------
    system : System
    bank : FilterBank
        The observer's latent, run over each run from ``z = 0``.
    config : RolloutConfig
    seed : int
        Seeds the initial states (Latin hypercube), the input parameters and the noise.
    dt : float
        The model's sample period.
    measurement_std : float
        Measurement-noise std (nominal; times the per-run factor of ``config.noise_range``).
    process_std : float or sequence of float (nx,)
        Process-noise std added to ``xdot`` (one for all states or one per state).
    time_scale : float
        The rate (rad/s) ``config``'s times are in units of (``T`` seconds at 1): its horizon and
        sample times are divided by it, the inputs' frequencies multiplied.
    copies : ModelCopies or None
        The latent's model copies of the plant (:mod:`kklcasadi.model.variants.copies`), run over each run
        after the filters (their latents follow the bank's in ``z``).
    ekf : EKFBlock or None
        The latent's augmented EKF block (:mod:`kklcasadi.model.variants.ekfblock`), last in ``z``.
    progress : bool
        A progress bar over the runs.

    Returns
    -------
    OperationalData
        Every run's samples before its escape (if any).
    """
    t0 = time.perf_counter()
    plan = resolved(system, config)
    n = time_grid(_horizon(config.T, time_scale, dt), dt).size
    keep = _keep(n, dt, plan, time_scale)
    parts: dict[str, list[np.ndarray]] = {"z": [], "y": [], "u": [], "x": [], "t": [], "run": []}
    first = 0
    cut = failed = 0
    factors: list[float] = []
    substeps = 0
    cut_by_kind: dict[str, list[int]] = {}
    models: dict[str, int] = {}
    drawn: list[np.ndarray] = []
    for batch, escape, noise in _chunks(system, config, seed, dt, measurement_std, process_std, time_scale, progress,
                                        "operational runs"):
        cut += int(np.sum(escape < n))
        for kind, left in zip(noise["kinds"], escape):
            tally = cut_by_kind.setdefault(kind, [0, 0])
            tally[0] += 1
            tally[1] += int(left < n)
        failed += int(np.sum(~np.all(np.isfinite(batch.x), axis=(1, 2))))
        factors.extend(noise["measurement"].tolist())
        substeps = noise["substeps"]
        for name in noise["noise_models"]:
            models[name] = models.get(name, 0) + 1
        if noise["params"] is not None:
            drawn.append(noise["params"])
        valid = np.arange(n)[None, :] < escape[:, None]
        y = np.where(valid[..., None], batch.y, 0.0)          # after an escape: ignored, kept finite
        u = np.where(valid[..., None], batch.u, 0.0)
        z = fb.latent_run(bank, y, u, dt, copies=copies, ekf=ekf)
        mask = valid & keep[None, :]
        runs = np.broadcast_to(np.arange(first, first + len(escape))[:, None], mask.shape)
        first += len(escape)
        for name, arr in (("z", z), ("y", y), ("u", u), ("x", np.asarray(batch.x)),
                          ("t", np.broadcast_to(batch.t, mask.shape)), ("run", runs)):
            parts[name].append(arr[mask])
    data = {k: np.concatenate(v) for k, v in parts.items()}
    record = {"runs": config.n_traj, "cut": cut, "failed": failed, "samples": int(len(data["x"])),
              "horizon_s": n * dt, "simulated_s": float(config.n_traj * n * dt),
              "sample_period_s": config.sample_period / time_scale, "substeps": substeps,
              "measurement_factor_range": [float(min(factors)), float(max(factors))],
              "escape_scale": float(plan.escape_scale), "stabilised": bool(plan.stabilise),
              "drifting_states": list(drifting_states(system)),
              "kinds": {kind: {"runs": runs_, "cut": cut_} for kind, (runs_, cut_) in cut_by_kind.items()},
              "noise_models": models, "seconds": round(time.perf_counter() - t0, 2)}
    if drawn:
        values = np.concatenate(drawn)
        record["params"] = {"names": list(system.param_names), "box": system.param_box.tolist(),
                            "nominal": system.param_nominal.tolist(),
                            "draw": f"a Latin hypercube over the box, one value per run (default_rng([{seed}, 7]))",
                            "drawn_range": [values.min(axis=0).tolist(), values.max(axis=0).tolist()]}
    return OperationalData(data["z"], data["y"], data["u"], data["x"], data["t"], data["run"], record)


def _settled(data: OperationalData, settle_time: float) -> tuple[np.ndarray, float]:
    """The samples of ``data`` at or after ``settle_time`` (S,) of bool, and the settle time used: 0 (all
    samples) where the runs end before it."""
    if len(data) and data.t.max() < settle_time:
        settle_time = 0.0
    return data.t >= settle_time, settle_time


def bank_monitor(data: OperationalData, seed: int, *, source: str = "the decoder's fitting runs",
                 validation_share: float = 0.2, settle_time: float = 5.0,
                 spread: Optional[Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]] = None,
                 spread_data: Optional[OperationalData] = None, spread_source: str = "",
                 quantile: float = DEFAULT_QUANTILE, spread_quantile: float = DEFAULT_SPREAD_QUANTILE
                 ) -> FeatureMonitor:
    """The decoder-input domain monitor calibrated on the decoder's samples (:func:`kklcasadi.model.monitor.calibrate`).

    The features are the decoder's input ``[z_k; y_k; u_k]`` (the observer's ``[z; vec(w)]``); the
    first runs give the prototypes and the metric, the samples after ``settle_time`` of the last
    ``validation_share`` of the runs the threshold (all their samples where the runs are shorter).
    ``spread`` (:func:`member_spread`: samples ``(z, y, u)`` to the members' spread of a decoder
    ensemble) adds the spread test (:func:`kklcasadi.model.monitor.with_spread`), its threshold from the
    samples after ``settle_time`` of ``spread_data`` (:func:`nominal_runs`; described by
    ``spread_source`` in the card), or from the same validation samples where it is None. ``quantile``
    and ``spread_quantile`` are the shares of those samples inside the two thresholds. ``source`` is
    recorded in the card's ``monitor.calibration``.
    """
    features = bd.decoder_features(data.z, data.y, data.u)
    n_runs = int(data.run.max()) + 1 if len(data) else 0
    if n_runs < 2:
        raise error("data", "samples of at least 2 runs (the monitor's threshold comes from runs it was not fit on)",
                    Text(f"{n_runs} runs"))
    first_val = n_runs - max(1, int(round(validation_share * n_runs)))
    after, settle_time = _settled(data, settle_time)
    fit = features[data.run < first_val]
    held = (data.run >= first_val) & after
    monitor = calibrate(fit, features[held], quantile=quantile, settle_time=settle_time, seed=seed,
                        calibration={"source": source, "fit_runs": first_val, "validation_runs": n_runs - first_val})
    if spread is None:
        return monitor
    if spread_data is None:
        return with_spread(monitor, spread(data.z[held], data.y[held], data.u[held]), quantile=spread_quantile,
                           source="the validation samples")
    if not len(spread_data):
        raise error("spread_data", "samples of the runs that set the spread threshold", Text("none"))
    pick, _ = _settled(spread_data, settle_time)
    return with_spread(monitor, spread(spread_data.z[pick], spread_data.y[pick], spread_data.u[pick]),
                       quantile=spread_quantile, source=spread_source or "runs given to bank_monitor")


def nominal_runs(system: System, bank: fb.FilterBank, rollouts: RolloutConfig, n_runs: int, seed: int, *, dt: float,
                 measurement_std: float, process_std: np.ndarray, time_scale: float,
                 copies: Optional[ModelCopies] = None, ekf: Optional[EKFBlock] = None,
                 progress: bool = False) -> tuple[OperationalData, str]:
    """The runs that set a ``bank``'s spread threshold: ``n_runs`` runs of the recipe ``rollouts`` at the
    nominal noise levels (factors 1), seeded ``seed + SPREAD_SEED_OFFSET``, and their description for the card.

    ``seed`` is the training seed; the other arguments are those of
    :func:`kklcasadi.model.operational.operational_data` for the fitting runs.
    """
    nominal = replace(rollouts, n_traj=positive_int(n_runs, "n_runs"), noise_range=(1.0, 1.0))
    data = operational_data(system, bank, nominal, seed + SPREAD_SEED_OFFSET, dt=dt, measurement_std=measurement_std,
                            process_std=process_std, time_scale=time_scale, copies=copies, ekf=ekf,
                            progress=progress)
    return data, (f"{n_runs} runs of the fitting recipe at the nominal noise (factor 1), seed "
                  f"{seed + SPREAD_SEED_OFFSET}")


def member_spread(arrays: dict, bank: fb.FilterBank, spec: BankSpec, *,
                  chunk: int = 65536) -> Optional[Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]]:
    """The ensemble's spread as a function of samples ``(z (S, nz), y (S, ny), u (S, nu)) -> (S,)``,
    evaluated ``chunk`` samples at a time (None for a single decoder)."""
    if spec.members < 2:
        return None
    full, decoder = {**arrays, **fb.bank_arrays(bank)}, spec.decoder_spec

    def spread(z: np.ndarray, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.concatenate([bd.spread(decoder, full, z[i:i + chunk], y[i:i + chunk], u[i:i + chunk])
                               for i in range(0, len(z), chunk)] or [np.empty(0)])

    return spread
