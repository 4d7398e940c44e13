"""A CSV log of any length put on a model's grid a block of samples at a time, in the memory of a block.

:func:`scan_log` reads the file once with :func:`~kklcasadi.plant.logs.read_log`'s reader (the same one-line
errors for a malformed file), keeps the columns it reads in a temporary binary file, and checks what
:func:`~kklcasadi.plant.logs.read_log` checks; :meth:`LogScan.blocks` then gives the grid a block at a time with
:func:`~kklcasadi.plant.logs.read_log`'s values bit for bit: ``y`` and the reference interpolated at the grid times,
angle columns unwrapped with :func:`numpy.unwrap`'s arithmetic carried across blocks, ``u`` held zero-order.

:func:`scan_log` returns None, so that the caller reads the log whole with :func:`~kklcasadi.plant.logs.read_log`
(which then raises its error, or averages the inputs), where the log is not finite, its times do not increase,
its median spacing is not certainly at the model's rate (a faster log's inputs are averaged over each interval;
a slower one is refused; a median between two spacings that straddle a bound needs the whole log), it has a gap,
or a value is outside its box. What differs from :func:`~kklcasadi.plant.logs.read_log` on a log of more than
:data:`~kklcasadi.plant.logs.table_blocks`' block of rows: the mean spacing and an angle column's mean (which picks
its shift, a whole multiple of ``2 pi``) are summed a block at a time, the same up to rounding.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from typing import Any, Iterator, Mapping, Optional, Sequence

import numpy as np

from .logs import (
    RATE_TOLERANCE,
    U_HOLD,
    Y_METHOD,
    Resampling,
    _angle_shift,
    _Arguments,
    _arguments,
    _grid_size,
    _outside,
    table_blocks,
)

__all__ = ["LogScan", "scan_log", "BLOCK"]

#: Grid samples per block of :meth:`LogScan.blocks` (and rows per read of the binary copy).
BLOCK = 65536


@dataclass
class _Unwrap:
    """:func:`numpy.unwrap` (period ``2 pi``) of a column a block at a time: the last raw value and the last
    correction's cumulative sum carried."""

    last: Optional[float] = None
    carried: float = 0.0

    def __call__(self, raw: np.ndarray) -> np.ndarray:
        p = raw if self.last is None else np.concatenate([[self.last], raw])
        dd = np.diff(p)
        ddmod = np.mod(dd + math.pi, 2 * math.pi) - math.pi
        np.copyto(ddmod, math.pi, where=(ddmod == -math.pi) & (dd > 0))
        correction = ddmod - dd
        np.copyto(correction, 0, where=abs(dd) < math.pi)
        up = raw.copy()
        if self.last is None:                         # numpy's own: the first sample as it is
            sums = np.cumsum(correction)
            up[1:] = raw[1:] + sums
        else:
            sums = np.cumsum(np.concatenate([[self.carried], correction]))[1:]
            up += sums
        if sums.size:
            self.carried = float(sums[-1])
        self.last = float(raw[-1])
        return up


