"""``kklcasadi estimate`` on a log of any length: read, estimated and written a block of samples at a time.

:func:`estimate_streamed` reads the log once into a binary copy (:func:`kklcasadi.plant.logstream.scan_log`),
then per block of the grid (:data:`~kklcasadi.plant.logstream.BLOCK` samples) runs the observer and the EKF
through their compiled steps, their states carried from block to block
(:meth:`~kklcasadi.evaluation.chunked.ChunkedObserver.advance`), adds the block's squared errors to the
scores and appends its estimates to the output file (:class:`~kklcasadi.plant.logs.EstimatesWriter`: a
temporary file that replaces ``out`` at the end). The memory is that of a block, whatever the log's length;
the estimates are :func:`~kklcasadi.evaluation.logged.estimate_log`'s bit for bit, the scores the same up to
the rounding of their sums (a block at a time).

It returns None, having written nothing, where the log must be read whole (:func:`scan_log` says so: a faster log,
or one :func:`~kklcasadi.plant.logs.read_log` refuses, which then raises its error) or where the sample guard
would hold a sample or restart the observer (:mod:`kklcasadi.observer.guard`: the guarded run is the CasADi VM's,
over the whole log): the caller then runs :func:`~kklcasadi.evaluation.logged.estimate_log`.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
from tqdm.auto import tqdm

from .. import metrics
from ..estimators.ekf import EKF
from ..observer.guard import SampleGuard
from ..observer.kkl import KKLObserver
from ..plant.logs import EstimatesWriter, Resampling
from ..plant.logstream import scan_log
from ..provenance import Stamp
from ..validation import Text, error, nonnegative_number
from .chunked import FAST, ChunkedEKF, ChunkedObserver
from .compiled import Compiler
from .logged import ekf_for_model, log_arguments, recorded_column, score_table

__all__ = ["StreamedEstimate", "estimate_streamed"]


@dataclass(frozen=True)
class StreamedEstimate:
    """What :func:`estimate_streamed` wrote and scored.

    Attributes
    ----------
    source : str
        The log read.
    resampling : Resampling
    n : int
        Samples on the grid (rows written).
    in_domain : int or None
        Estimates in the domain the maps were trained on (None where the model records no domain).
    ekf_noise : tuple of float or None
        ``(process_std, measurement_std)`` of the EKF made from the card's levels (None for one passed in or none).
    scores : dict
        As :attr:`~kklcasadi.evaluation.logged.LogEstimate.scores`.
    settle : float
    path : Path
        The estimates written.
    """

    source: str
    resampling: Resampling
    n: int
    in_domain: Optional[int]
    ekf_noise: Optional[tuple]
    scores: dict
    settle: float
    path: Path

    def table(self, state_names: Optional[Sequence[str]] = None) -> str:
        """The scores as a few lines of text (one per recorded state)."""
        return score_table(self.scores, self.settle, state_names)


def estimate_streamed(observer: KKLObserver, path: Union[str, os.PathLike], *, out: Union[str, os.PathLike],
                      time_col: str = "time", y_cols: Sequence[str] = (), u_cols: Sequence[str] = (),
                      u_zero: bool = False, reference_cols: Sequence[Optional[str]] = (),
                      angle_cols: Optional[Sequence[str]] = None, range_check: bool = True,
                      ekf: Union[bool, EKF] = False, process_std: Optional[float] = None,
                      measurement_std: Optional[float] = None, settle: float = 0.0,
                      compiler: Optional[Compiler] = FAST, state_names: Optional[Sequence[str]] = None,
                      stamp: Optional[Stamp] = None, progress: bool = False) -> Optional[StreamedEstimate]:
    """Estimate a CSV log's states a block at a time and write them to ``out``; None where it cannot (see the module).

    Parameters
    ----------
    observer : KKLObserver
    path : str or path-like
        The log.
    out : str or path-like
        The estimates to write (:meth:`~kklcasadi.evaluation.logged.LogEstimate.write`'s columns).
    time_col, y_cols, u_cols, u_zero, reference_cols, angle_cols, range_check, ekf, process_std, measurement_std, settle
        As :func:`~kklcasadi.evaluation.logged.estimate_log`.
    compiler : Compiler or None
        As :func:`~kklcasadi.evaluation.logged.estimate_log`.
    state_names : sequence of str, optional
        Column names of the states (default ``x1 .. xn``).
    stamp : Stamp, optional
        The provenance of the file written.
    progress : bool
        A progress bar over the samples (tqdm).

    Returns
    -------
    StreamedEstimate or None
    """
    plant = observer.system
    arguments, reference = log_arguments(observer, time_col=time_col, y_cols=y_cols, u_cols=u_cols, u_zero=u_zero,
                                         reference_cols=reference_cols, angle_cols=angle_cols,
                                         range_check=range_check)
    settle = nonnegative_number(settle, "settle")
    if ekf is not True and ekf is not False and not isinstance(ekf, EKF):
        raise error("ekf", "True, False or a kklcasadi.EKF", Text(type(ekf).__name__), kind=TypeError)
    scan = scan_log(path, **arguments)
    if scan is None:
        return None
    with scan:
        t0 = scan.resampling.t0
        if reference and not scan.t_last - t0 >= settle:
            raise error("settle", f"less than the log's {scan.t_last - t0:.6g} s", settle)
        noise = None
        if ekf is True:
            ekf, noise = ekf_for_model(observer, process_std=process_std, measurement_std=measurement_std)
        names = tuple(state_names) if state_names is not None else tuple(f"x{i + 1}" for i in range(plant.nx))
        where = {i: recorded_column(scan.columns, name) for i, name in reference.items()}
        guard = SampleGuard.of(observer)
        runs = [ChunkedObserver(observer, compiler=compiler)] + ([ChunkedEKF(ekf, compiler=compiler)]
                                                                 if isinstance(ekf, EKF) else [])
        states: list = [None] * len(runs)
        squares = {i: [0.0, 0.0] for i in reference}           # per recorded state: KKL, EKF
        kept, inside, last = 0, 0, None
        writer = EstimatesWriter(out, state_names=names, stamp=stamp)
        try:
            with tqdm(total=scan.n, unit="sample", disable=not progress, unit_scale=True) as bar:
                for t, y, u, ref in scan.blocks():
                    u = u if u.shape[1] else np.zeros((t.size, plant.nu))
                    if not guard.accepts(y, u).all():
                        writer.discard()
                        return None
                    results = []
                    for j, run in enumerate(runs):
                        results.append(_advance(run, states, j, y, u, last, scan.n))
                    xhat, z = results[0][0], results[0][1]
                    if not guard.keeps(z, xhat).all():
                        writer.discard()
                        return None
                    flags = results[0][2][:, 0] > 0.5 if len(results[0]) > 2 else None
                    ekf_xhat = results[1][0] if len(results) > 1 else None
                    keep = t - t0 >= settle
                    kept += int(np.count_nonzero(keep))
                    for i, (key, column) in where.items():
                        truth = (y if key == "y" or ref is None else ref)[keep, column]
                        for e, estimate in enumerate((xhat, ekf_xhat)):
                            if estimate is not None:
                                difference = truth - estimate[keep, i]
                                if i in plant.angle_states:
                                    difference = metrics.wrap_angle(difference)
                                squares[i][e] += float(np.sum(difference ** 2))
                    inside += 0 if flags is None else int(np.count_nonzero(flags))
                    extra = None if ekf_xhat is None else {f"ekf_{n}": ekf_xhat[:, i] for i, n in enumerate(names)}
                    writer.write(t, xhat, in_domain=flags, status=np.zeros(t.size, dtype=np.int8), extra=extra)
                    last = (y[-1:], u[-1:])
                    bar.update(t.size)
            written = writer.commit()
        except BaseException:
            writer.discard()
            raise
        scores = {i: {"column": reference[i], "rmse": math.sqrt(squares[i][0] / kept),
                      "rmse_ekf": math.sqrt(squares[i][1] / kept) if len(runs) > 1 else None} for i in reference}
        return StreamedEstimate(scan.source, scan.resampling, scan.n,
                                None if observer.domain_check is None else inside, noise, scores, settle, written)


def _advance(run: Union[ChunkedObserver, ChunkedEKF], states: list, j: int, y: np.ndarray, u: np.ndarray,
             last: Optional[tuple[np.ndarray, np.ndarray]], n: int) -> list[np.ndarray]:
    """The outputs of a block's samples for one estimator, its state carried in ``states[j]`` (None before the
    first block; ``last`` the previous block's last sample)."""
    if states[j] is None:
        states[j], first = run.start(y[0], u[0])
        states[j], rest = run.advance(states[j], y, u, n)
        return [np.concatenate([a, b]) for a, b in zip(first, rest)] if rest else first
    assert last is not None
    states[j], outputs = run.advance(states[j], np.concatenate([last[0], y]), np.concatenate([last[1], u]), n)
    return outputs
