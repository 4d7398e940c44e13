"""examples/qube_hardware.py in a reduced form: a tiny training budget, every log estimated and scored."""

import json
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
    # the encoders' noise about a smoothing: below their resolution's 1e-3 rad (examples/qube/data/README.md)
    assert 1e-4 < example["encoder_noise"](example["FIT_RUNS"]) < 1e-3


@pytest.mark.parametrize("case", ["theta_alpha", "alpha"])
def test_the_settings_are_the_ones_chosen_on_the_fit_runs(example, case):
    """Each case's flags are those of the best fit-run record of benchmarks/accuracy/qube.py (runs 1, 3, 5)."""
    root = EXAMPLE.parents[1] / "results" / "real_rig" / "qube"
    outputs = {"theta_alpha": "both", "alpha": "alpha"}[case]
    records = [json.loads(f.read_text()) for f in root.glob(f"*_{outputs}_fit.json")]
    tried = [r for r in records if r["args"] and r["args"]["n_traj"] == "1000" and r["args"]["T"] == "60.0"
             and r["args"]["epochs"] == "15" and r["args"]["process_all"] == "False"]
    assert len(tried) >= 2 and all(r["runs"] == "fit" for r in tried)
    best = min(tried, key=lambda r: r["bank"]["mean"]["velocities"])
    assert {"--measurement-std": float(best["args"]["measurement_std"]),
            "--process-std": float(best["args"]["process_std"]),
            "--box-scale": float(best["args"]["box_scale"])} == example["CHOSEN"][case]


def test_the_filtered_difference_of_a_ramp_is_its_slope_after_the_filter_settles(example):
    t = np.arange(500) * 0.004
    v = example["filtered_difference"](t, np.column_stack([3.0 * t, -t]))
    np.testing.assert_allclose(v[-1], [3.0, -1.0], rtol=1e-9)
    assert abs(v[10, 0] - 3.0 * (1 - np.exp(-50.0 * 10 * 0.004))) < 1e-12      # a first-order lag at 50 rad/s


@pytest.mark.parametrize("recipe", ["like", "chosen"])
def test_example_runs_in_a_reduced_form(example, tmp_path, capsys, monkeypatch, recipe):
    results = example["main"](tmp_path, epochs=1, runs=12, horizon=2.0, cases=("theta_alpha",), recipe=recipe)
    table, text = results["theta_alpha"]
    assert sorted(table) == [1, 3, 5, 7, 9, 11]
    for run in table.values():
        assert set(run) == {"KKL (bank)", "EKF", "EKF (check_logs)", "filtered difference"}
        assert np.isfinite(run["KKL (bank)"]).all() and np.isfinite(run["EKF"]).all()
        assert max(run["EKF"][:2]) < 0.01 and max(run["EKF (check_logs)"][:2]) < 0.01   # they follow the angles
    assert "| **EKF** | **mean 7, 9, 11** |" in text and "(fit)" in text and "| bank / EKF |" in text
    assert (tmp_path / "qube_theta_alpha.png").stat().st_size > 20000
    record = json.loads((tmp_path / "qube_hardware.json").read_text())["theta_alpha"]
    data = "examples/qube/data/free_swing_"
    assert record["command"] == {
        "like": ("kklcasadi train --plant examples/qube/qube_plant.py:make_plant --dt 0.004 "
                 f"--like {data}1.csv --like {data}3.csv --like {data}5.csv --time-col time --y-cols theta,alpha "
                 "--u-zero --out DIR"),
        "chosen": ("kklcasadi train --plant examples/qube/qube_plant.py:make_plant --dt 0.004 "
                   "--measurement-std 0.001 --process-std 16.0 --box-scale 0.5 --out DIR")}[recipe]
    np.testing.assert_allclose(record["scored_mean"]["EKF"], np.mean([table[k]["EKF"] for k in (7, 9, 11)], axis=0))
    from kklcasadi.model.files import load_model

    model = load_model(tmp_path / "theta_alpha")
    assert model.method == "bank" and model.dt == 0.004
    training = model.card["training"]
    assert training["rollouts"]["n_traj"] == 12
    if recipe == "chosen":
        assert model.spec.measurement_std == 1e-3 and model.spec.process_std == (0.0, 0.0, 16.0, 16.0)
        assert training["rollouts"]["box_scale"] == 0.5 and training["rollouts"]["envelope"] is None
    else:                       # the noise estimated from the development runs, the same the EKF beside runs with
        envelope = training["rollouts"]["envelope"]
        assert [s["path"].rsplit("/", 1)[-1] for s in envelope["sources"]] == [f"free_swing_{k}.csv" for k in (1, 3, 5)]
        assert 3e-4 < model.spec.measurement_std < 1e-3 and model.spec.process_std[:2] == (0.0, 0.0)
        assert all(5.0 < q < 30.0 for q in model.spec.process_std[2:])
        assert training["runs"]["escape_scale"] == 1.25 and "like" in training["runs"]["kinds"]
    assert "kklcasadi train --plant" in capsys.readouterr().out
    from kklcasadi import provenance

    assert provenance.read(tmp_path / "qube_theta_alpha.png") == provenance.read(tmp_path / "qube_hardware.json")
    if recipe == "chosen":
        # a run that fails in its second case after the first's plot: no plot and no scores written, not even a part
        import shutil

        def train(case, out, **_):
            if case == "alpha":
                raise OSError("disk")
            return shutil.copytree(tmp_path / case, out / case)          # this run's model, not trained again

        monkeypatch.setitem(example["main"].__globals__, "train", train)
        with pytest.raises(OSError, match="disk"):
            example["main"](tmp_path / "again", cases=("theta_alpha", "alpha"), recipe=recipe)
        assert [p.name for p in (tmp_path / "again").iterdir()] == ["theta_alpha"]


@pytest.mark.parametrize("taken, flag", [("alpha", "--out"), ("qube_alpha.png", "--out"),
                                         ("scores.json", "--results")])
def test_example_refuses_any_file_it_would_write_before_any_work(example, tmp_path, taken, flag):
    (tmp_path / taken).write_text("kept")
    with pytest.raises(FileExistsError, match=f"^{flag}: .*{taken} exists and this command does not overwrite"):
        example["main"](tmp_path, results=tmp_path / "scores.json")
    assert [p.name for p in tmp_path.iterdir()] == [taken] and (tmp_path / taken).read_text() == "kept"
