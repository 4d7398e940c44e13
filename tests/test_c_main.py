"""The generated C main over CSV logs: the model's columns by name in any order (their names in the header
file), one output row per input row, plain decimal numbers only, a byte-order mark, one-line refusals with
exit status 2, the sample guard (a non-finite or absurd sample is flagged and not fed, and the run recovers,
as :func:`kklcasadi.observer.guard.guarded_simulate` computes it, in every variant; exit status 3), and a
build with -fsanitize=address,undefined on hostile input."""

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from kklcasadi.model import variants
from kklcasadi.observer.codegen import DEFAULT_FLAGS, generate_c
from kklcasadi.observer.guard import HELD, RESTARTED, SampleGuard, guarded_simulate
from kklcasadi.observer.kkl import load_observer

GCC = shutil.which("gcc")
ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(GCC is None, reason="gcc is not installed")
DT = 0.05
WARNINGS = ("-Wall", "-Wextra", "-Werror", "-pedantic")
SANITIZE = ("-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer", "-g")


def with_domain(nx, nz):
    """A card's training domain: the states in [-1.5, 1.5]^nx, the latents in [-3, 3]^nz."""
    return {"domain": {"x_lo": [-1.5] * nx, "x_hi": [1.5] * nx, "z_lo": [-3.0] * nz, "z_hi": [3.0] * nz}}


