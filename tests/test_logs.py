"""kklcasadi.plant.logs on synthetic jittered logs with known signals, and the Qube plant on its real logs."""

import csv
import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import interp1d

import kklcasadi as kc
from kklcasadi import provenance
from kklcasadi.plant import logs

ROOT = Path(__file__).resolve().parents[1]
QUBE = ROOT / "examples" / "qube"
DT = 0.004


def jittered_times(seed, n, start=3.2):
    """Spacings uniform in [3.1, 4.9] ms about a mean of 4 ms, as on the Qube's logs."""
    rng = np.random.default_rng(seed)
    return start + np.concatenate([[0.0], np.cumsum(DT + rng.uniform(-0.9e-3, 0.9e-3, n - 1))])


def write_csv(path, header, columns):
    with open(path, "w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(header)
        for row in zip(*columns):
            writer.writerow([v if isinstance(v, str) else repr(float(v)) for v in row])
    return path


def wrap(a):
    return np.angle(np.exp(1j * a))                    # to [-pi, pi], as the rig logs angles


# --- resampling ---------------------------------------------------------------------------------

@pytest.mark.parametrize("seed, omega", [(0, 5.0), (1, 20.0), (2, 60.0)])
def test_linear_resampling_is_within_the_interpolation_bound(tmp_path, seed, omega):
    t_raw = jittered_times(seed, 1500)
    columns = [t_raw, np.sin(omega * t_raw), 2 * np.cos(omega * t_raw)]
    path = write_csv(tmp_path / "log.csv", ["time", "s", "c"], columns)
    log = logs.read_log(path, time_col="time", y_cols=["s", "c"], dt=DT)
    # the grid: from the first logged time, spaced by dt, never past the last logged time
    assert log.t[0] == t_raw[0] and log.t[-1] <= t_raw[-1] < log.t[-1] + DT
    np.testing.assert_allclose(np.diff(log.t), DT, rtol=1e-9)
    # linear interpolation of f with |f''| <= M over spacings <= h errs by at most M h^2 / 8
    h = np.diff(t_raw).max()
    for column, amplitude, truth in ((0, 1.0, np.sin(omega * log.t)), (1, 2.0, 2 * np.cos(omega * log.t))):
        bound = amplitude * omega ** 2 * h ** 2 / 8
        assert np.max(np.abs(log.y[:, column] - truth)) <= bound * (1 + 1e-9) + 1e-14
    # and it is the linear interpolant (an independent implementation)
    reference = interp1d(t_raw, np.column_stack([np.sin(omega * t_raw), 2 * np.cos(omega * t_raw)]), axis=0)(log.t)
    np.testing.assert_allclose(log.y, reference, rtol=0, atol=1e-14)
    record = log.resampling
    steps = np.diff(t_raw)
    assert (record.n_raw, record.dt_min, record.dt_max) == (1500, steps.min(), steps.max())
    assert record.dt_mean == pytest.approx(steps.mean(), rel=1e-15)
    assert log.u.shape == (log.t.size, 0) and log.reference is None
    assert log.columns == {"time": ("time",), "y": ("s", "c"), "u": (), "reference": ()}
    assert not log.y.flags.writeable


def test_inputs_are_held_zero_order(tmp_path):
    t_raw = jittered_times(3, 800)
    u_sin = np.sin(7.0 * t_raw)
    u_step = np.where(t_raw >= t_raw[0] + 1.0011, 1.5, -0.5)
    path = write_csv(tmp_path / "log.csv", ["time", "y", "u1", "u2"], [t_raw, np.cos(t_raw), u_sin, u_step])
    log = logs.read_log(path, time_col="time", y_cols=("y",), u_cols=("u1", "u2"), dt=DT)
    # u_k is the last logged value at or before t_k (written as a loop, independently)
    last = np.array([max(i for i in range(t_raw.size) if t_raw[i] <= tk) for tk in log.t])
    np.testing.assert_array_equal(log.u, np.column_stack([u_sin[last], u_step[last]]))
    # the hold errs by at most max|u'| h on a smooth input, and keeps a step's two levels
    assert np.max(np.abs(log.u[:, 0] - np.sin(7.0 * log.t))) <= 7.0 * np.diff(t_raw).max()
    assert set(np.unique(log.u[:, 1])) == {-0.5, 1.5}
    switch = t_raw[np.argmax(u_step > 0)]
    assert np.all(log.u[log.t < switch, 1] == -0.5) and np.all(log.u[log.t >= switch, 1] == 1.5)


def test_t0_starts_the_grid_later(tmp_path):
    t_raw = jittered_times(4, 500)
    path = write_csv(tmp_path / "log.csv", ["time", "y"], [t_raw, t_raw ** 2])
    log = logs.read_log(path, time_col="time", y_cols=("y",), dt=DT, t0=4.0)
    assert log.t[0] == 4.0 and log.resampling.t0 == 4.0
    np.testing.assert_allclose(log.y[:, 0], log.t ** 2, atol=2 * np.diff(t_raw).max() ** 2 / 8)


# --- logs faster than the model: the input averaged over each interval -------------------------

def _zoh_mean_by_hand(t_raw, u_raw, start, dt):
    """(1/dt) * integral over [start, start + dt] of the log's zero-order hold (held past the end), in a plain loop."""
    total = 0.0
    for i in range(len(t_raw)):
        right = t_raw[i + 1] if i + 1 < len(t_raw) else math.inf
        overlap = min(right, start + dt) - max(t_raw[i], start)
        if overlap > 0:
            total += u_raw[i] * overlap
    return total / dt


def test_a_1khz_log_decimated_to_10ms_by_hand(tmp_path):
    """1 kHz samples, a 10 ms model: u_k is the mean of the 10 logged values of [t_k, t_k + 10 ms), y_k the
    sample at t_k."""
    t_raw = np.arange(201) * 1e-3
    u_raw = (np.arange(201) % 7) - 3.0 + 0.25 * (np.arange(201) % 2)      # a staircase no interpolation reproduces
    y_raw = np.sin(9.0 * t_raw)
    path = write_csv(tmp_path / "fast.csv", ["time", "y", "u"], [t_raw, y_raw, u_raw])
    log = logs.read_log(path, time_col="time", y_cols=("y",), u_cols=("u",), dt=0.01)
    assert log.resampling.u_method == logs.U_MEAN and log.t.size == 21
    np.testing.assert_allclose(log.t, np.arange(21) * 0.01, rtol=0, atol=1e-15)
    assert log.u[0, 0] == pytest.approx(np.mean(u_raw[0:10]), abs=1e-12)
    assert np.mean(u_raw[0:10]) == pytest.approx((-3 - 1.75 - 1 + 0.25 + 1 + 2.25 + 3 - 2.75 - 2 - 0.75) / 10,
                                                 abs=1e-15)
    for k in range(20):
        assert log.u[k, 0] == pytest.approx(np.mean(u_raw[10 * k:10 * k + 10]), abs=1e-12)
    assert log.u[20, 0] == u_raw[200]                       # the last sample held past the end of the log
    np.testing.assert_allclose(log.y[:, 0], y_raw[::10], rtol=0, atol=1e-12)   # sampled at the grid times


def test_a_1khz_log_on_a_2_5ms_grid_by_hand(tmp_path):
    """Not an integer multiple: each 2.5 ms interval holds two whole samples and two halves."""
    t_raw = np.arange(12) * 1e-3
    u_raw = np.arange(12, dtype=float) ** 2                    # 0, 1, 4, 9, 16, 25, ...
    path = write_csv(tmp_path / "fast.csv", ["time", "y", "u"], [t_raw, -t_raw, u_raw])
    log = logs.read_log(path, time_col="time", y_cols=("y",), u_cols=("u",), dt=0.0025)
    # [0, 2.5 ms]: (0*1 + 1*1 + 4*0.5) / 2.5 = 1.2; [2.5, 5]: (4*0.5 + 9*1 + 16*1) / 2.5 = 10.8;
    # [5, 7.5]: (25 + 36 + 49*0.5) / 2.5 = 34.2; [7.5, 10]: (49*0.5 + 64 + 81) / 2.5 = 67.8
    np.testing.assert_allclose(log.u[:4, 0], [1.2, 10.8, 34.2, 67.8], rtol=1e-13)
    np.testing.assert_allclose(log.y[:, 0], -log.t, atol=1e-15)      # y at 1.25 ms etc.: linear between samples


@pytest.mark.parametrize("seed, dt", [(0, 0.01), (1, 0.0073), (2, 0.0031)])
def test_a_jittered_fast_log_carries_the_same_impulse(tmp_path, seed, dt):
    rng = np.random.default_rng(seed)
    t_raw = 0.4 + np.concatenate([[0.0], np.cumsum(1e-3 + rng.uniform(-3e-4, 3e-4, 1999))])
    u_raw = np.column_stack([rng.normal(size=2000), np.where(t_raw > 1.0, 2.0, -1.0)])
    path = write_csv(tmp_path / "fast.csv", ["time", "y", "a", "b"], [t_raw, np.cos(t_raw), *u_raw.T])
    t0 = 0.4 + 0.37 * dt
    log = logs.read_log(path, time_col="time", y_cols=("y",), u_cols=("a", "b"), dt=dt, t0=t0)
    assert log.resampling.u_method == logs.U_MEAN
    # each u_k against the integral written as a plain loop (an independent implementation)
    by_hand = np.array([[_zoh_mean_by_hand(t_raw, u_raw[:, j], tk, dt) for j in range(2)] for tk in log.t])
    np.testing.assert_allclose(log.u, by_hand, rtol=0, atol=1e-11)
    # the impulse over the whole grid is the log's, and the step's two levels and its impulse are kept
    assert np.sum(log.u[:, 0]) * dt == pytest.approx(_zoh_mean_by_hand(t_raw, u_raw[:, 0], t0, log.t.size * dt)
                                                     * log.t.size * dt, abs=1e-10)
    assert log.u[:, 1].min() == -1.0 and log.u[:, 1].max() == 2.0
    assert np.sum((log.u[:, 1] > -1.0) & (log.u[:, 1] < 2.0)) <= 1       # one interval straddles the step
    np.testing.assert_allclose(log.y[:, 0], np.cos(log.t), atol=np.diff(t_raw).max() ** 2 / 8 + 1e-14)


def test_a_constant_input_stays_exactly_constant(tmp_path):
    t_raw = np.cumsum(np.full(500, 1.0 / 1024))
    path = write_csv(tmp_path / "fast.csv", ["time", "y", "u"], [t_raw, t_raw, np.full(500, 0.3)])
    log = logs.read_log(path, time_col="time", y_cols=("y",), u_cols=("u",), dt=0.01)
    assert np.all(log.u == 0.3)


def test_a_log_at_the_models_rate_keeps_the_hold(tmp_path):
    """Within RATE_TOLERANCE of dt the log is at the model's rate (jitter): u is held, not averaged."""
    t_raw = jittered_times(9, 300)
    u_raw = np.sin(5.0 * t_raw)
    path = write_csv(tmp_path / "log.csv", ["time", "y", "u"], [t_raw, t_raw, u_raw])
    for dt in (DT, DT * 1.04, DT / 1.04):
        log = logs.read_log(path, time_col="time", y_cols=("y",), u_cols=("u",), dt=dt)
        assert log.resampling.u_method == logs.U_HOLD
        np.testing.assert_array_equal(log.u[:, 0], u_raw[np.searchsorted(t_raw, log.t, side="right") - 1])
    faster = logs.read_log(path, time_col="time", y_cols=("y",), u_cols=("u",), dt=DT * 1.06)
    assert faster.resampling.u_method == logs.U_MEAN


# --- angles -------------------------------------------------------------------------------------

def test_wrapped_angles_crossing_pi_many_times_are_unwrapped(tmp_path):
    t_raw = jittered_times(5, 3000)
    tau = t_raw - t_raw[0]
    alpha = 3.0 + 2.5 * np.sin(3.0 * tau) + 8.0 * tau        # spins and swings: many +-pi crossings
    beta = -2.0 - 6.0 * tau                                   # a reference column spinning the other way
    logged = wrap(alpha)
    assert np.sum(np.abs(np.diff(logged)) > np.pi) >= 15
    path = write_csv(tmp_path / "log.csv", ["time", "alpha", "beta"], [t_raw, logged, wrap(beta)])
    log = logs.read_log(path, time_col="time", y_cols=("alpha",), reference_cols=("beta",),
                        angle_cols=("alpha", "beta"), dt=DT)
    grid = log.t - t_raw[0]
    # without a box the first sample keeps its logged value, and the series is continuous from it
    truth = 3.0 + 2.5 * np.sin(3.0 * grid) + 8.0 * grid
    bound = 2.5 * 9.0 * np.diff(t_raw).max() ** 2 / 8
    assert np.max(np.abs(log.y[:, 0] - truth)) <= bound + 1e-12
    np.testing.assert_allclose(log.reference[:, 0], -2.0 - 6.0 * grid, atol=1e-12)
    assert log.resampling.angle_cols == ("alpha", "beta") and log.resampling.angle_shifts == (0.0, 0.0)
    # interpolating the wrapped series instead would cut across every jump
    assert np.max(np.abs(np.interp(log.t, t_raw, logged) - wrap(truth))) > 1.0


def test_a_box_moves_an_angle_onto_its_branch(tmp_path):
    t_raw = jittered_times(6, 1000)
    alpha = np.pi + 2.5 * np.sin(5.0 * (t_raw - t_raw[0]) + 2.0)   # a pendulum swinging about hanging
    logged = wrap(alpha)
    assert logged[0] < 0                                             # starts on the -pi side
    path = write_csv(tmp_path / "log.csv", ["time", "alpha"], [t_raw, logged])
    plain = logs.read_log(path, time_col="time", y_cols=("alpha",), angle_cols=("alpha",), dt=DT)
    boxed = logs.read_log(path, time_col="time", y_cols=("alpha",), angle_cols=("alpha",), dt=DT,
                          box={"alpha": (np.pi - 2.8, np.pi + 2.8)})
    np.testing.assert_allclose(boxed.y, plain.y + 2 * np.pi, atol=1e-12)
    assert boxed.resampling.angle_shifts == (2 * np.pi,)
    truth = np.pi + 2.5 * np.sin(5.0 * (boxed.t - t_raw[0]) + 2.0)
    assert np.max(np.abs(boxed.y[:, 0] - truth)) <= 2.5 * 25.0 * np.diff(t_raw).max() ** 2 / 8 + 1e-12


# --- malformed logs -----------------------------------------------------------------------------

def _good(n=40):
    t = jittered_times(7, n)
    return ["time", "theta", "alpha"], [list(t), list(0.5 * np.sin(t)), list(np.cos(t))]


def _edit(kind):
    """A malformed log: (header, columns, read_log keywords, the message's pattern)."""
    header, cols = _good()
    options = {}
    if kind == "decreasing time":
        cols[0][7] = cols[0][6] - 1e-4
        pattern = r"row 7 \(line 9\), column 'time': expected a time after row 6's .*Times must be strictly"
    elif kind == "repeated time":
        cols[0][12] = cols[0][11]
        pattern = r"row 12 \(line 14\), column 'time': expected a time after row 11's"
    elif kind == "missing column":
        header[2] = "beta"
        pattern = (r"^y_cols: expected a column of .*bad\.csv, received 'alpha'\. "
                   r"Its header holds \['time', 'theta', 'beta'\]\.$")
    elif kind == "nan":
        cols[1][5] = float("nan")
        pattern = r"row 5 \(line 7\), column 'theta': expected a finite number, received nan"
    elif kind == "inf":
        cols[2][9] = float("-inf")
        pattern = r"row 9 \(line 11\), column 'alpha': expected a finite number, received -inf"
    elif kind == "text":
        cols[2][3] = "abc"
        pattern = (r"row 3 \(line 5\), column 'alpha': expected a plain decimal number \(digits, '\.', an "
                   r"exponent\), received 'abc'")
    elif kind == "empty field":
        cols[1][4] = ""
        pattern = r"row 4 \(line 6\), column 'theta': expected a plain decimal number .*, received ''"
    elif kind == "slow log":
        options = {"dt": 0.001}
        pattern = (r"column 'time': expected a log at least as fast as the model: a median sample time of at most "
                   r"dt = 0.001 s \(\+5% for jitter\), received a median sample time of 0.00[34]\d* s \(spacings .*"
                   r"use a model trained at the log's rate \(kklcasadi train --dt 0.00[34]\d*\)\.$")
    elif kind == "slightly slow log":
        options = {"dt": DT / 1.06}
        pattern = r"expected a log at least as fast as the model: a median sample time of at most dt = 0.00377"
    elif kind == "gap":
        for c in cols:
            del c[20:24]
        pattern = r"row 20 \(line 22\), column 'time': expected spacings of at most .* received a gap of 0.0\d+ s"
    elif kind == "outside the box":
        cols[1][17] = 3.0
        options = {"box": {"theta": (-1.0, 1.0)}}
        pattern = (r"row 17 \(line 19\), column 'theta': expected values within the box \[-1, 1\] .* "
                   r"received 3, above hi = 1")
    elif kind == "below the box":
        cols[2][2] = -2.5
        options = {"box": {"alpha": (-1.0, 1.0)}}
        pattern = r"row 2 \(line 4\), column 'alpha': .* received -2.5, below lo = -1"
    elif kind == "t0 outside":
        options = {"t0": 100.0}
        pattern = r"^t0: expected a time within the log \[3.2, "
    else:
        raise KeyError(kind)
    return header, cols, options, pattern


@pytest.mark.parametrize("kind", ["decreasing time", "repeated time", "missing column", "nan", "inf", "text",
                                  "empty field", "slow log", "slightly slow log", "gap", "outside the box",
                                  "below the box", "t0 outside"])
def test_malformed_logs_name_the_row_and_column(tmp_path, kind):
    header, cols, options, pattern = _edit(kind)
    path = write_csv(tmp_path / "bad.csv", header, cols)
    keywords = {"time_col": "time", "y_cols": ("theta", "alpha"), "dt": DT, **options}
    with pytest.raises(ValueError, match=pattern) as caught:
        logs.read_log(path, **keywords)
    assert "\n" not in str(caught.value)


def test_a_value_just_outside_the_box_is_within_its_margin(tmp_path):
    header, cols = _good()
    cols[1][17] = 1.15                                   # 0.15 outside a box of width 2: within 10 %
    path = write_csv(tmp_path / "log.csv", header, cols)
    log = logs.read_log(path, time_col="time", y_cols=("theta",), dt=DT, box={"theta": (-1.0, 1.0)})
    assert log.y.shape[1] == 1
    with pytest.raises(ValueError, match="column 'theta'"):
        logs.read_log(path, time_col="time", y_cols=("theta",), dt=DT, box={"theta": (-1.0, 1.0)}, box_margin=0.05)


@pytest.mark.parametrize("text, pattern", [
    ("", r"expected a CSV file with a header row, received an empty file"),
    ("time,theta\n0.0,1.0\n", r"expected at least 2 data rows, received 1 rows"),
    ("time,theta,theta\n0,1,2\n0.004,1,2\n", r"header: expected distinct column names, received repeated \['theta'\]"),
    ("time,theta\n0,1\n0.004\n0.008,1\n", r"row 1 \(line 3\): expected 2 fields \(one per header column\), received 1"),
])
def test_malformed_files(tmp_path, text, pattern):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=pattern):
        logs.read_log(path, time_col="time", y_cols=("theta",), dt=DT)


