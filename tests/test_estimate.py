"""kklcasadi estimate and evaluation.logged.estimate_log: an observer and the EKF over a recorded log (the Qube's)."""

import csv
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
from kklcasadi.evaluation.logged import ekf_for_model, estimate_log, output_ranges, read_plant_log
from kklcasadi.plant.logs import read_log

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
            "--reference-cols", STATES, "--ekf", "--settle", "0.4", "--state-names", STATES, "--out", str(out),
            "--math", "libm"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "your model" in printed and "300 rows" in printed and "angles unwrapped: theta, alpha" in printed
    assert "EKF      Q = (0.5 dt)^2 I, R = 0.002^2 I" in printed          # the card's noise levels
    assert "against 'alpha_dot': KKL" in printed
    with open(out, newline="") as stream:
        comment, rows = stream.readline(), list(csv.reader(stream))
    assert provenance.read(out).command == shlex.join(["kklcasadi", *args]) and comment.startswith("# provenance")
    assert rows[0] == ["time", *STATES.split(","), "in_domain", *[f"ekf_{s}" for s in STATES.split(",")]]
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
    np.testing.assert_array_equal(values[:, 6:], ekf)
    assert np.all(np.abs(log.y[:, 1] - np.pi) < 2.8)                     # alpha on the box's branch (hanging = pi)


def test_estimate_log_in_one_call_scores_with_wrapped_angles(model, plant):
    obs = kc.load_observer(model, system=plant)
    result = estimate_log(obs, RUN, y_cols=("theta", "alpha"), reference_cols=("theta", "alpha", None, None),
                          ekf=True, settle=2.0)
    assert set(result.scores) == {0, 1} and result.ekf_noise == (0.5, 0.002)
    keep = result.t - result.t[0] >= 2.0
    shifted = result.xhat[keep, 1] + 2 * np.pi                          # the same angle on another branch
    wrapped = np.sqrt(np.mean(kc.metrics.wrap_angle(result.log.y[keep, 1] - shifted) ** 2))
    assert result.scores[1]["rmse"] == pytest.approx(wrapped, rel=1e-12)
    assert result.scores[1]["rmse_ekf"] < 0.01                          # the EKF follows a measured angle
    log, reference = read_plant_log(RUN, obs, time_col="time", y_cols=("theta", "alpha"),
                                    reference_cols=(None, None, "theta_dot", None))
    again = estimate_log(obs, log, reference=reference)
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
    (_text, 0.004, r"--data: .*run\.csv: row 3 \(line 5\), column 'alpha': expected a number, received 'abc'"),
    (_gap, 0.004, r"--data: .*run\.csv: row 20 \(line 22\), column 'time': expected spacings of at most"),
    (_outside, 0.004, r"--data: .*run\.csv: row 17 \(line 19\), column 'theta': expected values within the box "
                      r"\[-1\.6, 1\.6\] .* received 2\.\d+, above hi = 1\.6"),
    (_missing, 0.004, r"--data: .*run\.csv: columns: expected \['alpha'\] among the file's columns"),
    (None, 0.05, r"--data: .*run\.csv: column 'time': expected a mean sample time within a factor 1\.5 of the "
                 r"model's dt = 0\.05 s"),
])
def test_a_bad_log_is_one_line_naming_its_row_and_column(model_dir_factory, plant, tmp_path, edit, dt, expected):
    model = model_dir_factory("bank", system=plant, dt=dt)
    result = _cli("estimate", str(model), "--plant", PLANT, "--data", str(short_log(tmp_path, edit=edit)),
                  "--y-cols", "theta,alpha", "--out", str(tmp_path / "est.csv"))
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
                  *extra)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and expected in lines[0], result.stderr