@dataclass(eq=False)
class LogScan:
    """A log read once, its columns kept in a temporary binary file: :meth:`blocks` gives its grid.

    Attributes
    ----------
    source : str
        The file read.
    columns : dict
        ``{"time": (name,), "y": names, "u": names, "reference": names}``, as :class:`~kklcasadi.plant.logs.Log`'s.
    resampling : Resampling
    n : int
        Samples on the grid.
    """

    source: str
    columns: dict
    resampling: Resampling
    n: int
    _arguments: _Arguments
    _store: Any
    _shifts: dict

    @property
    def t_last(self) -> float:
        """The last grid time."""
        r = self.resampling
        return r.t0 + (self.n - 1) * r.dt

    def blocks(self, size: int = BLOCK) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, Optional[np.ndarray]]]:
        """The grid ``(t (b,), y (b, ny), u (b, nu), reference (b, nr) or None)`` a block of ``size`` samples at a
        time: :func:`~kklcasadi.plant.logs.read_log`'s ``Log.t``, ``.y``, ``.u`` and ``.reference``, bit for bit."""
        a, r = self._arguments, self.resampling
        width = len(a.wanted) + 1
        index = {name: 1 + i for i, name in enumerate(a.data_cols)}
        self._store.seek(0)
        left = r.n_raw
        rows = np.empty((0, width))
        for k0 in range(0, self.n, size):
            t = r.t0 + np.arange(k0, min(self.n, k0 + size)) * r.dt
            while left and (rows.shape[0] == 0 or rows[-1, 0] < t[-1]):
                take = min(left, BLOCK)
                more = np.fromfile(self._store, dtype=np.float64, count=take * width).reshape(take, width)
                for name, shift in self._shifts.items():
                    more[:, index[name]] = more[:, index[name]] + shift
                rows = np.concatenate([rows, more])
                left -= take
            t_raw = rows[:, 0]

            def sampled(names: tuple[str, ...]) -> np.ndarray:
                return np.column_stack([np.interp(t, t_raw, rows[:, index[name]]) for name in names]) if names \
                    else np.zeros((t.size, 0))

            u = rows[np.searchsorted(t_raw, t, side="right") - 1][:, [index[name] for name in a.u_cols]] \
                if a.u_cols else np.zeros((t.size, 0))
            yield t, sampled(a.y_cols), u, sampled(a.reference_cols) if a.reference_cols else None
            rows = rows[max(0, int(np.searchsorted(t_raw, t[-1], side="right")) - 1):]

    def close(self) -> None:
        """Remove the binary copy."""
        self._store.close()

    def __enter__(self) -> LogScan:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def scan_log(path: str | os.PathLike, *, time_col: str, y_cols: Sequence[str], u_cols: Sequence[str] = (),
             reference_cols: Sequence[str] = (), dt: float, angle_cols: Sequence[str] = (), max_dt_ratio: float = 1.5,
             box: Optional[Mapping[str, Sequence[float]]] = None, box_margin: float = 0.1) -> Optional[LogScan]:
    """Read a CSV log once for :meth:`LogScan.blocks`; None where :func:`~kklcasadi.plant.logs.read_log` must read it
    (see the module).

    Parameters
    ----------
    path, time_col, y_cols, u_cols, reference_cols, dt, angle_cols, max_dt_ratio, box, box_margin
        As :func:`~kklcasadi.plant.logs.read_log` (the grid starts at the first logged time).

    Returns
    -------
    LogScan or None

    Raises
    ------
    ValueError, TypeError
        :func:`~kklcasadi.plant.logs.read_log`'s errors about the arguments and the file's text.
    """
    a = _arguments(path, time_col, y_cols, u_cols, reference_cols, dt, angle_cols, max_dt_ratio, box, box_margin)
    hi, lo = a.dt * (1.0 + RATE_TOLERANCE), a.dt / (1.0 + RATE_TOLERANCE)
    store = tempfile.TemporaryFile()
    try:
        unwrap = {name: _Unwrap() for name in a.angle_cols}
        sums = dict.fromkeys(a.angle_cols, 0.0)
        index = {name: 1 + i for i, name in enumerate(a.data_cols)}
        n, t_first, t_last = 0, math.nan, math.nan
        dt_min, dt_max, dt_sum = math.inf, -math.inf, 0.0
        at_most_hi = below_lo = 0                               # steps <= dt (1 + tol), steps < dt / (1 + tol)
        ok = True
        for values, lines in table_blocks(a.path, a.wanted, a.asked):
            if ok and not np.isfinite(values).all():
                ok = False
            if not ok:                                          # read on: the reader's own errors come first
                continue
            t = values[:, 0]
            steps = np.diff(t) if n == 0 else np.diff(np.concatenate([[t_last], t]))
            if np.any(steps <= 0):
                ok = False
                continue
            if n == 0:
                t_first = float(t[0])
            if steps.size:
                dt_min, dt_max = min(dt_min, float(steps.min())), max(dt_max, float(steps.max()))
                dt_sum += float(np.add.reduce(steps))
                at_most_hi += int(np.count_nonzero(steps <= hi))
                below_lo += int(np.count_nonzero(steps < lo))
            for name in a.angle_cols:
                values[:, index[name]] = unwrap[name](values[:, index[name]])
                sums[name] += float(np.add.reduce(values[:, index[name]]))
            np.column_stack([values, lines.astype(np.float64)]).tofile(store)
            n += t.size
            t_last = float(t[-1])
        m = n - 1                                               # steps; their median is the log's rate
        middle = (m // 2,) if m % 2 else (m // 2 - 1, m // 2)  # the sorted steps' indices it averages
        at_rate = ok and at_most_hi > max(middle) and below_lo <= min(middle)   # lo <= both <= hi, for sure
        if not at_rate or dt_max > a.dt * a.max_dt_ratio:
            store.close()
            return None
        shifts = {name: _angle_shift(a.bounds.get(name), sums[name] / n) for name in a.angle_cols}
        scan = LogScan(str(a.path), {"time": (a.time_col,), "y": a.y_cols, "u": a.u_cols,
                                     "reference": a.reference_cols},
                       Resampling(a.dt, t_first, n, t_first, t_last, dt_min, dt_sum / m, dt_max, Y_METHOD, U_HOLD,
                                  a.angle_cols, tuple(shifts.values())),
                       _grid_size(t_first, t_last, a.dt), a, store, {k: v for k, v in shifts.items() if k in a.bounds})
        if not _inside(scan):
            store.close()
            return None
        return scan
    except BaseException:
        store.close()
        raise


def _inside(scan: LogScan) -> bool:
    """Whether every value of a column with a box lies in it widened by the margin (read back block by block)."""
    a = scan._arguments
    if not a.bounds:
        return True
    width = len(a.wanted) + 1
    index = {name: 1 + i for i, name in enumerate(a.data_cols)}
    scan._store.seek(0)
    left = scan.resampling.n_raw
    while left:
        take = min(left, BLOCK)
        rows = np.fromfile(scan._store, dtype=np.float64, count=take * width).reshape(take, width)
        left -= take
        for name in a.bounds:
            values = rows[:, index[name]] + scan._shifts[name] if name in scan._shifts else rows[:, index[name]]
            if _outside(a, name, values).any():
                return False
    return True
