"""The robustness benchmark (issue 46.5): its cases and trials, every estimator on the same trials, the report,
and the smallest case end to end from the command line."""

import json

import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi import provenance
from kklcasadi.cli import main
from kklcasadi.estimators import AugmentedEKF, ParameterPF, TunedEKF
from kklcasadi.estimators.pf import ROUGHENING
from kklcasadi.evaluation import generalisation as gen
from kklcasadi.evaluation import robustness as rb
from kklcasadi.evaluation.trialcache import TrialCache
from kklcasadi.observer.kkl import load_observer
from kklcasadi.plant.augment import perturbed

SHORT = rb.Settings(n_trials=3, n_tuning=3, T=6.0)


@pytest.fixture(scope="module")
def family():
    return kc.systems.get("duffing", param_spread=0.3)


def test_the_grid(family):
    grid = rb.cases(family)
    assert [c.name for c in grid] == ["exact", "alpha- beta-", "alpha- beta+", "alpha+ beta-", "alpha+ beta+",
                                      "inside", "damping 0.3", "input gain 0.7", "student-t:2",
                                      "gauss+outliers:0.05,10", "gauss+quantised:0.2"]
    np.testing.assert_allclose(grid[2].params, [0.7, 1.3])
    assert [c.kind for c in grid].count("corner") == 4
    assert len(rb.cases(kc.systems.get("vdp", param_spread=0.3), kinds=["corner"])) == 8
    assert [c.name for c in rb.cases(family, kinds=["outside"], input_gain=1.0)] == ["damping 0.3"]
    assert grid[0].targets == (("ekf", 1.05),) and grid[1].targets == (("tuned", 0.85), ("augmented", 1.0))
    with pytest.raises(ValueError, match=r"^family: expected a plant with parameters"):
        rb.cases(kc.systems.get("duffing"))
    with pytest.raises(ValueError, match=r"^tuning_seed: expected a seed other than the scored trials' \(5\)"):
        rb.Settings(seed=5, tuning_seed=5)


def test_cells_share_their_draws_and_differ_by_what_the_case_changes(family):
    exact, corner, inside, damped, heavy = (rb.RobustCell(c, SHORT) for c in (
        rb.RobustCase("exact", "exact"), rb.RobustCase("c", "corner", (0.7, 1.3)), rb.RobustCase("inside", "inside"),
        rb.RobustCase("damping", "outside", damping=0.3), rb.RobustCase("t", "noise", noise_model="student-t:2")))
    a, b, c, d, e = (cell.simulate(family) for cell in (exact, corner, inside, damped, heavy))
    for batch in (b, c, d, e):
        np.testing.assert_array_equal(batch.x[:, 0], a.x[:, 0])
        np.testing.assert_array_equal(batch.u, a.u)
    np.testing.assert_array_equal(e.x, a.x)                                    # only the measurement differs
    assert not np.array_equal(e.y, a.y)
    # the inputs cycle through the four id families
    assert np.all(a.u[0] == 0) and np.ptp(a.u[1]) == 0 and a.u[1, 0, 0] != 0
    # the corner and the damped plant, against simulations of those plants
    kw = dict(T=6.0, dt=0.05, process_std=0.1, measurement_std=0.1, seed=np.random.SeedSequence([2026, 3]).spawn(3))
    ref = kc.simulate_batch(family.at([0.7, 1.3]), a.x[:, 0], list(a.u), **kw)
    np.testing.assert_allclose(b.x, ref.x, rtol=1e-9, atol=1e-9)
    ref = kc.simulate_batch(perturbed(family, damping=0.3), a.x[:, 0], list(a.u), **kw)
    np.testing.assert_allclose(d.x, ref.x, rtol=1e-12, atol=1e-12)
    drawn = inside.params(family)
    assert drawn.shape == (3, 2) and np.all((drawn >= 0.7) & (drawn <= 1.3)) and len(np.unique(drawn[:, 0])) == 3
    tuning = rb.RobustCell(exact.case, SHORT, tuning=True)
    assert tuning.seed == 4242 and not np.array_equal(tuning.simulate(family).x[:, 0], a.x[:, 0])
    assert exact.describe() != tuning.describe() and exact.describe() != corner.describe()