# --- what a field may hold: plain decimal numbers ---------------------------------------------

@pytest.mark.parametrize("text, value", [
    ("1", 1.0), ("-2.5", -2.5), ("+.5", 0.5), ("3.", 3.0), ("1e3", 1000.0), ("-1.25E-2", -0.0125), (" 7 ", 7.0),
    ("\t0.125", 0.125), ('"2.5"', 2.5), ("1e308", 1e308),
])
def test_plain_decimal_numbers_are_read(tmp_path, text, value):
    path = tmp_path / "log.csv"
    path.write_text(f"time,y\n0,0\n0.004,{text}\n0.008,0\n", encoding="utf-8")
    assert logs.read_log(path, time_col="time", y_cols=("y",), dt=DT).y[1, 0] == value


@pytest.mark.parametrize("text", ["1_000", "\u0661\u0662", "\u0968", "0x10", "1.0.5", "1.5.5", "1e", "e3", "--1", "1,5",
                                  "\u00a01", "1 2", "\uff11", "1d3", "inf1", "\u2212" + "1", "."])
def test_anything_else_is_refused_in_one_line(tmp_path, text):
    """``1_000``, Arabic-Indic and Devanagari digits, hex, a second point: Python's float() takes several, the log
    does not."""
    path = tmp_path / "log.csv"
    path.write_text(f'time,y,z\n0,0,0\n0.004,"{text}",0\n0.008,0,0\n', encoding="utf-8")
    with pytest.raises(ValueError) as caught:
        logs.read_log(path, time_col="time", y_cols=("y",), dt=DT)
    message = str(caught.value)
    assert "\n" not in message
    assert re.search(r"log\.csv: row 1 \(line 3\), column 'y': expected a plain decimal number", message), message


