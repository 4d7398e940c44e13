"""kklcasadi estimate and evaluation.logged.estimate_log: an observer and the EKF over a recorded log (the Qube's); a
log a block at a time (evaluation.streamed on plant.logstream): the whole-log path's values and file bit for bit
across blocks, and the logs it leaves to the whole-log reader."""

import csv
import math
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi import provenance
from kklcasadi.cli import main
from kklcasadi.evaluation.chunked import BITWISE
from kklcasadi.evaluation.logged import ekf_for_model, estimate_log, read_plant_log
from kklcasadi.evaluation.streamed import estimate_streamed
from kklcasadi.plant import logs, logstream
from kklcasadi.plant.envelope import output_ranges
from kklcasadi.plant.logs import read_log
from kklcasadi.plant.logstream import scan_log

QUBE = Path(__file__).resolve().parents[1] / "examples" / "qube"
RUN = QUBE / "data" / "free_swing_1.csv"
PLANT = f"{QUBE / 'qube_plant.py'}:make_plant"
STATES = "theta,alpha,theta_dot,alpha_dot"


@pytest.fixture(scope="module")
def plant():
    return kc.systems.load_plant(PLANT)


@pytest.fixture
def model(model_dir_factory, plant):
    """A random-weight bank model of the Qube at 4 ms whose card records noise levels and a domain."""
    domain = {"x_lo": list(plant.x0_box[:, 0]), "x_hi": list(plant.x0_box[:, 1]), "z_lo": [-10.0] * 18,
              "z_hi": [10.0] * 18}
    return model_dir_factory("bank", system=plant, dt=0.004, card_extra={
        "noise": {"measurement_std": 0.002, "process_std": 0.5}, "domain": domain})


def short_log(tmp_path, rows=300, edit=None):
    """The first ``rows`` rows of a real Qube run, optionally edited: ``edit(header, rows)``."""
    with open(RUN, newline="") as stream:
        table = list(csv.reader(stream))
    header, body = table[0], table[1:rows + 1]
    if edit is not None:
        edit(header, body)
    path = tmp_path / "run.csv"
    with open(path, "w", newline="") as stream:
        csv.writer(stream).writerows([header, *body])
    return path


