"""Logged data in and out: a CSV log put on a model's uniform grid, and estimates written back.

:func:`read_log` reads the columns it is told to from a CSV file with a header row, validates
them (times strictly increasing, every value finite, the mean sample time close to the model's
``dt``, no gap much longer than ``dt``, values inside an optional box) and resamples them onto
the grid ``t_k = t0 + k dt`` that observers and the EKF expect:

- measurements ``y`` and reference columns are interpolated **linearly** (for a signal with
  ``|f''| <= M`` sampled with spacing at most ``h``, the error is at most ``M h^2 / 8``); angle
  columns are unwrapped first (:func:`numpy.unwrap`), so a pendulum angle logged wrapped to
  ``[-pi, pi]`` becomes continuous and is never interpolated across a jump of ``2 pi``;
- inputs ``u`` are held **zero-order**: ``u_k`` is the last logged value at or before ``t_k``.
  A digital controller holds its output between updates, so the plant saw piecewise-constant
  inputs; a linear interpolation would invent voltages that were never applied (between the two
  levels of a step) and shift every step by half a sample. The hold keeps the applied levels,
  and delays a change logged between two grid points by less than ``dt`` (the model's own
  convention holds ``u_k`` over ``[t_k, t_k+1)``).

:func:`write_estimates` writes estimates as CSV atomically (a temporary file in the same folder,
then :func:`os.replace`), and :func:`savgol_derivative` is the zero-lag velocity reference that
logs of angles are scored against (a Savitzky-Golay derivative on the uniform grid).
"""

from __future__ import annotations

import csv
import io
import itertools
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from .. import provenance
from ..validation import Text, error, finite_number, is_int, nonnegative_number, positive_int, positive_number

__all__ = ["Log", "Resampling", "read_log", "write_estimates", "savgol_derivative", "Y_METHOD", "U_METHOD"]

#: How ``y`` and the reference are put on the grid.
Y_METHOD = "linear (angle columns unwrapped first)"
#: How ``u`` is put on the grid.
U_METHOD = "zero-order hold (last logged value at or before each grid time)"


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
        :data:`Y_METHOD` and :data:`U_METHOD`.
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
        Measurements, linearly interpolated (angle columns unwrapped).
    u : numpy.ndarray, shape (N, nu)
        Inputs, held zero-order; shape (N, 0) without ``u_cols`` (pass ``np.zeros((N, nu))`` to an
        estimator for a run at ``u = 0``).
    reference : numpy.ndarray, shape (N, nr), or None
        Reference columns (e.g. logged velocities), linearly interpolated; None without ``reference_cols``.
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


#: Rows parsed into Python lists before they become one float64 block (bounds the reader's Python objects).
_BLOCK = 65536