@pytest.mark.parametrize("text", ["nan", "-inf", "Infinity", "NaN"])
def test_non_finite_words_are_refused_as_not_finite(tmp_path, text):
    path = tmp_path / "log.csv"
    path.write_text(f"time,y\n0,0\n0.004,{text}\n0.008,0\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"row 1 \(line 3\), column 'y': expected a finite number, received"):
        logs.read_log(path, time_col="time", y_cols=("y",), dt=DT)


def test_a_byte_order_mark_is_dropped_and_the_first_row_kept(tmp_path):
    path = tmp_path / "bom.csv"
    path.write_bytes("\ufefftime,y\r\n0,1.5\r\n0.004,2.5\r\n0.008,3.5\r\n".encode("utf-8"))
    log = logs.read_log(path, time_col="time", y_cols=("y",), dt=DT)
    assert log.resampling.n_raw == 3 and log.y[0, 0] == 1.5


def test_comment_and_blank_lines_are_skipped_and_lines_still_counted(tmp_path):
    path = tmp_path / "log.csv"
    path.write_text("# made by a rig\ntime,y\n0,1\n\n# a note\n0.004,2\n0.008,x\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"row 2 \(line 7\), column 'y'"):
        logs.read_log(path, time_col="time", y_cols=("y",), dt=DT)
    path.write_text("# made by a rig\ntime,y\n0,1\n\n# a note\n0.004,2\n0.008,3\n", encoding="utf-8")
    np.testing.assert_array_equal(logs.read_log(path, time_col="time", y_cols=("y",), dt=DT).y[:, 0], [1, 2, 3])


@pytest.mark.parametrize("content, pattern", [
    (b"time,y\n0,1\n0.004," + b"1" * 131073 + b"\n", r"line 3: expected fields of at most 131072 characters"),
    (b"time,y,note\n0,1," + b"x" * 200000 + b"\n0.004,2,a\n", r"line 2: expected fields of at most 131072"),
    (b"time,y\n0,1\n0.004,\xff\xfe2\n", r"line \d: expected UTF-8 text, received bytes that are not UTF-8"),
    (b'time,y\n0,1\n0.004,"2\n0.008,3\n', r"line \d: expected a well-formed CSV row, received unexpected end of data"),
    (b'time,y\n0,1\n0.004,"2"3\n0.008,3\n', r"line 3: expected a well-formed CSV row, received ',' expected"),
    (b"time,y\n0,1\n0.004,2\x00\n0.008,3\n", r"row 1 \(line 3\), column 'y': expected a plain decimal number"),
])
def test_hostile_files_are_one_line_errors(tmp_path, content, pattern):
    path = tmp_path / "bad.csv"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=pattern) as caught:
        logs.read_log(path, time_col="time", y_cols=("y",), dt=DT)
    assert "\n" not in str(caught.value) and len(str(caught.value)) < 400


def test_columns_are_matched_by_name_in_any_order(tmp_path):
    t_raw = np.arange(100) * 1e-3
    a, b = np.sin(t_raw), np.cos(3 * t_raw)
    one = logs.read_log(write_csv(tmp_path / "one.csv", ["time", "y", "u"], [t_raw, a, b]), time_col="time",
                        y_cols=("y",), u_cols=("u",), dt=0.004)
    two = logs.read_log(write_csv(tmp_path / "two.csv", ["u", "extra", "y", "time"], [b, a * 7, a, t_raw]),
                        time_col="time", y_cols=("y",), u_cols=("u",), dt=0.004)
    np.testing.assert_array_equal(one.y, two.y)
    np.testing.assert_array_equal(one.u, two.u)


@pytest.mark.parametrize("argument, keywords", [
    ("time_col", {"time_col": "t"}), ("y_cols", {"y_cols": ("alpha", "gamma")}), ("u_cols", {"u_cols": ("Vm",)}),
    ("reference_cols", {"reference_cols": ("alpha_dot",)}),
])
def test_a_missing_column_names_the_argument_that_asked_for_it(tmp_path, argument, keywords):
    header, cols = _good()
    path = write_csv(tmp_path / "log.csv", header, cols)
    with pytest.raises(ValueError, match=rf"^{argument}: expected a column of .*log\.csv, received '\w+'\. Its "
                                         r"header holds \['time', 'theta', 'alpha'\]\.$"):
        logs.read_log(path, **{"time_col": "time", "y_cols": ("theta",), "dt": DT, **keywords})


@pytest.mark.parametrize("keywords, kind, pattern", [
    ({"y_cols": "theta"}, TypeError, r"^y_cols: expected a list or tuple of column names, received str"),
    ({"y_cols": ()}, ValueError, r"^y_cols: expected at least one column name"),
    ({"y_cols": ("theta",), "u_cols": ("theta",)}, ValueError, r"distinct columns other than time_col"),
    ({"y_cols": ("theta",), "angle_cols": ("alpha",)}, ValueError, r"^angle_cols: expected columns of y_cols"),
    ({"y_cols": ("theta",), "dt": 0.0}, ValueError, r"^dt: expected a finite number > 0"),
    ({"y_cols": ("theta",), "max_dt_ratio": 1.05}, ValueError, r"^max_dt_ratio: expected a number > 1 \+ "
                                                                    r"RATE_TOLERANCE = 1\.05"),
    ({"y_cols": ("theta",), "box": {"beta": (0, 1)}}, ValueError, r"^box: expected columns among those read"),
    ({"y_cols": ("theta",), "box": {"theta": (1, 0)}}, ValueError, r"^box\['theta'\]: expected finite \(lo, hi\)"),
    ({"y_cols": ("theta",), "box": [(0, 1)]}, TypeError, r"^box: expected a mapping"),
])
def test_bad_arguments(tmp_path, keywords, kind, pattern):
    header, cols = _good()
    path = write_csv(tmp_path / "log.csv", header, cols)
    with pytest.raises(kind, match=pattern):
        logs.read_log(path, **{"time_col": "time", "dt": DT, **keywords})


def test_a_missing_file_is_named(tmp_path):
    with pytest.raises(ValueError, match=r"^path: expected an existing CSV file, received '.*nowhere.csv'"):
        logs.read_log(tmp_path / "nowhere.csv", time_col="time", y_cols=("theta",), dt=DT)


# --- writing estimates --------------------------------------------------------------------------

def test_write_read_round_trip(tmp_path):
    rng = np.random.default_rng(8)
    t = 2.5 + np.arange(300) * DT
    xhat = rng.normal(size=(300, 3)) * np.array([1.0, 1e-7, 1e5])
    in_domain = rng.random(300) > 0.2
    reference = rng.normal(size=300)
    path = logs.write_estimates(tmp_path / "est.csv", t, xhat, state_names=("a", "b", "c"), in_domain=in_domain,
                                extra={"ref": reference})
    with open(path, newline="") as stream:
        comment, rows = stream.readline(), list(csv.reader(stream))
    assert comment.startswith("# provenance {") and provenance.read(path).command     # the stamp, then the header
    assert rows[0] == ["time", "a", "b", "c", "in_domain", "ref"]
    assert {r[4] for r in rows[1:]} == {"0", "1"}
    log = logs.read_log(path, time_col="time", y_cols=("a", "b", "c"), reference_cols=("in_domain", "ref"), dt=DT)
    np.testing.assert_array_equal(log.t, t)
    np.testing.assert_array_equal(log.y, xhat)
    np.testing.assert_array_equal(log.reference, np.column_stack([in_domain, reference]))


def _old_file(tmp_path):
    path = logs.write_estimates(tmp_path / "est.csv", [0.0, 0.1], [[1.0], [2.0]], state_names=("x",))
    return path, path.read_bytes()


def test_rejected_estimates_leave_the_old_file(tmp_path):
    path, before = _old_file(tmp_path)
    with pytest.raises(ValueError, match=r"^xhat: expected finite values, received nan at row 1, column 0"):
        logs.write_estimates(path, [0.0, 0.1, 0.2], [[1.0], [np.nan], [3.0]], state_names=("x",))
    with pytest.raises(ValueError, match=r"^state_names: expected 1 names"):
        logs.write_estimates(path, [0.0, 0.1], [[1.0], [2.0]], state_names=("x", "y"))
    with pytest.raises(ValueError, match=r"repeated \['time'\]"):
        logs.write_estimates(path, [0.0, 0.1], [[1.0], [2.0]], state_names=("time",))
    with pytest.raises(ValueError, match=r"^in_domain: expected 2 booleans"):
        logs.write_estimates(path, [0.0, 0.1], [[1.0], [2.0]], state_names=("x",), in_domain=[0.5, 1.0])
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["est.csv"]


def test_estimates_are_written_over_a_file_only_with_overwrite(tmp_path):
    path, before = _old_file(tmp_path)
    with pytest.raises(FileExistsError, match=r"^path: .*est.csv exists; pass overwrite to replace it"):
        logs.write_estimates(path, [0.0, 0.1], [[5.0], [6.0]], state_names=("x",))
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["est.csv"]
    logs.write_estimates(path, [0.0, 0.1], [[5.0], [6.0]], state_names=("x",), overwrite=True)
    assert logs.read_log(path, time_col="time", y_cols=("x",), dt=0.1).y[:, 0].tolist() == [5.0, 6.0]


@pytest.mark.parametrize("failing, overwrite", [("replace", True), ("fsync", True), ("link", False),
                                                ("fsync", False)])
def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch, failing, overwrite):
    path, before = _old_file(tmp_path)

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(logs.os, failing, boom)
    with pytest.raises(OSError, match="disk full"):
        logs.write_estimates(path if overwrite else tmp_path / "new.csv", [0.0, 0.1, 0.2], [[5.0], [6.0], [7.0]],
                             state_names=("x",), overwrite=overwrite)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["est.csv"]
    assert os.path.exists(path)


