"""An observer (and the EKF) over a recorded log, in one call: ``kklcasadi estimate`` from Python.

:func:`estimate_log` reads a CSV log onto the observer's grid (:func:`kklcasadi.plant.logs.read_log`:
columns by name, ``y`` sampled at the grid times, angle columns unwrapped and moved onto the branch
of the training domain, ``u`` zero-order hold or, from a faster log, averaged over each interval),
checks the outputs against the model's training domain, runs the observer from ``z = 0``,
optionally the EKF beside it with the model's noise levels, and scores both against recorded
states where the log has them (errors of angle states wrapped to ``(-pi, pi]``).
:meth:`LogEstimate.write` writes the estimates, the domain flags and the EKF's estimates as CSV.
The observer and the EKF run their compiled steps a chunk of samples per call
(:mod:`kklcasadi.evaluation.chunked`), so a log of millions of samples takes memory for its
estimates only; a log with a sample the guard holds or a step it restarts at
(:mod:`kklcasadi.observer.guard`) runs the guarded CasADi VM path instead.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np

from .. import metrics
from ..estimators.ekf import EKF
from ..observer.guard import SampleGuard, guarded_simulate, training_box
from ..observer.kkl import KKLObserver
from ..plant.envelope import output_ranges
from ..plant.logs import Log, read_log, write_estimates
from ..plant.systems import System
from ..provenance import Stamp
from ..validation import Text, error, nonnegative_number, state_stds
from .chunked import FAST, ChunkedEKF, ChunkedObserver
from .compiled import Compiler

__all__ = ["LogEstimate", "estimate_log", "read_plant_log", "ekf_for_model", "log_arguments", "check_inputs",
           "recorded_column", "score_table"]

@dataclass(frozen=True, eq=False)
class LogEstimate:
    """An observer run over a log, with the EKF beside it and the scores against the log's reference.

    Not a :class:`kklcasadi.estimate.Estimate` (the result of one estimator): a report on a log that holds
    the observer's estimate, the EKF's, the log itself, its reference and the scores.

    Attributes
    ----------
    log : Log
        The log on the observer's grid.
    t : numpy.ndarray, shape (N,)
        Grid times, in the log's clock.
    xhat : numpy.ndarray, shape (N, nx)
        The observer's estimates (``z(0) = 0``).
    z : numpy.ndarray, shape (N, nz)
    in_domain : numpy.ndarray of bool, shape (N,), or None
        The domain monitor (None when the model records no domain).
    status : numpy.ndarray of int8, shape (N,)
        The sample guard per sample (:func:`kklcasadi.observer.guard.guarded_simulate`): 0, or
        the sum of ``guard.HELD`` (1: the sample was not fed) and ``guard.RESTARTED`` (2: the
        observer restarted there).
    ekf : numpy.ndarray, shape (N, nx), or None
        The EKF's estimates, when it ran.
    ekf_noise : tuple of float or None
        ``(process_std, measurement_std)`` of that EKF (:meth:`kklcasadi.EKF.for_noise`), None for an
        EKF passed in or none.
    reference : dict
        ``{state index: column}``: the log's recorded states.
    scores : dict
        Per recorded state ``i``: ``{"column", "rmse", "rmse_ekf"}`` over ``t - t[0] >= settle``
        (``rmse_ekf`` None without the EKF); wrapped errors for the plant's angle states.
    settle : float
        Seconds from the start left out of the scores.
    """

    log: Log
    t: np.ndarray
    xhat: np.ndarray
    z: np.ndarray
    in_domain: Optional[np.ndarray]
    status: np.ndarray
    ekf: Optional[np.ndarray]
    ekf_noise: Optional[tuple]
    reference: dict
    scores: dict
    settle: float

    def write(self, path: str | os.PathLike, *, state_names: Optional[Sequence[str]] = None,
              stamp: Optional[Stamp] = None, overwrite: bool = False) -> Path:
        """Write ``time``, the estimates, ``in_domain`` (where recorded), ``status`` (the sample guard) and
        ``ekf_<state>`` columns (with the EKF) as CSV under a provenance line, atomically, over an existing file
        only with ``overwrite`` (:func:`kklcasadi.plant.logs.write_estimates`).

        Parameters
        ----------
        path : str or path-like
        state_names : sequence of str, optional
            Column names of the states; default ``x1 .. xn``.
        stamp : kklcasadi.provenance.Stamp, optional
            The file's provenance (default: this process's).
        """
        nx = self.xhat.shape[1]
        names = tuple(state_names) if state_names is not None else tuple(f"x{i + 1}" for i in range(nx))
        extra = None if self.ekf is None else {f"ekf_{name}": self.ekf[:, i] for i, name in enumerate(names)}
        return write_estimates(path, self.t, self.xhat, state_names=names, in_domain=self.in_domain,
                               status=self.status, extra=extra, stamp=stamp, overwrite=overwrite)

    def table(self, state_names: Optional[Sequence[str]] = None) -> str:
        """The scores as a few lines of text (one per recorded state)."""
        return score_table(self.scores, self.settle, state_names)


def score_table(scores: dict, settle: float, state_names: Optional[Sequence[str]] = None) -> str:
    """Scores ``{state index: {"column", "rmse", "rmse_ekf"}}`` as a few lines of text (one per recorded state)."""
    if not scores:
        return "no recorded states to score against (reference columns)"
    lines = [f"RMSE for t >= {settle:g} s after the start (angle states wrapped):"]
    for i, s in scores.items():
        name = state_names[i] if state_names is not None else f"x{i + 1}"
        ekf = "" if s["rmse_ekf"] is None else f"   EKF {s['rmse_ekf']:.4g}"
        lines.append(f"  {name:<12s} against {s['column']!r}: KKL {s['rmse']:.4g}{ekf}")
    return "\n".join(lines)


def _reference_columns(reference_cols: Sequence[Optional[str]], nx: int) -> dict:
    if isinstance(reference_cols, str) or not isinstance(reference_cols, (list, tuple)):
        raise error("reference_cols", "a sequence of nx column names (None for a state without one)",
                    Text(type(reference_cols).__name__), kind=TypeError)
    if reference_cols and len(reference_cols) != nx:
        raise error("reference_cols", f"{nx} entries, one per state in order (None for a state the log does not "
                    "record)", list(reference_cols))
    return {i: name for i, name in enumerate(reference_cols) if name is not None}


def read_plant_log(path: str | os.PathLike, observer: KKLObserver, *, time_col: str, y_cols: Sequence[str],
                   u_cols: Sequence[str] = (), u_zero: bool = False, reference_cols: Sequence[Optional[str]] = (),
                   angle_cols: Optional[Sequence[str]] = None, t0: Optional[float] = None,
                   max_dt_ratio: float = 1.5, range_check: bool = True) -> tuple[Log, dict]:
    """A log on ``observer``'s grid, checked against its plant and its training domain.

    The outputs' plausible ranges are those of ``h`` over the states the model was trained on
    (:func:`training_box`: the card's recorded domain, else the plant's X0 box; :func:`output_ranges`):
    a logged output more than 10 % of its range outside is an error naming its row and column
    (``range_check=False`` skips the test), and an angle is moved onto the branch of that range.
    Angle columns default to the ``y_cols`` of the plant's ``angle_outputs`` and the
    ``reference_cols`` of its ``angle_states``.

    Parameters
    ----------
    path, time_col, y_cols, t0, max_dt_ratio
        See :func:`kklcasadi.plant.logs.read_log`; ``y_cols`` in the plant's output order.
    observer : KKLObserver
    u_cols : sequence of str
        The plant's inputs, in order: required for a plant with inputs unless ``u_zero``.
    u_zero : bool
        The plant's input was zero throughout the log (no ``u_cols``).
    reference_cols : sequence of str or None
        ``nx`` entries in state order: the column of each recorded state, None for the others.
    angle_cols : sequence of str, optional
    range_check : bool
        Refuse outputs outside the training domain's range (default).

    Returns
    -------
    Log
    dict
        ``{state index: column}`` of the reference columns.
    """
    arguments, reference = log_arguments(observer, time_col=time_col, y_cols=y_cols, u_cols=u_cols, u_zero=u_zero,
                                         reference_cols=reference_cols, angle_cols=angle_cols,
                                         max_dt_ratio=max_dt_ratio, range_check=range_check)
    return read_log(path, t0=t0, **arguments), reference


def log_arguments(observer: KKLObserver, *, time_col: str, y_cols: Sequence[str], u_cols: Sequence[str] = (),
                  u_zero: bool = False, reference_cols: Sequence[Optional[str]] = (),
                  angle_cols: Optional[Sequence[str]] = None, max_dt_ratio: float = 1.5,
                  range_check: bool = True) -> tuple[dict, dict]:
    """:func:`read_plant_log`'s arguments checked against ``observer``: the keyword arguments of
    :func:`~kklcasadi.plant.logs.read_log` but the path and ``t0``, and ``{state index: column}`` of the
    reference columns."""
    plant = observer.system
    y_cols = tuple(y_cols)
    if len(y_cols) != plant.ny:
        raise error("y_cols", f"{plant.ny} columns (the outputs of {plant.name!r}, in order)", list(y_cols))
    check_inputs(plant, len(u_cols), u_zero)
    if u_cols and len(u_cols) != plant.nu:
        raise error("u_cols", f"{plant.nu} columns (the inputs of {plant.name!r}, in order)", list(u_cols))
    if not isinstance(range_check, bool):
        raise error("range_check", "a bool", Text(type(range_check).__name__), kind=TypeError)
    reference = _reference_columns(reference_cols, plant.nx)
    extra = tuple(dict.fromkeys(name for name in reference.values() if name not in y_cols))  # others are y's
    if angle_cols is None:
        angle_cols = ([y_cols[j] for j in plant.angle_outputs]
                      + [name for i, name in reference.items() if i in plant.angle_states and name in extra])
    angle_cols = tuple(dict.fromkeys(angle_cols))
    ranges = output_ranges(plant, training_box(observer))
    box = {name: tuple(ranges[j]) for j, name in enumerate(y_cols)
           if ranges[j, 1] > ranges[j, 0] and (range_check or name in angle_cols)}
    return dict(time_col=time_col, y_cols=y_cols, u_cols=tuple(u_cols), reference_cols=extra, dt=observer.dt,
                angle_cols=angle_cols, max_dt_ratio=max_dt_ratio, box=box,
                box_margin=0.1 if range_check else math.inf), reference


def check_inputs(plant: System, n_columns: int, u_zero: bool) -> None:
    """A plant with inputs needs their columns, or ``u_zero`` saying the input was zero."""
    if not isinstance(u_zero, bool):
        raise error("u_zero", "a bool", Text(type(u_zero).__name__), kind=TypeError)
    if n_columns and u_zero:
        raise error("u_zero", "False with u_cols (the inputs are either logged or zero)", True)
    if plant.nu and not n_columns and not u_zero:
        raise error("u_cols", f"{plant.nu} column(s) (the inputs of {plant.name!r}, in order)", Text("none"),
                    "Name the logged inputs, or pass u_zero=True if the input was zero throughout the log.")


def ekf_for_model(observer: KKLObserver, *, process_std: Optional[float | Sequence[float]] = None,
                  measurement_std: Optional[float] = None) -> tuple[EKF, tuple]:
    """The EKF for the model's noise (:meth:`kklcasadi.EKF.for_noise`): the card's levels unless given.

    Raises
    ------
    ValueError
        A level neither given nor recorded in the card (cards record ``process_std`` for methods
        trained on noisy runs).
    """
    spec = observer.model.spec
    if process_std is None:
        if spec.process_std is None:
            raise error("process_std", "the process-noise level of the EKF", Text("none given, and the card records "
                        "none"), "Pass it (kklcasadi estimate --process-std).")
        process_std = spec.process_std
    if measurement_std is None:
        if spec.measurement_std <= 0:
            raise error("measurement_std", "the measurement-noise level of the EKF", Text("none given, and the card "
                        "records 0"), "Pass it (kklcasadi estimate --measurement-std).")
        measurement_std = spec.measurement_std
    levels = (state_stds(process_std, observer.nx), nonnegative_number(measurement_std, "measurement_std"))
    return EKF.for_noise(observer.system, observer.dt, process_std=levels[0], measurement_std=levels[1]), levels


def _recorded(log: Log, name: str) -> np.ndarray:
    """The column ``name`` of a log on its grid, (N,): a reference column, or a measured output."""
    key, j = recorded_column(log.columns, name)
    return (log.reference if key == "reference" else log.y)[:, j]


def recorded_column(columns: dict, name: str) -> tuple[str, int]:
    """Where a log's column ``name`` is: ``("reference", j)``, or ``("y", j)`` for a measured output (``columns``
    as :attr:`Log.columns`)."""
    for key in ("reference", "y"):
        if name in columns[key]:
            return key, columns[key].index(name)
    raise error("reference", f"columns of the log {list(columns['y'] + columns['reference'])}", name)


def estimate_log(observer: KKLObserver, log: Union[Log, str, os.PathLike], *, time_col: str = "time",
                 y_cols: Sequence[str] = (), u_cols: Sequence[str] = (), u_zero: bool = False,
                 reference_cols: Sequence[Optional[str]] = (), angle_cols: Optional[Sequence[str]] = None,
                 range_check: bool = True, ekf: Union[bool, EKF] = False, process_std: Optional[float] = None,
                 measurement_std: Optional[float] = None, settle: float = 0.0,
                 reference: Optional[dict] = None, compiler: Optional[Compiler] = FAST,
                 progress: bool = False) -> LogEstimate:
    """Run ``observer`` (and the EKF) over a recorded log and score it against recorded states.

    Parameters
    ----------
    observer : KKLObserver
    log : Log or path
        A log already on the observer's grid (:func:`read_plant_log`; then ``reference`` maps
        state indices to its reference columns), or a CSV file read with the column arguments.
    time_col, y_cols, u_cols, u_zero, angle_cols, range_check
        See :func:`read_plant_log`: a plant with inputs needs ``u_cols``, or ``u_zero=True`` for a
        log taken at ``u = 0`` (also for a ``Log`` without inputs).
    reference_cols : sequence of str or None
        ``nx`` entries in state order: the column of each recorded state, None for the others (a
        measured output's column may be one: the angles of a pendulum are states and outputs).
    ekf : bool or EKF
        Run an EKF beside the observer: True for :func:`ekf_for_model` (the card's noise levels,
        or ``process_std``/``measurement_std``), or an :class:`~kklcasadi.EKF` to use as it is.
    settle : float
        Seconds from the start left out of the scores.
    compiler : Compiler or None
        How the observer and the EKF run: their steps compiled, a chunk of samples per call
        (:mod:`kklcasadi.evaluation.chunked`: memory independent of the log's length); default
        :data:`~kklcasadi.evaluation.chunked.FAST` (within 1e-14 per step of the VM),
        :data:`~kklcasadi.evaluation.chunked.BITWISE` for :meth:`KKLObserver.simulate`'s values bit for
        bit; None, or no C compiler on the machine (a :class:`~kklcasadi.evaluation.compiled.CompilerWarning`),
        the CasADi VM, chunked the same way.
    progress : bool
        Progress bars over the samples (tqdm).

    Returns
    -------
    LogEstimate
    """
    plant = observer.system
    if isinstance(log, Log):
        reference = {} if reference is None else dict(reference)
        if log.y.shape[1] != plant.ny:
            raise error("log", f"a log of {plant.ny} outputs", Text(f"{log.y.shape[1]} outputs"))
        check_inputs(plant, log.u.shape[1], u_zero)
        if log.u.shape[1] not in (0, plant.nu):
            raise error("log", f"a log of {plant.nu} inputs", Text(f"{log.u.shape[1]} inputs"))
    else:
        log, reference = read_plant_log(log, observer, time_col=time_col, y_cols=y_cols, u_cols=u_cols,
                                        u_zero=u_zero, reference_cols=reference_cols, angle_cols=angle_cols,
                                        range_check=range_check)
    settle = nonnegative_number(settle, "settle")
    u = log.u if log.u.shape[1] else np.zeros((log.t.size, plant.nu))
    if ekf is not True and ekf is not False and not isinstance(ekf, EKF):
        raise error("ekf", "True, False or a kklcasadi.EKF", Text(type(ekf).__name__), kind=TypeError)
    guard = SampleGuard.of(observer)
    clean = bool(guard.accepts(log.y, u).all())
    if clean:                                 # the compiled chunks; the guard's rule would change nothing
        xhat, z, in_domain = ChunkedObserver(observer, compiler=compiler).estimate(log.y, u, progress=progress)
        clean = bool(guard.keeps(z, xhat).all())
    if clean:
        status = np.zeros(log.t.size, dtype=np.int8)
    else:                                     # held samples or restarts: the guarded run (CasADi VM)
        est, status = guarded_simulate(observer, log.t, log.y, u, guard=guard)
        xhat, z, in_domain = est.xhat, est.z, est.in_domain
    ekf_xhat, noise = None, None
    if ekf is True:
        ekf, noise = ekf_for_model(observer, process_std=process_std, measurement_std=measurement_std)
    if isinstance(ekf, EKF):
        ekf_xhat = (ChunkedEKF(ekf, compiler=compiler).run(log.y, u, progress=progress)[0] if clean
                    else ekf.simulate(log.t, log.y, u).xhat)
    for array in (xhat, z, in_domain, status, ekf_xhat):
        if array is not None:
            array.setflags(write=False)
    keep = log.t - log.t[0] >= settle
    if reference and not keep.any():
        raise error("settle", f"less than the log's {log.t[-1] - log.t[0]:.6g} s", settle)
    scores = {}
    for i, name in reference.items():
        recorded = _recorded(log, name)[keep, None]
        wrap = (0,) if i in plant.angle_states else ()
        scores[i] = {"column": name, "rmse": float(metrics.rmse(recorded, xhat[keep, i:i + 1], angles=wrap)),
                     "rmse_ekf": None if ekf_xhat is None else float(metrics.rmse(recorded, ekf_xhat[keep, i:i + 1],
                                                                                  angles=wrap))}
    return LogEstimate(log, log.t, xhat, z, in_domain, status, ekf_xhat, noise, reference, scores, settle)