def test_estimate_writes_the_estimates_flags_and_the_ekf(model, plant, tmp_path, capsys):
    out = tmp_path / "est.csv"
    args = ["estimate", str(model), "--plant", PLANT, "--data", str(short_log(tmp_path)), "--y-cols", "theta,alpha",
            "--u-zero", "--reference-cols", STATES, "--ekf", "--settle", "0.4", "--state-names", STATES,
            "--out", str(out), "--math", "libm"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "your model" in printed and "300 rows" in printed and "angles unwrapped: theta, alpha" in printed
    assert "EKF      Q = (0.5 dt)^2 I, R = 0.002^2 I" in printed          # the card's noise levels
    assert "against 'alpha_dot': KKL" in printed
    with open(out, newline="") as stream:
        comment, rows = stream.readline(), list(csv.reader(stream))
    assert provenance.read(out).command == shlex.join(["kklcasadi", *args]) and comment.startswith("# provenance")
    assert rows[0] == ["time", *STATES.split(","), "in_domain", "status", *[f"ekf_{s}" for s in STATES.split(",")]]
    values = np.array(rows[1:], dtype=float)
    # the same as the observer and the EKF run on the log read onto the grid by hand
    obs = kc.load_observer(model, system=plant)
    ranges = output_ranges(plant)
    log = read_log(short_log(tmp_path), time_col="time", y_cols=("theta", "alpha"), dt=0.004,
                   angle_cols=("theta", "alpha"), box={"theta": tuple(ranges[0]), "alpha": tuple(ranges[1])})
    est = obs.simulate(log.t, log.y, np.zeros((log.t.size, 1)))
    ekf = kc.EKF.for_noise(plant, 0.004, process_std=0.5, measurement_std=0.002).simulate(
        log.t, log.y, np.zeros((log.t.size, 1))).xhat
    np.testing.assert_array_equal(values[:, 0], log.t)
    np.testing.assert_array_equal(values[:, 1:5], est.xhat)
    np.testing.assert_array_equal(values[:, 5], est.in_domain)
    np.testing.assert_array_equal(values[:, 6], 0)                       # no sample flagged by the guard
    np.testing.assert_array_equal(values[:, 7:], ekf)
    assert np.all(np.abs(log.y[:, 1] - np.pi) < 2.8)                     # alpha on the box's branch (hanging = pi)
    # a second run to the same --out: refused in one line before the log is read, the estimates as they were
    before = out.read_bytes()
    assert main(args) == 2
    captured = capsys.readouterr()
    assert captured.err == (f"error: --out: {out} exists and this command does not overwrite; move it away, or "
                            "choose another --out.\n") and captured.out == ""
    assert out.read_bytes() == before


def test_estimate_log_in_one_call_scores_with_wrapped_angles(model, plant):
    obs = kc.load_observer(model, system=plant)
    result = estimate_log(obs, RUN, y_cols=("theta", "alpha"), u_zero=True,
                          reference_cols=("theta", "alpha", None, None), ekf=True, settle=2.0)
    assert set(result.scores) == {0, 1} and result.ekf_noise == (0.5, 0.002)
    keep = result.t - result.t[0] >= 2.0
    shifted = result.xhat[keep, 1] + 2 * np.pi                          # the same angle on another branch
    wrapped = np.sqrt(np.mean(kc.metrics.wrap_angle(result.log.y[keep, 1] - shifted) ** 2))
    assert result.scores[1]["rmse"] == pytest.approx(wrapped, rel=1e-12)
    assert result.scores[1]["rmse_ekf"] < 0.01                          # the EKF follows a measured angle
    log, reference = read_plant_log(RUN, obs, time_col="time", y_cols=("theta", "alpha"), u_zero=True,
                                    reference_cols=(None, None, "theta_dot", None))
    again = estimate_log(obs, log, u_zero=True, reference=reference)
    np.testing.assert_array_equal(again.xhat, result.xhat)
    assert again.scores[2]["column"] == "theta_dot" and again.ekf is None


def test_the_ekf_needs_noise_levels_the_card_or_the_user_gives(model_dir_factory, plant):
    obs = kc.load_observer(model_dir_factory("bank", system=plant, dt=0.004), system=plant)   # no process_std
    with pytest.raises(ValueError, match=r"process_std: expected the process-noise level of the EKF, received none "
                                         r"given, and the card records none\. Pass it"):
        ekf_for_model(obs)
    ekf, levels = ekf_for_model(obs, process_std=0.3, measurement_std=0.01)
    assert levels == (0.3, 0.01)
    np.testing.assert_allclose(ekf.Q, (0.3 * 0.004) ** 2 * np.eye(4))
    np.testing.assert_allclose(ekf.R, 1e-4 * np.eye(2))


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "kklcasadi", *args], capture_output=True, text=True)


def _decreasing(header, rows):
    rows[7][header.index("time")] = rows[6][header.index("time")]


def _nan(header, rows):
    rows[5][header.index("theta")] = "nan"


def _text(header, rows):
    rows[3][header.index("alpha")] = "abc"


def _gap(header, rows):
    del rows[20:30]


def _outside(header, rows):
    """The arm moved by 2.5 rad from row 17 on: less than pi, so no unwrapping undoes it."""
    i = header.index("theta")
    for row in rows[17:]:
        row[i] = repr(float(row[i]) + 2.5)


def _missing(header, rows):
    header[header.index("alpha")] = "beta"