def test_writing_into_a_missing_folder_is_named(tmp_path):
    with pytest.raises(ValueError, match=r"^path: expected a file in an existing folder"):
        logs.write_estimates(tmp_path / "no" / "est.csv", [0.0, 0.1], [[1.0], [2.0]], state_names=("x",))


# --- the Savitzky-Golay velocity reference ------------------------------------------------------

def test_savgol_derivative_is_exact_on_cubics_and_close_on_a_swing():
    t = 1.0 + np.arange(400) * DT
    cubic = np.column_stack([2 - t + 0.5 * t ** 2 - 0.3 * t ** 3, t ** 3])
    np.testing.assert_allclose(logs.savgol_derivative(t, cubic),
                               np.column_stack([-1 + t - 0.9 * t ** 2, 3 * t ** 2]), rtol=0, atol=1e-8)
    swing = logs.savgol_derivative(t, 2.5 * np.sin(6.0 * t))
    # the cubic fit over 15 samples (56 ms) of a 6 rad/s swing: the error is far below its 15 rad/s peak
    assert swing.shape == t.shape and np.max(np.abs(swing - 15.0 * np.cos(6.0 * t))) < 0.05


def test_savgol_derivative_unwraps_angles():
    t = np.arange(500) * DT
    spin = 1.0 + 20.0 * t + 0.5 * np.sin(4 * t)
    np.testing.assert_allclose(logs.savgol_derivative(t, wrap(spin)), logs.savgol_derivative(t, spin), atol=1e-9)
    assert np.max(np.abs(logs.savgol_derivative(t, wrap(spin), unwrap=False))) > 100