def test_every_estimator_on_the_same_trials(monitored_bank, family, tmp_path):
    path, _ = monitored_bank
    obs = load_observer(path)
    case_list = [rb.RobustCase("exact", "exact"), rb.RobustCase("alpha+ beta+", "corner", (1.3, 1.3)),
                 rb.RobustCase("damping 0.3", "outside", damping=0.3),
                 rb.RobustCase("t", "noise", noise_model="student-t:2")]
    cache = TrialCache(None)
    report = rb.run([("bank", obs)], family, case_list, SHORT, trials=cache, pf_particles=30, compiler=None)
    nominal = kc.systems.get("duffing")
    for i, case in enumerate(case_list):
        batch = cache.trials(family, rb.RobustCell(case, SHORT))
        tuning = cache.trials(family, rb.RobustCell(case, SHORT, tuning=True))
        est = obs.simulate(batch.t, batch.y, batch.u)
        np.testing.assert_array_equal(report.models["bank"]["smape"][i], kc.metrics.smape(batch.x, est.xhat))
        np.testing.assert_array_equal(report.models["bank"]["flagged_share"][i],
                                      (~est.in_domain[:, batch.t >= 5.0]).mean(axis=1))
        ekf = gen.case_ekf(nominal, 0.1, 0.05)
        np.testing.assert_array_equal(report.baselines["ekf"][i],
                                      kc.metrics.smape(batch.x, ekf.simulate(batch.t, batch.y, batch.u).xhat))
        tuned = TunedEKF.fit(nominal, 0.05, tuning, process_std=0.1, measurement_std=0.1)
        assert report.tuning[i]["tuned"]["q_scale"] == tuned.q_scale
        np.testing.assert_array_equal(report.baselines["tuned"][i],
                                      kc.metrics.smape(batch.x, tuned.simulate(batch.t, batch.y, batch.u).xhat))
        record = report.tuning[i]["augmented"]
        aekf = AugmentedEKF(family, 0.05, q_scale=record["q_scale"], r_scale=record["r_scale"],
                            param_walk=record["param_walk"], input_disturbance=record["input_disturbance"])
        np.testing.assert_array_equal(report.baselines["augmented"][i],
                                      kc.metrics.smape(batch.x, aekf(batch.t, batch.y, batch.u)))
        assert record["score"] == min(record["score_with_disturbance"], record["score_without_disturbance"])
        pf = ParameterPF(family, 0.05, n_particles=30, noise_model=case.noise_model, roughening=ROUGHENING, seed=2026,
                         jit=False)
        np.testing.assert_array_equal(report.baselines["pf"][i], kc.metrics.smape(batch.x, pf(batch.t, batch.y,
                                                                                               batch.u)))
    (check,) = report.checks("bank", 0)
    assert check[:3] == ("ekf", report.mean("bank", 0) / report.mean("ekf", 0), 1.05)
    assert [c[0] for c in report.checks("bank", 1)] == ["tuned", "augmented"]
    met = rb.targets(report, "bank")
    assert set(met) == {c.name for c in case_list}
    assert met["damping 0.3"] == (report.checks("bank", 2)[0][3] and report.flagged("bank", 2) >= 0.5)
    table = report.markdown()
    assert "| alpha+ beta+ | corner | 3 |" in table and "tuned EKF <= 0.85x" in table and "PF (x, p)" in table
    data = json.loads(json.dumps(report.to_json()))
    assert data["cases"][1]["case"]["params"] == [1.3, 1.3] and data["pf_particles"] == 30
    assert data["cases"][0]["models"]["bank"]["targets"][0]["baseline"] == "ekf"
    report.plot(tmp_path / "plot.png")
    assert (tmp_path / "plot.png").read_bytes()[:4] == b"\x89PNG"


def test_run_refuses_observers_of_another_plant(model_dir_factory, family):
    obs = load_observer(model_dir_factory("bank", system="vdp"))
    with pytest.raises(ValueError, match=r"^observers: expected observers of the family's nominal plant"):
        rb.run([("x", obs)], family, rb.cases(family, kinds=["exact"]), SHORT)


def test_the_command(model_dir_factory, tmp_path, capsys):
    path = model_dir_factory("autonomous")                 # no monitor: quick in the VM over 50 s
    out = tmp_path / "rob"
    assert main(["robustness", str(path), "--kinds", "exact", "--trials", "2", "--tuning-trials", "2", "--vm",
                 "--no-cache", "--labels", "mine", "--out", str(out)]) == 0
    assert "| exact | exact | 2 |" in capsys.readouterr().out          # the smallest case, end to end
    data = json.loads((out / "duffing_robustness.json").read_text())
    for written in (out / "duffing_robustness.json", out / "duffing_robustness.md", out / "duffing_robustness.png"):
        stamp = provenance.read(written)
        assert stamp.command.startswith("kklcasadi robustness ") and stamp.seeds == {"trials": 2026, "tuning": 4242}
    assert data["settings"]["seed"] == 2026 and data["settings"]["tuning_seed"] == 4242
    assert (out / "duffing_robustness.png").exists() and (out / "duffing_robustness.md").exists()
    assert main(["robustness", str(path), "--kinds", "exact", "--trials", "2", "--out", str(out)]) == 2
    assert "error: --out: expected a directory without a report of 'duffing'" in capsys.readouterr().err
    assert main(["robustness", str(path), "--param-spread", "1.5", "--kinds", "exact"]) == 2
    assert "error: --param-spread: expected a relative uncertainty 0 < s < 1" in capsys.readouterr().err