def _read_table(path: Path, wanted: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The ``wanted`` columns of a CSV file as floats (n, len(wanted)), and each row's line number; comment
    lines starting with ``#`` before the header row (a provenance stamp) are skipped. The rows are parsed a
    block at a time into float64 arrays (8 bytes per value, not Python lists of floats)."""
    source = str(path)
    with open(path, newline="") as stream:
        skipped, first = 0, stream.readline()
        while first.startswith("#"):
            skipped, first = skipped + 1, stream.readline()
        reader = csv.reader(itertools.chain([first] if first else [], stream))
        header = next(reader, None)
        if header is None:
            raise error(source, "a CSV file with a header row", Text("an empty file"))
        header = [name.strip() for name in header]
        repeated = sorted({name for name in header if header.count(name) > 1})
        if repeated:
            raise error(f"{source}: header", "distinct column names", Text(f"repeated {repeated}"))
        missing = [name for name in wanted if name not in header]
        if missing:
            raise error(f"{source}: columns", f"{missing} among the file's columns", Text(f"columns {header}"),
                        "Pass the names of the file's header row.")
        index = [header.index(name) for name in wanted]
        width = len(header)
        blocks: list[np.ndarray] = []
        line_blocks: list[np.ndarray] = []
        values: list[list[float]] = []
        lines: list[int] = []
        count = 0
        for row in reader:
            if not row:                                   # blank lines carry no sample
                continue
            if len(row) != width:
                raise error(_where(source, count, reader.line_num + skipped), f"{width} fields (one per header "
                            "column)", Text(f"{len(row)} fields"))
            try:
                values.append([float(row[i]) for i in index])
            except ValueError:
                line = reader.line_num + skipped
                for i, name in zip(index, wanted):
                    text = row[i].strip()
                    try:
                        float(text)
                    except ValueError:
                        raise error(_where(source, count, line, name), "a number", text) from None
                raise
            lines.append(reader.line_num + skipped)
            count += 1
            if len(values) == _BLOCK:
                blocks.append(np.array(values, dtype=np.float64))
                line_blocks.append(np.array(lines))
                values, lines = [], []
    if count < 2:
        raise error(source, "at least 2 data rows", Text(f"{count} rows"))
    if values:
        blocks.append(np.array(values, dtype=np.float64))
        line_blocks.append(np.array(lines))
    return np.concatenate(blocks), np.concatenate(line_blocks)


def read_log(path: str | os.PathLike, *, time_col: str, y_cols: Sequence[str], u_cols: Sequence[str] = (),
             reference_cols: Sequence[str] = (), dt: float, angle_cols: Sequence[str] = (),
             t0: Optional[float] = None, max_dt_ratio: float = 1.5,
             box: Optional[Mapping[str, Sequence[float]]] = None, box_margin: float = 0.1) -> Log:
    """Read a CSV log, validate it and resample it onto the grid ``t0 + k dt``.

    Parameters
    ----------
    path : str or path-like
        A CSV file with a header row (comment lines starting with ``#`` before it are skipped); other
        columns are ignored, blank lines skipped.
    time_col : str
        The column of sample times (seconds, strictly increasing, any origin).
    y_cols : sequence of str
        Measurement columns, in the order of the model's outputs.
    u_cols : sequence of str
        Input columns, in the order of the model's inputs (held zero-order, see the module).
    reference_cols : sequence of str
        Further columns to carry along linearly interpolated (e.g. logged velocities to compare with).
    dt : float
        The model's sample period.
    angle_cols : sequence of str
        Columns of ``y_cols`` or ``reference_cols`` that are angles in radians, possibly wrapped:
        they are unwrapped (:func:`numpy.unwrap`, which assumes less than ``pi`` of true motion
        between two samples) before anything else.
    t0 : float, optional
        First grid time, in the log's clock, within the logged times; default the first logged time.
        The grid runs to the last grid time at or before the last logged time.
    max_dt_ratio : float
        The mean logged spacing must lie within ``[dt / max_dt_ratio, dt max_dt_ratio]``, and no
        spacing may exceed ``max_dt_ratio dt`` (a gap would be bridged by interpolation).
    box : mapping {column: (lo, hi)}, optional
        Plausible ranges of read columns (e.g. a plant's ``x0_box`` rows). An angle column is first
        moved by the multiple of ``2 pi`` that brings its mean closest to the middle of its range
        (the dynamics of an angle are ``2 pi``-periodic; the shift is recorded). A logged value
        more than ``box_margin`` times the range's width outside it is an error.
    box_margin : float
        See ``box``.

    Returns
    -------
    Log

    Raises
    ------
    ValueError
        One line naming the file and what is wrong: missing columns (with the file's columns),
        an unparsable or non-finite value (row, line and column), times not strictly increasing
        (the first bad row), a mean spacing far from ``dt`` (both given) or a gap (its row), a
        value outside the box (column, row, value and bound), or ``t0`` outside the log.
    TypeError
        Column arguments that are not sequences of strings, or a box that is not a mapping.
    """
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
    if max_dt_ratio <= 1.0:
        raise error("max_dt_ratio", "a number > 1", max_dt_ratio)
    box_margin = nonnegative_number(box_margin, "box_margin")
    bounds = _box_bounds(box, data_cols)
    if not path.is_file():
        raise error("path", "an existing CSV file", source)

    wanted = (time_col,) + data_cols
    table, lines = _read_table(path, wanted)
    bad = np.argwhere(~np.isfinite(table))
    if bad.size:
        k, c = bad[0]
        raise error(_where(source, int(k), int(lines[k]), wanted[c]), "a finite number", float(table[k, c]))
    t_raw = table[:, 0]
    steps = np.diff(t_raw)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise error(_where(source, k, int(lines[k]), time_col), f"a time after row {k - 1}'s {t_raw[k - 1]!r}",
                    float(t_raw[k]), "Times must be strictly increasing.")
    dt_min, dt_mean, dt_max = float(steps.min()), float(steps.mean()), float(steps.max())
    if not dt / max_dt_ratio <= dt_mean <= dt * max_dt_ratio:
        raise error(f"{source}: column {time_col!r}",
                    f"a mean sample time within a factor {max_dt_ratio:g} of the model's dt = {dt:g} s",
                    Text(f"a mean sample time of {dt_mean:.6g} s (spacings {dt_min:.6g} to {dt_max:.6g} s)"),
                    "Resample the log, or use a model trained at the log's sample time.")
    if dt_max > dt * max_dt_ratio:
        k = int(np.argmax(steps)) + 1
        raise error(_where(source, k, int(lines[k]), time_col),
                    f"spacings of at most max_dt_ratio dt = {dt * max_dt_ratio:.6g} s",
                    Text(f"a gap of {dt_max:.6g} s after row {k - 1}"), "Split the log at the gap.")

    columns = {name: table[:, 1 + i].copy() for i, name in enumerate(data_cols)}
    shifts = []
    for name in angle_cols:
        columns[name] = np.unwrap(columns[name])
        shift = 0.0
        if name in bounds:
            lo, hi = bounds[name]
            shift = 2.0 * math.pi * round((0.5 * (lo + hi) - float(columns[name].mean())) / (2.0 * math.pi))
            columns[name] = columns[name] + shift
        shifts.append(shift)
    for name, (lo, hi) in bounds.items():
        margin = box_margin * (hi - lo)
        values = columns[name]
        outside = (values < lo - margin) | (values > hi + margin)
        if outside.any():
            k = int(np.argmax(outside))
            side = f"below lo = {lo:g}" if values[k] < lo else f"above hi = {hi:g}"
            raise error(_where(source, k, int(lines[k]), name),
                        f"values within the box [{lo:g}, {hi:g}] widened by {box_margin:g} of its width",
                        Text(f"{values[k]:.6g}, {side}"))

    t0 = float(t_raw[0]) if t0 is None else finite_number(t0, "t0")
    if not t_raw[0] <= t0 < t_raw[-1]:
        raise error("t0", f"a time within the log [{t_raw[0]:.6g}, {t_raw[-1]:.6g})", t0)
    t = t0 + np.arange(int(math.floor((t_raw[-1] - t0) / dt * (1.0 + 1e-12))) + 1) * dt
    t = t[t <= t_raw[-1]]                                 # the grid never extrapolates
    if t.size < 2:
        raise error("t0", f"a time at least dt = {dt:g} s before the last logged time {t_raw[-1]:.6g}", t0)

    def linear(names: tuple[str, ...]) -> np.ndarray:
        return np.column_stack([np.interp(t, t_raw, columns[name]) for name in names]) if names \
            else np.zeros((t.size, 0))

    held = np.searchsorted(t_raw, t, side="right") - 1
    y = linear(y_cols)
    u = np.column_stack([columns[name][held] for name in u_cols]) if u_cols else np.zeros((t.size, 0))
    reference = linear(reference_cols) if reference_cols else None
    for array in (t, y, u, reference):
        if array is not None:
            array.setflags(write=False)
    record = Resampling(dt, t0, int(t_raw.size), float(t_raw[0]), float(t_raw[-1]), dt_min, dt_mean, dt_max,
                        Y_METHOD, U_METHOD, angle_cols, tuple(shifts))
    names = {"time": (time_col,), "y": y_cols, "u": u_cols, "reference": reference_cols}
    return Log(t, y, u, reference, names, source, record)


def _finite(value: Any, argument: str, ndim: int, n: Optional[int] = None) -> np.ndarray:
    """``value`` as float64 with ``ndim`` axes (the first of length ``n`` if given), all finite."""
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != ndim or (n is not None and array.shape[0] != n) or array.shape[0] == 0:
        rows = "N" if n is None else str(n)
        expected = f"shape ({rows},)" if ndim == 1 else f"shape ({rows}, k)"
        raise error(argument, expected, Text(f"shape {array.shape}"))
    bad = np.argwhere(~np.isfinite(array))
    if bad.size:
        where = f"row {bad[0][0]}" + (f", column {bad[0][1]}" if array.ndim == 2 else "")
        raise error(argument, "finite values", Text(f"{array[tuple(bad[0])]} at {where}"))
    return array


def write_estimates(path: str | os.PathLike, t: Any, xhat: Any, *, state_names: Sequence[str],
                    in_domain: Any = None, extra: Optional[Mapping[str, Any]] = None,
                    stamp: Optional[provenance.Stamp] = None) -> Path:
    """Write estimates as a CSV file, atomically.

    A first line ``# provenance {...}`` holds the stamp (:mod:`kklcasadi.provenance`; ``stamp``,
    default this process's), then the header row (:func:`read_log` skips the comment). Columns:
    ``time``, the ``state_names``, then ``in_domain`` (0/1) if given, then the ``extra`` columns in
    their order. Numbers are written with :func:`repr`, so reading them back gives the same floats.
    Everything is validated before the file is touched; the text goes, a block of rows at a time, to
    a temporary file in the same folder, which then replaces ``path`` (:func:`os.replace`): a failure
    leaves an existing file as it was and no temporary file behind.

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
    extra : mapping {name: array_like (N,)}, optional
        Further finite columns (e.g. reference velocities).

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    path = Path(path)
    t = _finite(t, "t", 1)
    n = t.size
    xhat = _finite(xhat, "xhat", 2, n)
    names = _names(state_names, "state_names", allow_empty=False)
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
    if extra is not None:
        if not isinstance(extra, Mapping):
            raise error("extra", "a mapping {name: values (N,)}", Text(type(extra).__name__), kind=TypeError)
        _names(list(extra), "extra", allow_empty=True)
        for name, values in extra.items():
            header.append(name)
            body.append(_finite(values, f"extra[{name!r}]", 1, n))
    repeated = sorted({name for name in header if header.count(name) > 1})
    if repeated:
        raise error("state_names, extra", "names distinct from each other and from 'time', 'in_domain'",
                    Text(f"repeated {repeated}"))
    text = io.StringIO(provenance.csv_comment(stamp or provenance.stamp()))
    text.seek(0, io.SEEK_END)
    csv.writer(text, lineterminator="\n").writerow(header)

    if not path.parent.is_dir():
        raise error("path", "a file in an existing folder", str(path))
    handle, temp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "w", newline="") as stream:
            stream.write(text.getvalue())
            for start in range(0, n, _BLOCK):             # Python floats repr as the shortest round trip
                columns = [column[start:start + _BLOCK].tolist() for column in body]
                stream.write("".join(",".join(map(repr, row)) + "\n" for row in zip(*columns)))
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temp, path)
    except BaseException:
        Path(temp).unlink(missing_ok=True)
        raise
    return path


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