@pytest.mark.parametrize("keywords, pattern", [
    ({"window": 14}, r"^window: expected an odd length > order = 3 and <= N = 50"),
    ({"window": 51}, r"^window: expected an odd length"),
    ({"window": 3}, r"^window: expected an odd length > order = 3"),
    ({"t": np.r_[0.0, np.cumsum(np.full(49, DT) * np.linspace(1, 1.01, 49))]}, r"^t: expected uniform"),
    ({"angle": np.zeros(49)}, r"^angle: expected shape \(50,\)"),
])
def test_savgol_derivative_rejects(keywords, pattern):
    arguments = {"t": np.arange(50) * DT, "angle": np.zeros(50), **keywords}
    with pytest.raises(ValueError, match=pattern):
        logs.savgol_derivative(**arguments)


# --- the Qube plant and its logs ----------------------------------------------------------------

def readme_qube(x, vm):
    """data/README.md's model, transcribed in numpy."""
    theta_dot, alpha, alpha_dot = x[2], x[1], x[3]
    mr, Lr, mp, Lp = 0.095, 0.085, 0.024, 0.129
    Jr, Jp = mr * Lr ** 2 / 12, mp * Lp ** 2 / 12
    Rm, km, Dr, Dp, g = 14.0, 0.01, 0.0005, -3e-5, 9.81
    tau = -km * (vm - km * theta_dot) / Rm
    s, c = math.sin(alpha), math.cos(alpha)
    inertia = 4 * Jr + Lp ** 2 * mp * s ** 2 + 4 * Lr ** 2 * mp
    den = 4 * Lp ** 2 * Lr ** 2 * mp ** 2 * c ** 2 - (4 * Jp + Lp ** 2 * mp) * inertia
    a = -8 * Dp * alpha_dot + Lp ** 2 * mp * theta_dot ** 2 * math.sin(2 * alpha) + 4 * Lp * g * mp * s
    b = (4 * Dr * theta_dot + Lp ** 2 * mp * alpha_dot * theta_dot * math.sin(2 * alpha)
         + 2 * Lp * Lr * mp * alpha_dot ** 2 * s - 4 * tau)
    return np.array([theta_dot, alpha_dot, (-Lp * Lr * mp * a * c + (4 * Jp + Lp ** 2 * mp) * b) / den,
                     (2 * Lp * Lr * mp * b * c - 0.5 * inertia * a) / den])


