"""Logged data in and out: a CSV log put on a model's uniform grid, and estimates written back.

:func:`read_log` reads the columns it is told to, by name, from a CSV file with a header row,
validates them (plain decimal numbers, times strictly increasing, every value finite, a log at
least as fast as the model's ``dt``, no gap much longer than ``dt``, values inside an optional
box) and puts them on the grid ``t_k = t0 + k dt`` that observers and the EKF expect:

- measurements ``y`` and reference columns are **sampled at the grid times**, interpolated
  linearly between the two logged samples around each (for a signal with ``|f''| <= M`` sampled
  with spacing at most ``h``, the error is at most ``M h^2 / 8``); angle columns are unwrapped
  first (:func:`numpy.unwrap`), so a pendulum angle logged wrapped to ``[-pi, pi]`` becomes
  continuous and is never interpolated across a jump of ``2 pi``;
- inputs ``u`` of a log **at the model's rate** (mean spacing within :data:`RATE_TOLERANCE` of
  ``dt``, jitter allowed) are held **zero-order**: ``u_k`` is the last logged value at or before
  ``t_k``. A digital controller holds its output between updates, so the plant saw
  piecewise-constant inputs; a linear interpolation would invent voltages that were never
  applied (between the two levels of a step) and shift every step by half a sample. The hold
  keeps the applied levels, and delays a change logged between two grid points by less than
  ``dt`` (the model's own convention holds ``u_k`` over ``[t_k, t_k+1)``);
- inputs of a **faster log** (several samples per ``dt``, an integer multiple or not) are
  **averaged over each interval**: ``u_k`` is the exact integral of the log's own zero-order
  hold over ``[t_k, t_k + dt]`` divided by ``dt`` (the last logged value held past the end), the
  constant input that carries the same impulse over the interval as the logged one did.

A log slower than the model (median spacing above ``dt (1 + RATE_TOLERANCE)``) is refused: it
cannot be put on a finer grid without inventing samples; train a model at its rate.

The file is UTF-8 (a byte-order mark is dropped), read with :mod:`csv` (quoted fields, other
columns ignored, blank lines and lines starting with ``#`` skipped). A value is a plain decimal
number (:data:`NUMBER`: ASCII digits, an optional sign, point and exponent; ``1_000``, ``0x10``
or non-ASCII digits are refused) or ``nan``/``inf``, which are then refused as not finite.
Every error is one line naming the file, row, line and column.

:func:`write_estimates` writes estimates as CSV atomically and exclusively (a temporary file in the same
folder, then linked into place; renamed over an existing file only with ``overwrite``), and
:func:`savgol_derivative` is the zero-lag velocity reference that logs of angles are scored against (a
Savitzky-Golay derivative on the uniform grid).

Over 600 lines: one concept, a log in and estimates out; the strict CSV reader and its one-line errors are
half of it, and the resampling onto the grid shares its checks. :func:`write_estimates` and
:func:`savgol_derivative` are the parts that could leave for a module of their own.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, Optional, Sequence

import numpy as np

from .. import provenance
from ..validation import Text, error, finite_number, is_int, nonnegative_number, positive_int, positive_number
from ..writes import place

__all__ = ["Log", "Resampling", "read_log", "write_estimates", "EstimatesWriter", "table_blocks", "savgol_derivative",
           "Y_METHOD", "U_HOLD", "U_MEAN", "RATE_TOLERANCE", "NUMBER", "FIELD_LIMIT"]

#: How ``y`` and the reference are put on the grid.
Y_METHOD = "sampled at the grid times (linear between logged samples; angle columns unwrapped first)"
#: How ``u`` of a log at the model's rate is put on the grid.
U_HOLD = "zero-order hold (last logged value at or before each grid time)"
#: How ``u`` of a faster log is put on the grid.
U_MEAN = "mean over each interval of the log's zero-order hold (the same impulse)"
#: A log whose median spacing is within this share of ``dt`` is at the model's rate (jitter); above
#: ``dt (1 + RATE_TOLERANCE)`` it is slower than the model and refused, below ``dt / (1 +
#: RATE_TOLERANCE)`` it is faster and its inputs are averaged over each interval.
RATE_TOLERANCE = 0.05
#: The numbers a log may hold: an optional sign, ASCII digits with an optional decimal point, an
#: optional exponent (and ``nan``, ``inf``, ``infinity`` in any case, refused later as not finite).
NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|[+-]?(?:nan|inf|infinity)",
                    re.IGNORECASE | re.ASCII)
#: The longest field the reader accepts (the :mod:`csv` module's default limit).
FIELD_LIMIT = 131072


@dataclass(frozen=True)
class Resampling:
    """The record of how a log was put on its grid.

    Attributes
    ----------
    dt : float
        Grid step (the model's sample period).
    t0 : float
        First grid time, in the log's clock.
    n_raw : int
        Samples in the file.
    t_first, t_last : float
        First and last logged times.
    dt_min, dt_mean, dt_max : float
        Statistics of the logged sample spacing.
    y_method, u_method : str
        :data:`Y_METHOD`; :data:`U_HOLD` (a log at the model's rate) or :data:`U_MEAN` (a faster log).
    angle_cols : tuple of str
        Columns unwrapped as angles.
    angle_shifts : tuple of float
        The multiple of ``2 pi`` added to each of them after unwrapping (0 unless a box moved it
        onto the box's branch).
    """

    dt: float
    t0: float
    n_raw: int
    t_first: float
    t_last: float
    dt_min: float
    dt_mean: float
    dt_max: float
    y_method: str
    u_method: str
    angle_cols: tuple
    angle_shifts: tuple


@dataclass(frozen=True, eq=False)
class Log:
    """A log on a uniform grid (read-only arrays, float64).

    Attributes
    ----------
    t : numpy.ndarray, shape (N,)
        Grid times ``t0 + k dt``, in the log's clock.
    y : numpy.ndarray, shape (N, ny)
        Measurements sampled at the grid times (angle columns unwrapped).
    u : numpy.ndarray, shape (N, nu)
        Inputs, held zero-order or averaged over each interval (see the module); shape (N, 0)
        without ``u_cols`` (pass ``np.zeros((N, nu))`` to an estimator for a run at ``u = 0``).
    reference : numpy.ndarray, shape (N, nr), or None
        Reference columns (e.g. logged velocities), sampled as ``y``; None without ``reference_cols``.
    columns : dict
        ``{"time": (name,), "y": names, "u": names, "reference": names}``, tuples of the file's column names.
    source : str
        The file read.
    resampling : Resampling
    """

    t: np.ndarray
    y: np.ndarray
    u: np.ndarray
    reference: Optional[np.ndarray]
    columns: dict
    source: str
    resampling: Resampling


def _names(value: Any, argument: str, *, allow_empty: bool) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, (list, tuple)):
        raise error(argument, "a list or tuple of column names", Text(type(value).__name__), kind=TypeError)
    for name in value:
        if not isinstance(name, str) or not name:
            raise error(argument, "non-empty strings (column names)", Text(repr(name)), kind=TypeError)
    if not allow_empty and not value:
        raise error(argument, "at least one column name", Text("an empty sequence"))
    if len(set(value)) != len(value):
        raise error(argument, "distinct column names", list(value))
    return tuple(value)


def _box_bounds(box: Any, readable: tuple[str, ...]) -> dict[str, tuple[float, float]]:
    if box is None:
        return {}
    if not isinstance(box, Mapping):
        raise error("box", "a mapping {column: (lo, hi)} or None", Text(type(box).__name__), kind=TypeError)
    bounds = {}
    for name, pair in box.items():
        if name not in readable:
            raise error("box", f"columns among those read {list(readable)}", name)
        lo_hi = np.asarray(pair, dtype=float)
        if lo_hi.shape != (2,) or not np.all(np.isfinite(lo_hi)) or lo_hi[1] <= lo_hi[0]:
            raise error(f"box[{name!r}]", "finite (lo, hi) with lo < hi", Text(repr(pair)))
        bounds[name] = (float(lo_hi[0]), float(lo_hi[1]))
    return bounds


def _where(source: str, row: int, line: int, column: Optional[str] = None) -> str:
    place = f"{source}: row {row} (line {line})"
    return f"{place}, column {column!r}" if column is not None else place


def _shown(text: str, limit: int = 40) -> Text:
    """``text`` for an error message: quoted, cut to ``limit`` characters."""
    return Text(repr(text) if len(text) <= limit else f"{text[:limit]!r}... ({len(text)} characters)")


class _Lines:
    """The lines of a text stream without comment lines (``#`` first), counting every physical line."""

    def __init__(self, stream: Any) -> None:
        self.stream, self.line = stream, 0

    def __iter__(self) -> Iterator[str]:
        for text in self.stream:
            self.line += 1
            if not text.startswith("#"):
                yield text


def _rows(path: Path, source: str) -> Iterator[tuple[int, list[str]]]:
    """The non-blank rows of a CSV file with the number of the line each ends on; one-line errors."""
    with open(path, newline="", encoding="utf-8-sig") as stream:
        lines = _Lines(stream)
        reader = csv.reader(lines, strict=True)
        while True:
            try:
                row = next(reader)
            except StopIteration:
                return
            except UnicodeDecodeError:
                raise error(f"{source}: line {lines.line + 1}", "UTF-8 text", Text("bytes that are not UTF-8"),
                            "Save the log as UTF-8 CSV.") from None
            except csv.Error as exc:
                what = str(exc)
                if "field larger than field limit" in what:
                    raise error(f"{source}: line {lines.line}", f"fields of at most {FIELD_LIMIT} characters",
                                Text("a longer field")) from None
                raise error(f"{source}: line {lines.line}", "a well-formed CSV row", Text(what)) from None
            if row:                                       # blank lines carry no sample
                yield lines.line, row


#: Rows parsed into Python lists before they become one float64 block (bounds the reader's Python objects).
_BLOCK = 65536


def _number(text: str, source: str, row: int, line: int, column: str) -> float:
    """A field as a float: a plain decimal number (:data:`NUMBER`), blanks around it allowed; an error names
    the row, line and column."""
    text = text.strip(" \t")
    if NUMBER.fullmatch(text) is None:
        raise error(_where(source, row, line, column), "a plain decimal number (digits, '.', an exponent)",
                    _shown(text))
    return float(text)


def _read_table(path: Path, wanted: tuple[str, ...], arguments: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The ``wanted`` columns of a CSV file as floats (n, len(wanted)), and each row's line number.

    ``arguments`` names, per wanted column, the argument that asked for it (for a missing column).
    """
    blocks, line_blocks = zip(*table_blocks(path, wanted, arguments))
    return np.concatenate(blocks), np.concatenate(line_blocks)


def table_blocks(path: Path, wanted: tuple[str, ...], arguments: tuple[str, ...]) -> Iterator[tuple[np.ndarray,
                                                                                                      np.ndarray]]:
    """The ``wanted`` columns of a CSV file as floats, a block of at most :data:`_BLOCK` rows at a time
    ``(values (b, len(wanted)), line numbers (b,))``, the header checked before the first; a file of fewer
    than 2 data rows is an error before any block.

    ``arguments`` names, per wanted column, the argument that asked for it (for a missing column).
    """
    source = str(path)
    rows = _rows(path, source)
    first = next(rows, None)
    if first is None:
        raise error(source, "a CSV file with a header row", Text("an empty file"))
    header = [name.strip() for name in first[1]]
    repeated = sorted({name for name in header if header.count(name) > 1})
    if repeated:
        raise error(f"{source}: header", "distinct column names", Text(f"repeated {repeated}"))
    for name, argument in zip(wanted, arguments):
        if name not in header:
            raise error(argument, f"a column of {source}", name,
                        f"Its header holds {header if len(header) <= 20 else header[:20] + ['...']}.")
    index = [header.index(name) for name in wanted]
    values: list[list[float]] = []                # a block of rows at a time as float64 (not lists of floats)
    lines: list[int] = []
    count = 0
    for line, row in rows:
        if len(row) != len(header):
            raise error(_where(source, count, line), f"{len(header)} fields (one per header column)",
                        Text(f"{len(row)} fields"))
        values.append([_number(row[i], source, count, line, name) for i, name in zip(index, wanted)])
        lines.append(line)
        count += 1
        if len(values) == _BLOCK:
            yield np.array(values, dtype=np.float64), np.array(lines)
            values, lines = [], []
    if count < 2:
        raise error(source, "at least 2 data rows", Text(f"{count} rows"))
    if values:
        yield np.array(values, dtype=np.float64), np.array(lines)


def _interval_means(t_raw: np.ndarray, values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The mean over each ``[edges[k], edges[k+1]]`` of the zero-order hold of ``values`` (n, m) at
    ``t_raw`` (the last value held past the end), (len(edges) - 1, m).

    The intervals are cut at every logged time inside them; each piece's departure from the
    interval's first value, times its length, is summed per interval and divided by the summed
    lengths, then added to that first value (so an input constant over an interval is exactly kept).
    """
    inside = t_raw[(t_raw > edges[0]) & (t_raw < edges[-1])]
    cuts = np.union1d(edges, inside)
    lengths = np.diff(cuts)
    held = values[np.searchsorted(t_raw, cuts[:-1], side="right") - 1]           # each piece's value
    interval = np.minimum(np.searchsorted(edges, cuts[:-1], side="right") - 1, edges.size - 2)
    n = edges.size - 1
    first = held[np.searchsorted(interval, np.arange(n))]                          # each interval's first value
    total = np.bincount(interval, weights=lengths, minlength=n)
    departure = np.column_stack([np.bincount(interval, weights=lengths * (held[:, j] - first[interval, j]),
                                             minlength=n) for j in range(values.shape[1])])
    return first + departure / total[:, None]


def read_log(path: str | os.PathLike, *, time_col: str, y_cols: Sequence[str], u_cols: Sequence[str] = (),
             reference_cols: Sequence[str] = (), dt: float, angle_cols: Sequence[str] = (),
             t0: Optional[float] = None, max_dt_ratio: float = 1.5,
             box: Optional[Mapping[str, Sequence[float]]] = None, box_margin: float = 0.1) -> Log:
    """Read a CSV log, validate it and put it on the grid ``t0 + k dt``.

    Parameters
    ----------
    path : str or path-like
        A CSV file with a header row (UTF-8; see the module for what it may hold); other columns
        are ignored, blank lines and ``#`` lines (a provenance stamp, notes) skipped.
    time_col : str
        The column of sample times (seconds, strictly increasing, any origin).
    y_cols : sequence of str
        Measurement columns, in the order of the model's outputs (sampled at the grid times).
    u_cols : sequence of str
        Input columns, in the order of the model's inputs (held zero-order, or averaged over each
        interval for a log faster than the model; see the module).
    reference_cols : sequence of str
        Further columns to carry along, sampled as ``y`` (e.g. logged velocities to compare with).
    dt : float
        The model's sample period. The log's median spacing must be at most ``dt (1 +``
        :data:`RATE_TOLERANCE` ``)``: at the model's rate with jitter, or faster.
    angle_cols : sequence of str
        Columns of ``y_cols`` or ``reference_cols`` that are angles in radians, possibly wrapped:
        they are unwrapped (:func:`numpy.unwrap`, which assumes less than ``pi`` of true motion
        between two samples) before anything else.
    t0 : float, optional
        First grid time, in the log's clock, within the logged times; default the first logged time.
        The grid runs to the last grid time at or before the last logged time (to 1e-9 ``dt``, so
        that a log at the model's rate keeps its last sample whatever the rounding of its times).
    max_dt_ratio : float
        No logged spacing may exceed ``max_dt_ratio dt`` (a gap would be bridged by interpolation).
    box : mapping {column: (lo, hi)}, optional
        Plausible ranges of read columns (e.g. the outputs over a model's training domain). An
        angle column is first moved by the multiple of ``2 pi`` that brings its mean closest to
        the middle of its range (the dynamics of an angle are ``2 pi``-periodic; the shift is
        recorded). A logged value more than ``box_margin`` times the range's width outside it is
        an error.
    box_margin : float
        See ``box``; ``math.inf`` for no range test (the box then only moves angles onto its branch).

    Returns
    -------
    Log

    Raises
    ------
    ValueError
        One line naming the file and what is wrong: a column missing from the header (naming the
        argument that asked for it: ``time_col``, ``y_cols``, ``u_cols`` or ``reference_cols``),
        text that is not UTF-8 CSV or a field over :data:`FIELD_LIMIT` characters (its line), a
        value that is not a plain decimal number or not finite (row, line and column), times not
        strictly increasing (the first bad row), a log slower than ``dt`` (both given) or a gap
        (its row), a value outside the box (column, row, value and bound), or ``t0`` outside the log.
    TypeError
        Column arguments that are not sequences of strings, or a box that is not a mapping.
    """
    a = _arguments(path, time_col, y_cols, u_cols, reference_cols, dt, angle_cols, max_dt_ratio, box, box_margin)
    path, source, time_col, dt = a.path, a.source, a.time_col, a.dt
    y_cols, u_cols, reference_cols, angle_cols, data_cols = a.y_cols, a.u_cols, a.reference_cols, a.angle_cols, \
        a.data_cols
    bounds, box_margin = a.bounds, a.box_margin
    table, lines = _read_table(path, a.wanted, a.asked)
    bad = np.argwhere(~np.isfinite(table))
    if bad.size:
        k, c = bad[0]
        raise error(_where(source, int(k), int(lines[k]), a.wanted[c]), "a finite number", float(table[k, c]))
    t_raw = table[:, 0]
    steps = np.diff(t_raw)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise _order_error(source, time_col, k, int(lines[k]), t_raw[k - 1], t_raw[k])
    dt_min, dt_mean, dt_max = float(steps.min()), float(steps.mean()), float(steps.max())
    spacing = float(np.median(steps))                     # the log's rate, whatever its gaps
    _check_spacing(a, spacing, dt_min, dt_max, int(np.argmax(steps)) + 1, lines)

    columns = {name: table[:, 1 + i].copy() for i, name in enumerate(data_cols)}
    shifts = []
    for name in angle_cols:
        columns[name] = np.unwrap(columns[name])
        shift = _angle_shift(bounds.get(name), float(columns[name].mean()))
        if name in bounds:
            columns[name] = columns[name] + shift
        shifts.append(shift)
    for name in bounds:
        _check_box(a, name, columns[name], lines)

    t0 = float(t_raw[0]) if t0 is None else finite_number(t0, "t0")
    if not t_raw[0] <= t0 < t_raw[-1]:
        raise error("t0", f"a time within the log [{t_raw[0]:.6g}, {t_raw[-1]:.6g})", t0)
    edges = t0 + np.arange(_grid_size(t0, float(t_raw[-1]), dt) + 1) * dt
    t = edges[:-1]

    def sampled(names: tuple[str, ...]) -> np.ndarray:
        return np.column_stack([np.interp(t, t_raw, columns[name]) for name in names]) if names \
            else np.zeros((t.size, 0))

    at_rate = spacing >= dt / (1.0 + RATE_TOLERANCE)
    logged_u = np.column_stack([columns[name] for name in u_cols]) if u_cols else np.zeros((t_raw.size, 0))
    if not u_cols:
        u = np.zeros((t.size, 0))
    elif at_rate:
        u = logged_u[np.searchsorted(t_raw, t, side="right") - 1]
    else:
        u = _interval_means(t_raw, logged_u, edges)
    y = sampled(y_cols)
    reference = sampled(reference_cols) if reference_cols else None
    for array in (t, y, u, reference):
        if array is not None:
            array.setflags(write=False)
    record = Resampling(dt, t0, int(t_raw.size), float(t_raw[0]), float(t_raw[-1]), dt_min, dt_mean, dt_max,
                        Y_METHOD, U_HOLD if at_rate else U_MEAN, angle_cols, tuple(shifts))
    names = {"time": (time_col,), "y": y_cols, "u": u_cols, "reference": reference_cols}
    return Log(t, y, u, reference, names, source, record)


@dataclass(frozen=True)
class _Arguments:
    """The checked arguments of :func:`read_log` (and of the streamed reader)."""

    path: Path
    source: str
    time_col: str
    y_cols: tuple[str, ...]
    u_cols: tuple[str, ...]
    reference_cols: tuple[str, ...]
    angle_cols: tuple[str, ...]
    dt: float
    max_dt_ratio: float
    bounds: dict
    box_margin: float

    @property
    def data_cols(self) -> tuple[str, ...]:
        return self.y_cols + self.u_cols + self.reference_cols

    @property
    def wanted(self) -> tuple[str, ...]:
        """The columns read: the time, then the data columns."""
        return (self.time_col,) + self.data_cols

    @property
    def asked(self) -> tuple[str, ...]:
        """Per wanted column, the argument that asked for it."""
        return ("time_col",) + ("y_cols",) * len(self.y_cols) + ("u_cols",) * len(self.u_cols) + (
            "reference_cols",) * len(self.reference_cols)


def _arguments(path: Any, time_col: Any, y_cols: Any, u_cols: Any, reference_cols: Any, dt: Any, angle_cols: Any,
               max_dt_ratio: Any, box: Any, box_margin: Any) -> _Arguments:
    """:func:`read_log`'s arguments checked, before the file is read."""
    path = Path(path)
    source = str(path)
    if not isinstance(time_col, str) or not time_col:
        raise error("time_col", "a column name", Text(repr(time_col)), kind=TypeError)
    y_cols = _names(y_cols, "y_cols", allow_empty=False)
    u_cols = _names(u_cols, "u_cols", allow_empty=True)
    reference_cols = _names(reference_cols, "reference_cols", allow_empty=True)
    angle_cols = _names(angle_cols, "angle_cols", allow_empty=True)
    data_cols = y_cols + u_cols + reference_cols
    if len(set(data_cols)) != len(data_cols) or time_col in data_cols:
        raise error("y_cols, u_cols, reference_cols", f"distinct columns other than time_col {time_col!r}",
                    Text(f"{list(data_cols)}"))
    not_interpolated = [name for name in angle_cols if name not in y_cols + reference_cols]
    if not_interpolated:
        raise error("angle_cols", f"columns of y_cols or reference_cols {list(y_cols + reference_cols)}",
                    Text(f"{not_interpolated}"))
    dt = positive_number(dt, "dt")
    max_dt_ratio = finite_number(max_dt_ratio, "max_dt_ratio")
    if max_dt_ratio <= 1.0 + RATE_TOLERANCE:
        raise error("max_dt_ratio", f"a number > 1 + RATE_TOLERANCE = {1.0 + RATE_TOLERANCE:g}", max_dt_ratio)
    if not (isinstance(box_margin, (int, float)) and box_margin == math.inf):
        box_margin = nonnegative_number(box_margin, "box_margin")
    bounds = _box_bounds(box, data_cols)
    if not path.is_file():
        raise error("path", "an existing CSV file", source)
    return _Arguments(path, source, time_col, y_cols, u_cols, reference_cols, angle_cols, dt, max_dt_ratio, bounds,
                      box_margin)


def _grid_size(t0: float, t_last: float, dt: float) -> int:
    """Samples of the grid ``t0 + k dt`` up to the last logged time ``t_last`` (to 1e-9 ``dt``, so that a log at the
    model's rate keeps its last sample whatever the rounding of its times; the grid never extrapolates beyond it);
    fewer than 2 is an error naming ``t0``."""
    k = int(math.floor((t_last - t0) / dt * (1.0 + 1e-12))) + 1
    while k > 0 and t0 + (k - 1) * dt > t_last + 1e-9 * dt:
        k -= 1
    if k < 2:
        raise error("t0", f"a time at least dt = {dt:g} s before the last logged time {t_last:.6g}", t0)
    return k


def _order_error(source: str, time_col: str, k: int, line: int, before: float, after: float) -> Exception:
    """Row ``k``'s time is not after row ``k - 1``'s."""
    return error(_where(source, k, line, time_col), f"a time after row {k - 1}'s {before!r}", float(after),
                 "Times must be strictly increasing.")


def _check_spacing(a: _Arguments, spacing: float, dt_min: float, dt_max: float, k_max: int, lines: Any) -> None:
    """A log slower than the model (its median spacing), or a gap (the first longest spacing, before row ``k_max``;
    ``lines[k_max]`` its line), is an error."""
    dt = a.dt
    if spacing > dt * (1.0 + RATE_TOLERANCE):
        raise error(f"{a.source}: column {a.time_col!r}",
                    f"a log at least as fast as the model: a median sample time of at most dt = {dt:g} s "
                    f"(+{RATE_TOLERANCE:.0%} for jitter)",
                    Text(f"a median sample time of {spacing:.6g} s (spacings {dt_min:.6g} to {dt_max:.6g} s)"),
                    f"A slower log cannot be put on the model's grid: use a model trained at the log's rate "
                    f"(kklcasadi train --dt {spacing:.6g}).")
    if dt_max > dt * a.max_dt_ratio:
        raise error(_where(a.source, k_max, int(lines[k_max]), a.time_col),
                    f"spacings of at most max_dt_ratio dt = {dt * a.max_dt_ratio:.6g} s",
                    Text(f"a gap of {dt_max:.6g} s after row {k_max - 1}"), "Split the log at the gap.")


def _angle_shift(bounds: Optional[tuple[float, float]], mean: float) -> float:
    """The multiple of ``2 pi`` that brings an unwrapped angle's ``mean`` closest to the middle of its box (0.0
    without one)."""
    if bounds is None:
        return 0.0
    lo, hi = bounds
    return 2.0 * math.pi * round((0.5 * (lo + hi) - mean) / (2.0 * math.pi))


def _outside(a: _Arguments, name: str, values: np.ndarray) -> np.ndarray:
    """Where the values of column ``name`` lie outside its box widened by the margin."""
    lo, hi = a.bounds[name]
    margin = a.box_margin * (hi - lo) if a.box_margin < math.inf else math.inf
    return (values < lo - margin) | (values > hi + margin)


def _check_box(a: _Arguments, name: str, values: np.ndarray, lines: Any, offset: int = 0) -> None:
    """A value of column ``name`` outside its box widened by the margin is an error naming its row (``values[0]``
    is row ``offset``, ``lines`` the lines of ``values``)."""
    lo, hi = a.bounds[name]
    outside = _outside(a, name, values)
    if outside.any():
        k = int(np.argmax(outside))
        side = f"below lo = {lo:g}" if values[k] < lo else f"above hi = {hi:g}"
        raise error(_where(a.source, k + offset, int(lines[k]), name),
                    f"values within the box [{lo:g}, {hi:g}] widened by {a.box_margin:g} of its width",
                    Text(f"{values[k]:.6g}, {side}"))



def _finite(value: Any, argument: str, ndim: int, n: Optional[int] = None, offset: int = 0) -> np.ndarray:
    """``value`` as float64 with ``ndim`` axes (the first of length ``n`` if given), all finite; a row in an error
    is counted from ``offset``."""
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != ndim or (n is not None and array.shape[0] != n) or array.shape[0] == 0:
        rows = "N" if n is None else str(n)
        expected = f"shape ({rows},)" if ndim == 1 else f"shape ({rows}, k)"
        raise error(argument, expected, Text(f"shape {array.shape}"))
    bad = np.argwhere(~np.isfinite(array))
    if bad.size:
        where = f"row {bad[0][0] + offset}" + (f", column {bad[0][1]}" if array.ndim == 2 else "")
        raise error(argument, "finite values", Text(f"{array[tuple(bad[0])]} at {where}"))
    return array


def _columns(t: Any, xhat: Any, names: tuple[str, ...], in_domain: Any, status: Any,
             extra: Optional[Mapping[str, Any]], offset: int = 0) -> tuple[list[str], list[np.ndarray]]:
    """The header and the columns of a block of estimates (see :func:`write_estimates`), checked; rows in errors
    counted from ``offset``."""
    t = _finite(t, "t", 1, offset=offset)
    n = t.size
    xhat = _finite(xhat, "xhat", 2, n, offset)
    if len(names) != xhat.shape[1]:
        raise error("state_names", f"{xhat.shape[1]} names (one per column of xhat)", list(names))
    header = ["time", *names]
    body: list[np.ndarray] = [t, *xhat.T]
    if in_domain is not None:
        flags = np.asarray(in_domain)
        if flags.shape != (n,) or not (flags.dtype == bool or np.isin(flags, (0, 1)).all()):
            raise error("in_domain", f"{n} booleans", Text(f"shape {flags.shape}, dtype {flags.dtype}"))
        header.append("in_domain")
        body.append(flags.astype(bool).astype(np.int64))              # written 0 or 1
    if status is not None:
        codes = np.asarray(status)
        if codes.shape != (n,) or not np.issubdtype(codes.dtype, np.integer) or np.any(codes < 0):
            raise error("status", f"{n} integers >= 0", Text(f"shape {codes.shape}, dtype {codes.dtype}"))
        header.append("status")
        body.append(codes.astype(np.int64))
    if extra is not None:
        if not isinstance(extra, Mapping):
            raise error("extra", "a mapping {name: values (N,)}", Text(type(extra).__name__), kind=TypeError)
        _names(list(extra), "extra", allow_empty=True)
        for name, values in extra.items():
            header.append(name)
            body.append(_finite(values, f"extra[{name!r}]", 1, n, offset))
    repeated = sorted({name for name in header if header.count(name) > 1})
    if repeated:
        raise error("state_names, extra", "names distinct from each other and from 'time', 'in_domain', 'status'",
                    Text(f"repeated {repeated}"))
    return header, body


class EstimatesWriter:
    """:func:`write_estimates` a block of rows at a time: a record of any length in the memory of one block.

    :meth:`write` checks a block (rows in errors counted over the whole file) and appends it to a temporary file in
    the folder of ``path``; :meth:`commit` then puts it at ``path`` in one step (:func:`kklcasadi.writes.place`: an
    exclusive create, or with ``overwrite`` a rename over an existing file), :meth:`discard` removes it.
    As a context manager it commits on success and discards on an exception. Every block has the
    columns of the first (the header).

    Parameters
    ----------
    path : str or path-like
        The file to write; its folder must exist.
    state_names : sequence of str
    stamp : kklcasadi.provenance.Stamp, optional
        The file's provenance (default: this process's).
    overwrite : bool
        Replace an existing ``path``; without it an existing one is refused (before the first block is written)
        and :meth:`commit` never writes over a file.
    """

    def __init__(self, path: str | os.PathLike, *, state_names: Sequence[str],
                 stamp: Optional[provenance.Stamp] = None, overwrite: bool = False) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.names = _names(state_names, "state_names", allow_empty=False)
        self.stamp = stamp
        self.rows = 0
        self._header: Optional[list[str]] = None
        self._stream: Any = None
        self._temp: Optional[str] = None

    def write(self, t: Any, xhat: Any, *, in_domain: Any = None, status: Any = None,
              extra: Optional[Mapping[str, Any]] = None) -> None:
        """Append a block: ``t`` (n,), ``xhat`` (n, nx) and the optional columns of :func:`write_estimates`."""
        header, body = _columns(t, xhat, self.names, in_domain, status, extra, self.rows)
        self._rows(header, body)

    def _rows(self, header: list[str], body: list[np.ndarray]) -> None:
        if self._header is None:
            self._open(header)
        elif header != self._header:
            raise error("columns", f"the columns of the first block {self._header}", header)
        n = body[0].size
        for start in range(0, n, _BLOCK):                 # Python floats repr as the shortest round trip
            columns = [column[start:start + _BLOCK].tolist() for column in body]
            self._stream.write("".join(",".join(map(repr, row)) + "\n" for row in zip(*columns)))
        self.rows += n

    def _open(self, header: list[str]) -> None:
        path = self.path
        if not path.parent.is_dir():
            raise error("path", "a file in an existing folder", str(path))
        if path.is_dir():
            raise error("path", "a file path", Text(f"{str(path)!r}, a folder"))
        if not self.overwrite and os.path.lexists(path):
            raise FileExistsError(f"path: {path} exists; pass overwrite to replace it, or choose another path.")
        text = io.StringIO(provenance.csv_comment(self.stamp or provenance.stamp()))
        text.seek(0, io.SEEK_END)
        csv.writer(text, lineterminator="\n").writerow(header)
        handle, self._temp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        self._stream = os.fdopen(handle, "w", newline="")
        self._header = header
        self._stream.write(text.getvalue())

    def commit(self) -> Path:
        """Put the rows written at ``path`` (over an existing file only with ``overwrite``); ``path``."""
        if self._stream is None or self._temp is None:
            raise error("blocks", "at least one block written", Text("none"))
        try:
            self._stream.flush()
            os.fsync(self._stream.fileno())
            self._stream.close()
            place(Path(self._temp), self.path, overwrite=self.overwrite)
        except BaseException:
            self.discard()
            raise
        self._stream = self._temp = None
        return self.path

    def discard(self) -> None:
        """Remove the temporary file; ``path`` stays as it was."""
        if self._stream is not None:
            self._stream.close()
        if self._temp is not None:
            Path(self._temp).unlink(missing_ok=True)
        self._stream = self._temp = None

    def __enter__(self) -> EstimatesWriter:
        return self

    def __exit__(self, kind: Any, value: Any, traceback: Any) -> None:
        if kind is None:
            self.commit()
        else:
            self.discard()


def write_estimates(path: str | os.PathLike, t: Any, xhat: Any, *, state_names: Sequence[str],
                    in_domain: Any = None, status: Any = None, extra: Optional[Mapping[str, Any]] = None,
                    stamp: Optional[provenance.Stamp] = None, overwrite: bool = False) -> Path:
    """Write estimates as a CSV file, atomically, over an existing file only with ``overwrite``.

    A first line ``# provenance {...}`` holds the stamp (:mod:`kklcasadi.provenance`; ``stamp``,
    default this process's), then the header row (:func:`read_log` skips the comment). Columns:
    ``time``, the ``state_names``, then ``in_domain`` (0/1) and ``status`` (an integer >= 0) if
    given, then the ``extra`` columns in their order. Numbers are written with :func:`repr`, so
    reading them back gives the same floats. Everything is validated before the file is touched; the
    text goes, a block of rows at a time, to a temporary file in the same folder, which is then linked
    into place (with ``overwrite``, renamed over ``path``: :func:`kklcasadi.writes.place`): a failure leaves
    an existing file as it was and no temporary file behind.

    Parameters
    ----------
    path : str or path-like
        The file to write; its folder must exist.
    t : array_like, shape (N,)
    xhat : array_like, shape (N, nx)
        Finite estimates.
    state_names : sequence of str, length nx
    in_domain : array_like of bool, shape (N,), optional
        The domain monitor's flags (``Estimate.in_domain``).
    status : array_like of int, shape (N,), optional
        The sample guard's flags (:func:`kklcasadi.observer.guard.guarded_simulate`).
    extra : mapping {name: array_like (N,)}, optional
        Further finite columns (e.g. reference velocities).
    overwrite : bool
        Replace an existing ``path``; without it an existing one is refused (:class:`FileExistsError`).

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    names = _names(state_names, "state_names", allow_empty=False)
    header, body = _columns(t, xhat, names, in_domain, status, extra)
    writer = EstimatesWriter(path, state_names=names, stamp=stamp, overwrite=overwrite)
    try:
        writer._rows(header, body)
        return writer.commit()
    except BaseException:
        writer.discard()
        raise


def savgol_derivative(t: Any, angle: Any, window: int = 15, order: int = 3, *, unwrap: bool = True) -> np.ndarray:
    """Zero-lag derivative of sampled angles: a Savitzky-Golay filter with ``deriv=1``.

    The velocity reference of logged angles: each sample's derivative is that of the
    least-squares polynomial of degree ``order`` over the ``window`` samples centred on it (the
    first and last ``window // 2`` samples use the polynomial of the first and last window), so
    it does not lag as a backward difference does. Exact for polynomials of degree ``order``.

    Parameters
    ----------
    t : array_like, shape (N,)
        Uniform sample times (spacings equal to 1e-6 relative), e.g. ``Log.t``.
    angle : array_like, shape (N,) or (N, k)
        Angles (or any signals) along axis 0.
    window : int
        Odd window length, ``order < window <= N``.
    order : int
        Polynomial degree, at least 1.
    unwrap : bool
        Unwrap ``angle`` along axis 0 first (:func:`numpy.unwrap`; a no-op on continuous angles).

    Returns
    -------
    numpy.ndarray, the shape of ``angle``
        The derivative, per unit of ``t``.
    """
    from scipy.signal import savgol_filter

    t = _finite(t, "t", 1)
    values = _finite(angle, "angle", 2 if np.ndim(angle) == 2 else 1, t.size)
    window = positive_int(window, "window")
    if not is_int(order) or order < 1:
        raise error("order", "an int >= 1", Text(repr(order)), kind=TypeError if not is_int(order) else ValueError)
    if window % 2 == 0 or window <= order or window > t.size:
        raise error("window", f"an odd length > order = {order} and <= N = {t.size}", window)
    steps = np.diff(t)
    h = float(steps.mean())
    if h <= 0 or np.max(np.abs(steps - h)) > 1e-6 * h:
        raise error("t", "uniform, increasing sample times (e.g. Log.t)",
                    Text(f"spacings from {steps.min():.6g} to {steps.max():.6g}"))
    if unwrap:
        values = np.unwrap(values, axis=0)
    return savgol_filter(values, window, int(order), deriv=1, delta=h, axis=0)