@pytest.mark.parametrize("edit, dt, expected", [
    (_decreasing, 0.004, r"--data: .*run\.csv: row 7 \(line 9\), column 'time': expected a time after row 6's"),
    (_nan, 0.004, r"--data: .*run\.csv: row 5 \(line 7\), column 'theta': expected a finite number, received nan"),
    (_text, 0.004, r"--data: .*run\.csv: row 3 \(line 5\), column 'alpha': expected a plain decimal number "
                   r"\(digits, '\.', an exponent\), received 'abc'"),
    (_gap, 0.004, r"--data: .*run\.csv: row 20 \(line 22\), column 'time': expected spacings of at most"),
    (_outside, 0.004, r"--data: .*run\.csv: row 17 \(line 19\), column 'theta': expected values within the box "
                      r"\[-1\.6, 1\.6\] .* received 2\.\d+, above hi = 1\.6"),
    (_missing, 0.004, r"--y-cols: expected a column of .*run\.csv, received 'alpha'\. Its header holds \['id', "
                      r"'beta', 'theta', 'alpha_dot', 'theta_dot', 'time'\]\.$"),
    (None, 0.001, r"--data: .*run\.csv: column 'time': expected a log at least as fast as the model: a median sample "
                  r"time of at most dt = 0\.001 s .* use a model trained at the log's rate \(kklcasadi train --dt "
                  r"0\.0039\d*\)\.$"),
])
def test_a_bad_log_is_one_line_naming_its_row_and_column(model_dir_factory, plant, tmp_path, edit, dt, expected):
    model = model_dir_factory("bank", system=plant, dt=dt)
    result = _cli("estimate", str(model), "--plant", PLANT, "--data", str(short_log(tmp_path, edit=edit)),
                  "--y-cols", "theta,alpha", "--u-zero", "--out", str(tmp_path / "est.csv"))
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert re.search(expected, lines[0]), lines[0]
    assert not (tmp_path / "est.csv").exists()


@pytest.mark.parametrize("extra, expected", [
    (["--y-cols", "alpha"], "--y-cols: expected 2 column(s) (the outputs of 'qube'), received 1: alpha"),
    (["--y-cols", "theta,alpha", "--reference-cols", "theta"], "--reference-cols: expected 4 column(s)"),
    (["--y-cols", "theta,alpha", "--u-cols", "a,b"], "--u-cols: expected 1 column(s)"),
    (["--y-cols", "theta,,alpha"], "argument --y-cols: expected comma-separated column names"),
    (["--y-cols", "theta,alpha", "--ekf"], "--ekf: expected the process-noise level of the EKF"),
])
def test_bad_column_flags_are_one_line(model_dir_factory, plant, tmp_path, extra, expected):
    model = model_dir_factory("bank", system=plant, dt=0.004)
    result = _cli("estimate", str(model), "--plant", PLANT, "--data", str(RUN), "--out", str(tmp_path / "e.csv"),
                  *extra, *([] if "--u-cols" in extra else ["--u-zero"]))
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and expected in lines[0], result.stderr


# --- columns by name, inputs named, logs at any rate (issue 45.4), --out never an input (47.2) ---

ROOT = Path(__file__).resolve().parents[1]
DUFFING = ROOT / "models" / "duffing" / "bank"


def _run(capsys, *args):
    """``kklcasadi ARGS`` in this process: (exit status, stdout, stderr lines)."""
    status = main([str(a) for a in args])
    captured = capsys.readouterr()
    return status, captured.out, captured.err.strip().splitlines()


def _refused(capsys, *args):
    status, _, lines = _run(capsys, *args)
    assert status == 2 and len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0][len("error: "):]


@pytest.fixture(scope="module")
def demo_run():
    """The README's run (Duffing, square input 0.8 at 1 rad/s, noise 0.1) sampled at 1 kHz for 20 s."""
    plant = kc.systems.get("duffing")
    u = kc.signals.make("square", amplitude=0.8, omega=1.0)
    return kc.simulate(plant, [0.5, -0.2], u, T=20.0, dt=0.001, process_std=0.1, measurement_std=0.1, seed=0)