@pytest.fixture(scope="module")
def qube():
    return (kc.systems.load_plant(f"{QUBE / 'qube_plant.py'}:make_plant"),
            kc.systems.load_plant(f"{QUBE / 'qube_plant.py'}:make_plant_alpha"))


def test_qube_equations_match_the_readme(qube, rng):
    plant, plant_alpha = qube
    states = plant.sample_box(64, seed=9) * np.array([1.5, 1.2, 1.5, 1.5])     # beyond the box too
    states[:, 1] += rng.integers(-2, 3, 64) * 2 * np.pi
    voltages = rng.uniform(-10, 10, (64, 1))
    expected = np.array([readme_qube(x, v[0]) for x, v in zip(states, voltages)])
    for system in (plant, plant_alpha):
        np.testing.assert_allclose(system.f_batch(states, voltages), expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(plant.h_batch(states), states[:, :2])
    np.testing.assert_array_equal(plant_alpha.h_batch(states), states[:, 1:2])


def test_qube_marks_its_angles_and_covers_the_logged_ranges(qube):
    plant, plant_alpha = qube
    assert (plant.nx, plant.nu, plant.ny, plant_alpha.ny) == (4, 1, 2, 1)
    assert plant.angle_states == (0, 1) and plant.angle_outputs == (0, 1) and plant_alpha.angle_outputs == (0,)
    readme = np.array([[-1.5, 1.5], [np.pi - 2.7, np.pi + 2.7], [-13, 13], [-27, 27]])
    assert np.all(plant.x0_box[:, 0] <= readme[:, 0]) and np.all(plant.x0_box[:, 1] >= readme[:, 1])
    assert plant.fingerprint != plant_alpha.fingerprint


def test_a_real_qube_log_loads_onto_the_grid(qube):
    plant = qube[0]
    box = {"theta": plant.x0_box[0], "alpha": plant.x0_box[1]}
    log = logs.read_log(QUBE / "data" / "free_swing_1.csv", time_col="time", y_cols=("theta", "alpha"),
                        reference_cols=("theta_dot", "alpha_dot"), angle_cols=("theta", "alpha"), dt=DT, box=box)
    record = log.resampling
    assert record.n_raw == 3191 and 3e-3 < record.dt_min < record.dt_mean < record.dt_max < 5e-3
    assert record.dt_mean == pytest.approx(DT, rel=1e-3)
    assert log.y.shape == (log.t.size, 2) and log.t.size == int((record.t_last - record.t_first) / DT) + 1
    # alpha logged wrapped from -0.72 rad is unwrapped and moved onto the box's branch about +pi
    assert record.angle_shifts == (0.0, 2 * np.pi)
    assert np.all((log.y >= plant.x0_box[:2, 0]) & (log.y <= plant.x0_box[:2, 1]))
    assert np.max(np.abs(np.diff(log.y[:, 1]))) < 0.2
    velocity = logs.savgol_derivative(log.t, log.y)
    assert np.all(np.abs(velocity) <= plant.x0_box[2:, 1])
    # the device's velocities lag by about 4 samples (data/README.md): the reference agrees best there
    lags = [np.sqrt(np.mean((velocity[:-k or None] - log.reference[k:]) ** 2)) for k in range(8)]
    assert int(np.argmin(lags)) == 4
    assert re.search(r"free_swing_1\.csv$", log.source)


def test_the_ekf_follows_a_real_qube_log(qube):
    """examples/qube/check_logs.py's EKF on one run: the velocities after 2 s against the reference."""
    plant = qube[0]
    log = logs.read_log(QUBE / "data" / "free_swing_3.csv", time_col="time", y_cols=("theta", "alpha"),
                        angle_cols=("theta", "alpha"), dt=DT, box={"alpha": plant.x0_box[1]})
    velocity = logs.savgol_derivative(log.t, log.y)
    ekf = kc.EKF(plant, DT, Q=np.diag([0.0, 0.0, 1e-3, 1e-3]), R=1e-6 * np.eye(2))
    est = ekf.simulate(log.t, log.y, np.zeros((log.t.size, 1)))
    keep = log.t - log.t[0] >= 2.0
    assert kc.metrics.rmse(velocity[keep], est.xhat[keep, 2:]) < 0.1          # 0.031 measured
    assert kc.metrics.rmse(log.y[keep], est.xhat[keep, :2], angles=(0, 1)) < 0.01
