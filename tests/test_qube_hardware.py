"""examples/qube_hardware.py in a reduced form: a tiny training budget, every log estimated and scored."""

import runpy
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "qube_hardware.py"


@pytest.fixture(scope="module")
def example():
    return runpy.run_path(str(EXAMPLE), run_name="qube_hardware")


def test_the_split_fits_nothing_on_the_scored_runs(example):
    assert not set(example["FIT_RUNS"]) & set(example["SCORED_RUNS"])
    assert sorted(example["FIT_RUNS"] + example["SCORED_RUNS"]) == [1, 3, 5, 7, 9, 11]
    # the encoders' noise: of the order of their resolution (1e-3 rad, examples/qube/data/README.md)
    assert 1e-4 < example["encoder_noise"](example["FIT_RUNS"]) < 3e-3


def test_the_filtered_difference_of_a_ramp_is_its_slope_after_the_filter_settles(example):
    t = np.arange(500) * 0.004
    v = example["filtered_difference"](t, np.column_stack([3.0 * t, -t]))
    np.testing.assert_allclose(v[-1], [3.0, -1.0], rtol=1e-9)
    assert abs(v[10, 0] - 3.0 * (1 - np.exp(-50.0 * 10 * 0.004))) < 1e-12      # a first-order lag at 50 rad/s


def test_example_runs_in_a_reduced_form(example, tmp_path, capsys):
    results = example["main"](tmp_path, epochs=1, runs=12, horizon=2.0, cases=("theta_alpha",))
    table, text = results["theta_alpha"]
    assert sorted(table) == [1, 3, 5, 7, 9, 11]
    for run in table.values():
        assert set(run) == {"KKL (bank)", "EKF", "filtered difference"}
        assert np.isfinite(run["KKL (bank)"]).all() and np.isfinite(run["EKF"]).all()
        assert max(run["EKF"][:2]) < 0.01                 # the EKF follows the angles it measures
    assert "| **EKF** | **mean 5-11** |" in text and "(fit)" in text
    assert (tmp_path / "qube_theta_alpha.png").stat().st_size > 20000
    from kklcasadi.model.files import load_model

    model = load_model(tmp_path / "theta_alpha")
    assert model.method == "bank" and model.dt == 0.004
    assert model.spec.measurement_std == pytest.approx(example["encoder_noise"](example["FIT_RUNS"]))
    assert "encoder noise from runs (1, 3)" in capsys.readouterr().out