def _write(path, header, columns):
    with open(path, "w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(header)
        writer.writerows(zip(*[[repr(float(v)) for v in c] for c in columns]))
    return path


def test_a_plant_with_inputs_needs_its_input_columns_or_u_zero(model, tmp_path, capsys):
    common = ["estimate", model, "--plant", PLANT, "--data", short_log(tmp_path), "--y-cols", "theta,alpha",
              "--out", tmp_path / "est.csv"]
    assert _refused(capsys, *common) == ("--u-cols: expected 1 column(s) (the inputs of 'qube', in order), received "
                                         "none; name the logged inputs, or pass --u-zero if the input was zero "
                                         "throughout the log")
    assert _refused(capsys, *common, "--u-zero", "--u-cols", "theta_dot").startswith(
        "--u-zero: expected either --u-cols (the logged inputs) or --u-zero")
    assert not (tmp_path / "est.csv").exists()
    obs = kc.load_observer(model, system=kc.systems.load_plant(PLANT))
    with pytest.raises(ValueError, match=r"^u_cols: expected 1 column\(s\) \(the inputs of 'qube', in order\), "
                                         r"received none\. Name the logged inputs, or pass u_zero=True"):
        estimate_log(obs, RUN, y_cols=("theta", "alpha"))
    log, _ = read_plant_log(RUN, obs, time_col="time", y_cols=("theta", "alpha"), u_zero=True)
    with pytest.raises(ValueError, match=r"^u_cols: expected 1 column"):
        estimate_log(obs, log)                                          # a Log without inputs too
    status, out, _ = _run(capsys, *common, "--u-zero")
    assert status == 0 and "u zero (--u-zero)" in out


@pytest.mark.parametrize("extra, expected", [
    (["--time-col", "t", "--y-cols", "theta,alpha"], "--time-col: expected a column of "),
    (["--y-cols", "theta,gamma"], "--y-cols: expected a column of "),
    (["--y-cols", "theta,alpha", "--u-cols", "Vm"], "--u-cols: expected a column of "),
    (["--y-cols", "theta,alpha", "--reference-cols=-,-,-,omega"], "--reference-cols: expected a column of "),
])
def test_a_missing_column_names_its_flag(model, tmp_path, capsys, extra, expected):
    u = [] if "--u-cols" in extra else ["--u-zero"]
    message = _refused(capsys, "estimate", model, "--plant", PLANT, "--data", short_log(tmp_path), *extra, *u,
                       "--out", tmp_path / "est.csv")
    assert message.startswith(expected) and "run.csv" in message and "Its header holds ['id', " in message, message


def test_a_model_of_a_plant_kklcasadi_does_not_ship_asks_for_the_plant_flag(model, tmp_path, capsys):
    message = _refused(capsys, "estimate", model, "--data", RUN, "--y-cols", "theta,alpha", "--u-zero",
                       "--out", tmp_path / "est.csv")
    assert message == (f"--plant: expected the plant of the model MODEL {model} (its card names the system 'qube', "
                       "which kklcasadi does not ship), received none; pass --plant FILE.py:NAME")
    assert "load_observer" not in message


def test_out_is_never_an_input(model, tmp_path, capsys, monkeypatch):
    data = short_log(tmp_path)
    before = data.read_bytes()
    common = ["estimate", model, "--plant", PLANT, "--data", data, "--y-cols", "theta,alpha", "--u-zero"]
    assert _refused(capsys, *common, "--out", data) == (f"--out: expected a file other than the command's inputs, "
                                                        f"received {str(data)!r}, which is --data's file; choose "
                                                        "another --out")
    monkeypatch.chdir(tmp_path)
    link = tmp_path / "link.csv"
    link.symlink_to(data)
    for out in ("run.csv", "./sub/../run.csv", link):
        (tmp_path / "sub").mkdir(exist_ok=True)
        assert "which is --data's file" in _refused(capsys, *common, "--out", out)
    plant_copy = tmp_path / "plant.py"
    plant_copy.write_text((QUBE / "qube_plant.py").read_text())
    plant_before = plant_copy.read_bytes()
    message = _refused(capsys, "estimate", model, "--plant", f"{plant_copy}:make_plant", "--data", data, "--y-cols",
                       "theta,alpha", "--u-zero", "--out", plant_copy)
    assert "which is --plant's file" in message
    assert _refused(capsys, *common, "--out", model / "est.csv").startswith("--out: expected a file outside the "
                                                                              "model MODEL")
    assert _refused(capsys, *common, "--out", tmp_path).startswith("--out: expected a file path for the estimates")
    assert data.read_bytes() == before and plant_copy.read_bytes() == plant_before
    assert not (model / "est.csv").exists()


def test_out_equal_to_data_leaves_the_log_whole(demo_run, tmp_path, capsys):
    """47.2 as reported: a shipped model, a log inside its domain, ``--out`` the log itself (exit 0 and the log
    replaced by the estimates before)."""
    tr = demo_run
    data = _write(tmp_path / "run.csv", ["time", "y", "u"], [tr.t[:2000:50], 0.3 * tr.y[:2000:50, 0],
                                                             tr.u[:2000:50, 0]])
    before = data.read_bytes()
    message = _refused(capsys, "estimate", DUFFING, "--data", data, "--y-cols", "y", "--u-cols", "u", "--out", data)
    assert message.endswith("which is --data's file; choose another --out") and data.read_bytes() == before


def test_a_missing_log_names_data_not_out(tmp_path, capsys):
    """A --data file that does not exist is refused naming --data (the streamed run named --out: its reader's and
    its writer's errors share the argument name 'path'), before any model is loaded; nothing is written."""
    missing, out = tmp_path / "nowhere.csv", tmp_path / "e.csv"
    message = _refused(capsys, "estimate", DUFFING, "--data", missing, "--y-cols", "y", "--u-cols", "u", "--out", out)
    assert message == f"--data: expected an existing CSV file, received {str(missing)!r}" and not out.exists()


def test_a_1khz_log_is_averaged_onto_the_models_grid(demo_run, tmp_path, capsys):
    """The README's Duffing run logged at 1 kHz (t, u, y in that order) for the 50 ms bank: the estimate is the
    observer run on u averaged over each 50 ms and y sampled every 50 ms, computed here by hand."""
    tr = demo_run
    data = _write(tmp_path / "fast.csv", ["t", "u", "y"], [tr.t, tr.u[:, 0], tr.y[:, 0]])
    out = tmp_path / "est.csv"
    status, printed, _ = _run(capsys, "estimate", DUFFING, "--data", data, "--time-col", "t", "--y-cols", "y",
                              "--u-cols", "u", "--out", out)
    assert status == 0 and "u mean over each interval of the log's zero-order hold" in printed
    written = np.loadtxt(out, delimiter=",", skiprows=2)                # a provenance line, the header
    obs = kc.load_observer(DUFFING)
    grid = np.arange(0, 400) * 0.05
    assert written.shape[0] == 400 and np.allclose(written[:, 0], grid, rtol=0, atol=1e-12)
    u = tr.u[:20000, 0].reshape(400, 50).mean(axis=1)              # 50 samples per interval, each held 1 ms
    y = tr.y[::50, 0][:400]
    est = obs.simulate(grid, y, u)
    np.testing.assert_allclose(written[:, 1:3], est.xhat, rtol=0, atol=1e-9)
    # and the same run logged at the model's own 50 ms with the same averaged input gives those estimates too
    slow = _write(tmp_path / "slow.csv", ["t", "y", "u"], [grid, y, u])
    assert main(["estimate", str(DUFFING), "--data", str(slow), "--time-col", "t", "--y-cols", "y", "--u-cols", "u",
                 "--out", str(tmp_path / "slow_est.csv")]) == 0
    np.testing.assert_allclose(np.loadtxt(tmp_path / "slow_est.csv", delimiter=",", skiprows=2)[:, 1:3], est.xhat,
                               rtol=0, atol=1e-12)


def test_the_readme_run_passes_the_training_domain_check(demo_run, tmp_path, capsys):
    """47.10: the README demo's own run leaves the X0 box [-1, 1] by 70 % but not the states the bank was trained on."""
    tr = demo_run
    plant = kc.systems.get("duffing")
    assert tr.y.max() > 1.6 and tr.y.min() < -1.6                         # beyond the X0 box +-10 %
    obs = kc.load_observer(DUFFING)
    np.testing.assert_allclose(output_ranges(plant, np.column_stack([obs.domain.x_lo, obs.domain.x_hi]))[0],
                               [obs.domain.x_lo[0], obs.domain.x_hi[0]])
    data = _write(tmp_path / "run.csv", ["time", "y", "u"], [tr.t[::50], tr.y[::50, 0], tr.u[::50, 0]])
    status, printed, _ = _run(capsys, "estimate", DUFFING, "--data", data, "--y-cols", "y", "--u-cols", "u",
                              "--out", tmp_path / "est.csv")
    assert status == 0, printed
    # a run far outside the training domain is refused, and accepted with --no-range-check
    wild = _write(tmp_path / "wild.csv", ["time", "y", "u"], [tr.t[::50], 3.0 * tr.y[::50, 0], tr.u[::50, 0]])
    message = _refused(capsys, "estimate", DUFFING, "--data", wild, "--y-cols", "y", "--u-cols", "u",
                       "--out", tmp_path / "wild_est.csv")
    assert re.match(r"--data: .*wild\.csv: row \d+ \(line \d+\), column 'y': expected values within the box "
                    r"\[-3\.61\d*, 3\.65\d*\] widened by 0\.1 of its width, received", message), message
    status, printed, _ = _run(capsys, "estimate", DUFFING, "--data", wild, "--y-cols", "y", "--u-cols", "u",
                              "--no-range-check", "--out", tmp_path / "wild_est.csv")
    assert status == 0 and "not checked against the training domain (--no-range-check)" in printed


def test_an_absurd_sample_is_held_flagged_and_exit_status_3(demo_run, tmp_path, capsys):
    """47.8 from the command line: with --no-range-check one y of 1e300 reaches the observer; it is not fed, the row
    says so in the status column, the estimates stay finite, and the command ends with exit status 3."""
    tr = demo_run
    y = tr.y[::50, 0].copy()
    y[100] = 1e300
    data = _write(tmp_path / "spike.csv", ["time", "y", "u"], [tr.t[::50], y, tr.u[::50, 0]])
    out = tmp_path / "est.csv"
    assert "row 100 (line 102), column 'y': expected values within the box" in _refused(
        capsys, "estimate", DUFFING, "--data", data, "--y-cols", "y", "--u-cols", "u", "--out", out)
    status, printed, _ = _run(capsys, "estimate", DUFFING, "--data", data, "--y-cols", "y", "--u-cols", "u",
                              "--no-range-check", "--out", out)
    assert status == 3 and "guard    1 of 400 samples flagged in the status column: 1 not fed" in printed
    with open(out, newline="") as stream:
        comment, rows = stream.readline(), list(csv.reader(stream))
    assert comment.startswith("# provenance") and rows[0] == ["time", "x1", "x2", "in_domain", "status"]
    values = np.array(rows[1:], dtype=float)
    assert np.flatnonzero(values[:, 4]).tolist() == [100] and np.all(np.isfinite(values[:, 1:3]))
    clean = kc.load_observer(DUFFING).simulate(tr.t[::50], tr.y[::50], tr.u[::50]).xhat
    np.testing.assert_allclose(values[-50:, 1:3], clean[-50:], rtol=0, atol=1e-4)


# ---------------------------------------------------------------- a block at a time
@pytest.fixture
def small_blocks(monkeypatch):
    """Blocks of 37 rows read and 50 samples estimated: every log of the tests spans several."""
    monkeypatch.setattr(logs, "_BLOCK", 37)
    monkeypatch.setattr(logstream, "BLOCK", 50)


def test_blocks_are_read_logs_grid_bit_for_bit_with_angles_unwrapped_across_blocks(tmp_path, small_blocks):
    rng = np.random.default_rng(0)
    n = 400
    t = 2.0 + np.cumsum(0.01 * (1 + 0.02 * rng.uniform(-1, 1, n)))           # at the model's rate, jittered
    angle = np.cumsum(rng.normal(0.4, 0.3, n))                               # turns many times
    wrapped = (angle + np.pi) % (2 * np.pi) - np.pi
    path = _write(tmp_path / "log.csv", ["t", "a", "y", "u", "v"],
                  [t, wrapped, np.sin(t), np.round(np.cos(3 * t), 1), angle])
    arguments = dict(time_col="t", y_cols=("a", "y"), u_cols=("u",), reference_cols=("v",), dt=0.01,
                     angle_cols=("a", "v"), box={"a": (100.0, 110.0), "y": (-1.0, 1.0)}, box_margin=math.inf)
    whole = read_log(path, **arguments)
    with scan_log(path, **arguments) as scan:
        parts = [np.concatenate(p) for p in zip(*scan.blocks())]
        resampling = scan.resampling
    for part, expected in zip(parts, (whole.t, whole.y, whole.u, whole.reference)):
        np.testing.assert_array_equal(part, expected)
    assert resampling.angle_shifts == whole.resampling.angle_shifts and resampling.angle_shifts[0] != 0
    assert resampling.dt_mean == pytest.approx(whole.resampling.dt_mean, rel=1e-13)    # summed a block at a time
    assert resampling == logs.Resampling(**{**vars(whole.resampling), "dt_mean": resampling.dt_mean})


@pytest.mark.parametrize("edit, why", [
    (lambda t, y: (t, np.where(np.arange(t.size) == 250, np.nan, y)), "not finite"),
    (lambda t, y: (np.where(np.arange(t.size) == 250, t[249], t), y), "times not increasing"),
    (lambda t, y: (np.where(np.arange(t.size) >= 250, t + 0.5, t), y), "a gap"),
    (lambda t, y: (t, np.where(np.arange(t.size) == 300, 5.0, y)), "outside its box"),
    (lambda t, y: (np.linspace(0.0, 1.0, t.size), y), "faster than the model"),
    (lambda t, y: (np.concatenate([[0.0], np.cumsum(np.where(np.arange(t.size - 1) % 2, 0.008, 0.0125))]), y),
     "a median between two spacings on either side of a bound"),      # 0.01025: at the rate, as read_log finds
])
def test_logs_the_stream_leaves_to_the_whole_log_reader(tmp_path, small_blocks, edit, why):
    t, y = edit(np.arange(401) * 0.01, np.sin(np.arange(401) * 0.01))
    path = _write(tmp_path / "log.csv", ["t", "y"], [t, y])
    assert scan_log(path, time_col="t", y_cols=("y",), dt=0.01, box={"y": (-1.0, 1.0)}) is None, why
    if why.startswith("a median"):
        assert read_log(path, time_col="t", y_cols=("y",), dt=0.01).resampling.u_method == logs.U_HOLD


def test_a_streamed_estimate_writes_the_whole_log_paths_file(model, plant, tmp_path, small_blocks, capsys):
    run = short_log(tmp_path, rows=300)
    out = tmp_path / "est.csv"
    args = ["estimate", str(model), "--plant", PLANT, "--data", str(run), "--y-cols", "theta,alpha", "--u-zero",
            "--reference-cols", STATES, "--ekf", "--settle", "0.4", "--state-names", STATES, "--out", str(out),
            "--math", "libm"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    obs = kc.load_observer(model, system=plant)
    whole = estimate_log(obs, run, y_cols=("theta", "alpha"), u_zero=True, reference_cols=tuple(STATES.split(",")),
                         ekf=True, settle=0.4, compiler=BITWISE)
    expected = whole.write(tmp_path / "whole.csv", state_names=STATES.split(","))
    assert out.read_text().splitlines()[1:] == expected.read_text().splitlines()[1:]
    assert whole.table(STATES.split(",")) in printed and f"domain   {int(whole.in_domain.sum())} of" in printed
    streamed = estimate_streamed(obs, run, out=tmp_path / "again.csv", y_cols=("theta", "alpha"), u_zero=True,
                                 reference_cols=tuple(STATES.split(",")), ekf=True, settle=0.4, compiler=BITWISE)
    assert streamed is not None and streamed.n == whole.t.size == 300 and streamed.ekf_noise == whole.ekf_noise
    for i, score in whole.scores.items():
        assert streamed.scores[i]["rmse"] == pytest.approx(score["rmse"], rel=1e-12)
        assert streamed.scores[i]["rmse_ekf"] == pytest.approx(score["rmse_ekf"], rel=1e-12)


def test_a_sample_the_guard_holds_leaves_the_file_to_the_whole_log_path(demo_run, tmp_path, small_blocks):
    tr = demo_run
    y = tr.y[::50, 0].copy()
    y[120] = 1e300                                                           # in the third block
    data = _write(tmp_path / "spike.csv", ["time", "y", "u"], [tr.t[::50], y, tr.u[::50, 0]])
    out = tmp_path / "est.csv"
    assert estimate_streamed(kc.load_observer(DUFFING), data, out=out, y_cols=("y",), u_cols=("u",),
                             range_check=False) is None
    assert not out.exists() and not list(tmp_path.glob(".est.csv.*"))       # nothing written, no temporary left