def build(obs, directory, name="obs", *, sanitize=False, **names):
    files = generate_c(obs, directory, name, **names)
    binary = directory / name
    flags = (*DEFAULT_FLAGS[:1], "-O1") if sanitize else DEFAULT_FLAGS
    result = subprocess.run([GCC, *flags, *WARNINGS, *(SANITIZE if sanitize else ()), str(files[0]), str(files[2]),
                             "-o", str(binary), "-lm"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    return binary, files


def run(binary, data, *args):
    """(exit status, output header, output rows (n, k), stderr lines) of the main on ``data`` (str or bytes)."""
    raw = data.encode() if isinstance(data, str) else data
    result = subprocess.run([str(binary), *map(str, args)], input=raw, capture_output=True,
                            env={**os.environ, "ASAN_OPTIONS": "detect_leaks=1", "UBSAN_OPTIONS": "print_stacktrace=1"})
    lines = result.stdout.decode().splitlines()
    header = lines[0].split(",") if lines else []
    rows = np.array([[float(v) for v in line.split(",")] for line in lines[1:]]).reshape(len(lines[1:]), len(header))
    return result.returncode, header, rows, result.stderr.decode().strip().splitlines()


def csv_text(header, columns):
    return ",".join(header) + "\n" + "".join(",".join(repr(float(v)) for v in row) + "\n" for row in zip(*columns))


def trajectory(n=60, seed=0, ny=1, nu=1):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    y = np.column_stack([np.sin((1.3 + j) * t) + 0.1 * rng.normal(size=n) for j in range(ny)])
    u = np.column_stack([0.8 * np.sign(np.sin((2.0 + j) * t + 0.4)) for j in range(nu)])
    return t, y, u


# --- the columns by name ------------------------------------------------------------------------

@pytest.mark.parametrize("method, math", [("obs", "vector"), ("inject", "vector"), ("obs", "libm"),
                                          ("obs_stream", "libm"), ("dyn_stream", "vector")])
def test_the_main_reproduces_simulate(model_dir_factory, tmp_path, method, math):
    obs = load_observer(model_dir_factory(method, window=4))
    files = generate_c(obs, tmp_path, "observer", math=math)
    assert "Build: gcc -std=c99 -O3 observer.c observer_main.c -lm -o observer" in files[2].read_text()
    binary = tmp_path / "observer"
    subprocess.run([GCC, *DEFAULT_FLAGS, *WARNINGS, str(files[0]), str(files[2]), "-o", str(binary), "-lm"],
                   check=True)
    t, y, u = trajectory()
    text = csv_text(["time", "y1", "u1"], [t, y[:, 0], u[:, 0]])
    (tmp_path / "log.csv").write_text(text)
    status, header, rows, err = run(binary, text)
    assert status == 0 and err == [] and header == ["time", "x1", "x2", "status"]
    from_file = subprocess.run([str(binary), str(tmp_path / "log.csv")], capture_output=True, text=True, check=True)
    assert from_file.stdout.splitlines()[1:] == [",".join(f"{v:.17g}" for v in row) for row in rows] or \
        np.array_equal(np.loadtxt(from_file.stdout.splitlines()[1:], delimiter=","), rows)
    np.testing.assert_array_equal(rows[:, 0], t)
    expected = obs.simulate(t, y, u).xhat
    if math == "libm":
        np.testing.assert_array_equal(rows[:, 1:3], expected)
    else:
        np.testing.assert_allclose(rows[:, 1:3], expected, rtol=0, atol=1e-12)
    assert np.all(rows[:, 3] == 0)


def test_the_main_takes_its_columns_by_name_in_any_order(model_dir_factory, mimo_plant, tmp_path):
    """45.5: the names go into the header file; a reordered header with other columns gives the same estimates."""
    obs = load_observer(model_dir_factory("obs", system=mimo_plant, window=3), system=mimo_plant)
    binary, files = build(obs, tmp_path, "mimo", time_col="t [s]", y_cols=("pos", "sum"), u_cols=("volts", "amps"),
                          state_names=("x", "v"))
    header = files[1].read_text()
    for define in ('#define MIMO_TIME_COL "t [s]"', '#define MIMO_Y_COLS "pos", "sum"',
                   '#define MIMO_U_COLS "volts", "amps"', '#define MIMO_STATE_NAMES "x", "v"'):
        assert define in header
    t, y, u = trajectory(40, seed=2, ny=2, nu=2)
    ordered = csv_text(["t [s]", "pos", "sum", "volts", "amps"], [t, *y.T, *u.T])
    shuffled = csv_text(["amps", "noise", "sum", "t [s]", "volts", "pos"],
                        [u[:, 1], 7 * t, y[:, 1], t, u[:, 0], y[:, 0]])
    first, second = run(binary, ordered), run(binary, shuffled)
    assert first[0] == second[0] == 0 and first[1] == ["time", "x", "v", "status"]
    np.testing.assert_array_equal(first[2], second[2])
    np.testing.assert_allclose(first[2][:, 1:3], obs.simulate(t, y, u).xhat, rtol=0, atol=1e-12)
    quoted = ordered.replace("t [s],pos", '"t [s]", "pos"', 1)
    np.testing.assert_array_equal(run(binary, quoted)[2], first[2])


def test_a_log_with_other_column_names_is_refused_not_misread(model_dir_factory, tmp_path):
    """45: a ``t,u,y`` file ran through the old main by position (u read as y) with exit status 0."""
    obs = load_observer(model_dir_factory("inject", base=True))
    binary, _ = build(obs, tmp_path)
    t, y, u = trajectory(20)
    status, _, rows, err = run(binary, csv_text(["t", "u", "y"], [t, u[:, 0], y[:, 0]]))
    assert status == 2 and rows.size == 0
    assert err == ["error: line 1: expected a column 'time' (the time) in the header"]
    status, _, _, err = run(binary, csv_text(["time", "u1", "y"], [t, u[:, 0], y[:, 0]]))
    assert status == 2 and err == ["error: line 1: expected a column 'y1' (an output y) in the header"]
    status, _, rows, _ = run(binary, csv_text(["time", "u1", "y1"], [t, u[:, 0], y[:, 0]]))
    assert status == 0 and rows.shape[0] == 20
    np.testing.assert_allclose(rows[:, 1:3], obs.simulate(t, y, u).xhat, rtol=0, atol=1e-12)


def test_one_output_row_per_input_row_and_a_byte_order_mark(model_dir_factory, tmp_path):
    obs = load_observer(model_dir_factory("autonomous"))
    binary, _ = build(obs, tmp_path)
    t, y, u = trajectory(12)
    body = csv_text(["time", "y1", "u1"], [t, y[:, 0], u[:, 0]]).splitlines()
    text = "# a rig's note\n" + body[0] + "\n" + "\n".join(body[1:6]) + "\n\n# pause\n   \n" + "\r\n".join(body[6:])
    status, _, rows, _ = run(binary, text)                       # CRLF, blank and comment lines, no last newline
    assert status == 0 and rows.shape == (12, 4)
    np.testing.assert_array_equal(rows[:, 0], t)
    bom = "\ufeff" + "\n".join(body) + "\n"
    status, header, with_bom, _ = run(binary, bom)
    assert status == 0 and header[0] == "time" and with_bom.shape == (12, 4)      # the first data row kept (47.8)
    np.testing.assert_array_equal(with_bom, rows)


@pytest.mark.parametrize("line, message", [
    ("0.05,1.0,1.5.5", "column 'u1': expected a plain decimal number, received '1.5.5'"),
    ("0.05,1_000,0", "column 'y1': expected a plain decimal number, received '1_000'"),
    ("0.05,\u0661\u0662,0", "column 'y1': expected a plain decimal number, received '\\xD9\\xA1\\xD9\\xA2'"),
    ("0.05,0x10,0", "column 'y1': expected a plain decimal number, received '0x10'"),
    ("0.05,,0", "column 'y1': expected a plain decimal number, received ''"),
    ("0.05,1 2,0", "column 'y1': expected a plain decimal number, received '1 2'"),
    ("0.05,1e,0", "column 'y1': expected a plain decimal number, received '1e'"),
    ("0.05,0.1", "expected 3 fields (one per header column), received 2"),
    ("0.05,0.1,0,4", "expected 3 fields (one per header column), received 4"),
    ("nan,0.1,0", "column 'time': expected a finite time"),
    ("0.1,0.1,0", "time step 0.1 s from 0 to 0.10000000000000001, expected the model's dt = 0.050000000000000003 s; "
                  "resample the log at dt"),
    ("0.05,0.1,0\x00", "a NUL byte (not a text line)"),
])
def test_a_malformed_row_is_one_line_and_exit_status_2(model_dir_factory, tmp_path, line, message):
    obs = load_observer(model_dir_factory("autonomous"))
    binary, _ = build(obs, tmp_path)
    status, _, rows, err = run(binary, f"time,y1,u1\n0,0.1,0\n{line}\n0.1,0.1,0\n")
    assert status == 2 and rows.shape[0] == 1 and err == [f"error: line 3: {message}"], err


@pytest.mark.parametrize("text, message", [
    ("", "error: no header line (expected the columns time,y1,u1)"),
    ("# only a comment\n", "error: no header line (expected the columns time,y1,u1)"),
    ("time,y1,y1,u1\n0,1,1,0\n", "error: line 1: column 'y1' repeated in the header"),
    ("time,y1\n0,1\n", "error: line 1: expected a column 'u1' (an input u) in the header"),
])
def test_a_bad_header_is_one_line_and_exit_status_2(model_dir_factory, tmp_path, text, message):
    binary, _ = build(load_observer(model_dir_factory("autonomous")), tmp_path)
    status, _, _, err = run(binary, text)
    assert status == 2 and err == [message]


# --- the sample guard ---------------------------------------------------------------------------

def spoiled(y, u):
    """y with a NaN, +inf, 1e308 and a finite 1e200, u with 1e308, -inf and 1e200, apart from each other."""
    y, u = y.copy(), u.copy()
    y[5, 0], y[9, 0], y[14, 0], y[20, 0] = np.nan, np.inf, 1e308, 1e200
    u[26, 0], u[31, 0], u[37, 0] = 1e308, -np.inf, 1e200
    return y, u


@pytest.mark.parametrize("method", variants.names())
def test_one_absurd_sample_does_not_poison_the_run(model_dir_factory, tmp_path, method):
    """47.8 in every variant: every absurd sample is flagged, the estimates stay finite, the C main equals
    guarded_simulate, and 15 s after the last bad sample the run is back on the clean run."""
    base = method == "curriculum"
    probe = load_observer(model_dir_factory(method, base=base, window=3))
    obs = load_observer(model_dir_factory(method, base=base, window=3, card_extra=with_domain(probe.nx, probe.nz)))
    t, y, u = trajectory(400, seed=4)
    bad_y, bad_u = spoiled(y, u)
    est, status = guarded_simulate(obs, t, bad_y, bad_u)
    assert np.all(np.isfinite(est.xhat))
    # held: not finite, or y outside its guard box; the inputs have none (no range of them is recorded), so 1e308 and
    # 1e200 are fed, and where they throw the latent out of its box the observer restarts there, nowhere else
    assert np.flatnonzero(status & HELD).tolist() == [5, 9, 14, 20, 31]
    assert set(np.flatnonzero(status & RESTARTED)) <= {26, 27, 37, 38}     # u_k enters the step into k + 1
    np.testing.assert_allclose(est.xhat[-20:], obs.simulate(t, y, u).xhat[-20:], rtol=0, atol=1e-6)
    # not fed: the run is simulate's on the data with each held sample replaced by the one before it
    replaced = y.copy()
    for k in (5, 9, 14, 20):
        replaced[k] = replaced[k - 1]
    est_y, status_y = guarded_simulate(obs, t, bad_y, u)
    np.testing.assert_array_equal(est_y.xhat, obs.simulate(t, replaced, u).xhat)
    assert np.flatnonzero(status_y).tolist() == [5, 9, 14, 20]
    binary, _ = build(obs, tmp_path)
    code, header, rows, err = run(binary, csv_text(["time", "y1", "u1"], [t, bad_y[:, 0], bad_u[:, 0]]))
    assert code == 3 and header[-1] == "status" and rows.shape[0] == 400
    np.testing.assert_array_equal(rows[:, -1], status)
    np.testing.assert_allclose(rows[:, 1:3], est.xhat, rtol=0, atol=1e-9)
    restarts = int(np.count_nonzero(status & RESTARTED))
    assert err == [f"obs: {int(np.count_nonzero(status))} of 400 samples flagged in the status column (5 held, "
                   f"{restarts} restarts)"]
    if "in_domain" in header:
        np.testing.assert_array_equal(rows[:, 3], est.in_domain)


@pytest.mark.parametrize("value", [1e308, 1e300, 1e20])
def test_the_shipped_inject_observer_recovers_from_one_huge_sample(value):
    """47.8: one finite but huge y left the Duffing inject observer NaN (1e308) or stuck far off (1e300, 1e20: it
    ends at (-0.42, -2.43) against (-1.30, 0.95)) for the rest of the run; guarded, the sample is held."""
    import kklcasadi as kc

    obs = load_observer(ROOT / "models" / "duffing" / "inject")
    square = kc.signals.make("square", amplitude=0.8, omega=1.0)
    tr = kc.simulate(kc.systems.get("duffing"), [0.5, -0.2], square, T=30.0, dt=obs.dt, measurement_std=0.01, seed=1)
    huge = tr.y.copy()
    huge[40, 0] = value
    clean = obs.simulate(tr.t, tr.y, tr.u).xhat
    plain = obs.simulate(tr.t, huge, tr.u).xhat
    assert not np.all(np.abs(plain[-1] - clean[-1]) < 0.5)                # the old way: NaN or far off to the end
    est, status = guarded_simulate(obs, tr.t, huge, tr.u)
    assert np.flatnonzero(status).tolist() == [40] and np.all(np.isfinite(est.xhat))
    np.testing.assert_allclose(est.xhat[-100:], clean[-100:], rtol=0, atol=1e-6)


def test_the_guard_boxes_are_the_training_domain_widened(model_dir_factory):
    obs = load_observer(model_dir_factory("autonomous", card_extra=with_domain(2, 5)))
    guard = SampleGuard.of(obs)
    np.testing.assert_allclose([guard.y_lo[0], guard.y_hi[0]], [-1.5 - 30.0, 1.5 + 30.0])     # y = x1 on [-1.5, 1.5]
    np.testing.assert_allclose([guard.z_lo, guard.z_hi], [[-3.0 - 60.0] * 5, [3.0 + 60.0] * 5])
    assert np.all(np.isinf(guard.u_lo)) and np.all(np.isinf(guard.u_hi))
    bare = SampleGuard.of(load_observer(model_dir_factory("autonomous")))   # no domain: the X0 box, latent unbounded
    np.testing.assert_allclose([bare.y_lo[0], bare.y_hi[0]], [-21.0, 21.0])
    assert np.all(np.isinf(bare.z_hi))


# --- hostile input under AddressSanitizer and UBSan -----------------------------------------------

def hostile_inputs():
    rng = np.random.default_rng(47)
    good = "time,y1,u1\n" + "".join(f"{k * DT!r},{np.sin(k * DT)!r},0.5\n" for k in range(30))
    yield good.encode()
    yield b""
    yield b"\xef\xbb\xbf"
    yield b"\xef\xbb"
    yield "\ufefftime,y1,u1\n0,1,0".encode()
    yield b"time,y1,u1"
    yield b"time,y1,u1\n" + b"0," * 100000 + b"0\n"
    yield b"time,y1,u1," + b",".join(b"c%d" % i for i in range(20000)) + b"\n"
    yield b"time,y1,u1\n0,1," + b"9" * 2000000 + b"\n"
    yield b"time,y1,u1\n0,1," + b"1" * 400 + b"e99999\n0.05,1,0\n"
    yield b'"time","y1","u1"\n0,1,0\n0.05,1,0\n'
    yield b'"\n"time\n"'
    yield b"time,y1,u1\n0,1,0\r\r\r\n"
    yield b"time,y1,u1\n0,1,\x00\n"
    yield b"time,y1,u1\n" + b"\n" * 10000 + b"0,1,0\n"
    yield b",,,,\n,,,\n"
    yield b"time,y1,u1\n-0,-0,-0\n0.05,+.5,5.\n0.1,1e-400,1e400\n0.15,NAN,-Infinity\n"
    yield b"time,y1,u1\n0,1,0\n0.05,1,0\n" + b"0.1,1,0" * 50 + b"\n"
    for _ in range(20):
        yield rng.integers(0, 256, int(rng.integers(1, 4000)), dtype=np.uint8).tobytes()
    for _ in range(20):
        chars = np.array(list(b"0123456789.,-+eE\n\r #\"nai\xef\xbb\xbf\x00"), dtype=np.uint8)
        yield b"time,y1,u1\n" + rng.choice(chars, int(rng.integers(1, 3000))).tobytes()


def test_the_main_is_clean_under_sanitizers_on_hostile_input(model_dir_factory, tmp_path):
    obs = load_observer(model_dir_factory("obs", window=3, card_extra=with_domain(2, 5)))
    binary, _ = build(obs, tmp_path, sanitize=True)
    seen = set()
    for data in hostile_inputs():
        result = subprocess.run([str(binary)], input=data, capture_output=True,
                                env={**os.environ, "ASAN_OPTIONS": "detect_leaks=1:exitcode=86",
                                     "UBSAN_OPTIONS": "halt_on_error=1:exitcode=87"})
        err = result.stderr.decode(errors="replace")
        assert result.returncode in (0, 2, 3), (data[:200], result.returncode, err[-2000:])
        assert "Sanitizer" not in err and "runtime error" not in err, err[-2000:]
        lines = err.strip().splitlines()
        assert len(lines) <= 1, err[-2000:]
        if result.returncode == 2:
            assert re.match(r"error: (line \d+: |no header line)", lines[0]), lines
        seen.add(result.returncode)
    assert seen == {0, 2, 3}
    # and a file that cannot be opened is exit status 1, a second argument a usage error
    assert subprocess.run([str(binary), str(tmp_path / "missing.csv")], capture_output=True).returncode == 1
    assert subprocess.run([str(binary), "a", "b"], capture_output=True).returncode == 2
