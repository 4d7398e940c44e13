"""MHE and KKL-primed MHE: accuracy on the exact model, fallbacks on solver failure, protocol use."""

import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.estimators.ekf import EKF
from kklcasadi.estimators.kkl_mhe import KKLPrimedMHE, kkl_error_profile
from kklcasadi.estimators.mhe import MHE
from kklcasadi.estimators.solve import SolveRecord, solve_compiled
from kklcasadi.evaluation.protocol import Protocol, evaluate

DT = 0.05


def _run(system, *, T=3.0, noise=0.0, seed=0, kind="square"):
    prot = Protocol(n_trials=2, T=T, seed=seed, process_std=noise, measurement_std=noise)
    return prot.trials(system, kind)


@pytest.mark.parametrize("name", ["duffing", "vdp"])
def test_noise_free_mhe_recovers_the_state_once_the_window_is_full(name):
    plant = kc.systems.get(name)
    batch = _run(plant)
    mhe = MHE(plant, DT, 5, process_std=0.0, measurement_std=0.0)
    run = mhe.simulate(batch.t, batch.y, batch.u)
    assert run.xhat.shape == batch.x.shape
    late = batch.t >= 1.0
    assert np.max(np.abs(run.xhat[:, late] - batch.x[:, late])) < 2e-2
    assert run.stats.n_failed == 0
    assert run.stats.iterations.shape == batch.y.shape[:2]
    assert set(run.stats.statuses) <= {"Solve_Succeeded", "Solved_To_Acceptable_Level"}


def test_single_trajectory_shapes_and_protocol_evaluate():
    plant = kc.systems.get("duffing")
    batch = _run(plant, T=1.0)
    mhe = MHE(plant, DT, 4)
    single = mhe.simulate(batch.t, batch.y[0], batch.u[0])
    assert single.xhat.shape == (batch.t.size, 2)
    both = mhe.simulate(batch.t, batch.y, batch.u)
    np.testing.assert_allclose(single.xhat, both.xhat[0], rtol=0, atol=1e-10)
    cells = evaluate(mhe, plant, Protocol(n_trials=2, T=1.0, t_settle=0.5), kinds=("zero",))
    assert cells[0].smape.shape == (2,) and np.all(np.isfinite(cells[0].smape))
    assert mhe.last_stats.n_solves == 2 * batch.t.size


def test_noisy_mhe_matches_the_ekf_with_its_arrival_cost():
    """The EKF arrival cost makes the MHE at least as good as the EKF it generalises."""
    plant = kc.systems.get("duffing")
    batch = _run(plant, T=6.0, noise=0.1, seed=3)
    mhe = MHE(plant, DT, 10).simulate(batch.t, batch.y, batch.u)
    ekf = EKF(plant, DT).simulate(batch.t, batch.y, batch.u)
    s_mhe = kc.metrics.smape(batch.x, mhe.xhat).mean()
    s_ekf = kc.metrics.smape(batch.x, ekf.xhat).mean()
    assert s_mhe <= 1.05 * s_ekf


def test_failed_solve_falls_back_to_the_propagated_estimate_and_is_counted():
    plant = kc.systems.get("vdp")
    batch = _run(plant, T=1.0)
    mhe = MHE(plant, DT, 5, max_iter=1)
    run = mhe.simulate(batch.t, batch.y[0], batch.u[0])
    failed = run.stats.failed[0]
    assert run.stats.n_failed == failed.sum() > 0
    assert run.stats.statuses.get("Maximum_Iterations_Exceeded", 0) == run.stats.n_failed
    for k in np.flatnonzero(failed[1:]) + 1:
        expected = np.asarray(mhe.phi(run.xhat[k - 1], batch.u[0, k - 1], np.zeros(2))).ravel()
        np.testing.assert_allclose(run.xhat[k], expected, rtol=0, atol=1e-12)
    assert "failed" in str(run.stats)


def test_primed_mhe_falls_back_to_the_kkl_estimate(model_dir_factory):
    obs = kc.load_observer(model_dir_factory("autonomous", "duffing", seed=4))
    batch = _run(obs.system, T=1.0)
    primed = KKLPrimedMHE(obs, np.full(2, 0.5), horizon=3, max_iter=1)
    run = primed.simulate(batch.t, batch.y, batch.u)
    guide = obs.simulate(batch.t, batch.y, batch.u).xhat
    failed = run.stats.failed
    assert failed.any()
    np.testing.assert_allclose(run.xhat[failed], guide[failed], rtol=0, atol=1e-12)


def test_primed_mhe_corrects_a_poor_observer_without_noise(model_dir_factory):
    """A random-weight observer is a poor guide; the MHE still finds the state from the data."""
    obs = kc.load_observer(model_dir_factory("autonomous", "duffing", seed=5))
    batch = _run(obs.system, T=2.0)
    profile = np.full((batch.t.size, 2), 2.0)
    primed = KKLPrimedMHE(obs, profile, horizon=8, process_std=0.0, measurement_std=0.0)
    xhat = primed(batch.t, batch.y, batch.u)
    guide = obs.simulate(batch.t, batch.y, batch.u).xhat
    late = batch.t >= 1.0
    err_primed = np.max(np.abs(xhat[:, late] - batch.x[:, late]))
    err_guide = np.max(np.abs(guide[:, late] - batch.x[:, late]))
    assert err_primed < 0.05 < err_guide
    assert primed.last_stats.n_failed == 0


def test_kkl_error_profile_is_positive_and_per_sample(model_dir_factory):
    obs = kc.load_observer(model_dir_factory("autonomous", "duffing", seed=6))
    profile = kkl_error_profile(obs, Protocol(n_trials=2, T=1.0, seed=9), kinds=("zero",),
                                floor=0.1)
    assert profile.shape == (20, 2)
    assert np.all(profile >= 0.1 * 1.0 - 1e-15)


def test_solve_compiled_reports_status_iterations_and_time():
    import casadi as ca

    opti = ca.Opti()
    x, p = opti.variable(), opti.parameter()
    opti.minimize((x - p) ** 2)
    opti.solver("ipopt", {"print_time": False, "error_on_fail": False},
                {"print_level": 0, "sb": "yes"})
    outputs, record = solve_compiled(opti.to_function("f", [p, x], [x]), [2.0, 0.0])
    assert isinstance(record, SolveRecord)
    assert record.success and record.status == "Solve_Succeeded" and record.iterations >= 1
    assert record.seconds > 0
    np.testing.assert_allclose(outputs[0], [[2.0]], atol=1e-8)


@pytest.mark.parametrize("kwargs, error, fragment", [
    ({"horizon": 0}, ValueError, "horizon"),
    ({"horizon": 2.5}, TypeError, "horizon"),
    ({"process_std": -1.0}, ValueError, "process_std"),
    ({"noise_floor": 0.0}, ValueError, "noise_floor"),
    ({"P0": np.eye(3)}, ValueError, "P0"),
])
def test_bad_arguments_are_named(kwargs, error, fragment):
    with pytest.raises(error, match=fragment):
        MHE(kc.systems.get("duffing"), DT, **kwargs)


def test_bad_data_is_named():
    plant = kc.systems.get("duffing")
    mhe = MHE(plant, DT, 3)
    t = np.arange(5) * DT
    with pytest.raises(ValueError, match="y: expected shape"):
        mhe.simulate(t, np.zeros((4, 1)), np.zeros((4, 1)))
    with pytest.raises(ValueError, match="t: expected samples spaced"):
        mhe.simulate(t * 2, np.zeros((5, 1)), np.zeros((5, 1)))
    with pytest.raises(ValueError, match="guide_std: required"):
        mhe.simulate(t, np.zeros((5, 1)), np.zeros((5, 1)), guide=np.zeros((5, 2)))
    y = np.zeros((5, 1))
    y[2] = np.nan
    with pytest.raises(ValueError, match="y: expected finite values"):
        mhe.simulate(t, y, np.zeros((5, 1)))


def test_compare_command_writes_json_and_table(model_dir_factory, tmp_path, capsys):
    """``kklcasadi compare`` reduced: one trial, half a second, one regime, noise off."""
    import json
    import shutil

    from kklcasadi.cli import main
    from kklcasadi.evaluation.compare import SystemComparison
    from kklcasadi.evaluation.report import markdown_table

    root = tmp_path / "models"
    shutil.copytree(model_dir_factory("bank", "duffing", seed=2), root / "duffing" / "bank")
    out = tmp_path / "out"
    assert main(["compare", "--systems", "duffing", "--models-root", str(root), "--trials", "1",
                 "--T", "0.5", "--kinds", "zero", "--noise", "off", "--horizons", "3",
                 "--primed-horizon", "2", "--calibration-trials", "1", "--out", str(out),
                 "--quiet"]) == 0
    from kklcasadi import provenance

    comparison = SystemComparison.from_json(json.loads((out / "duffing.json").read_text()))
    for name in ("duffing.json", "table.md"):
        stamp = provenance.read(out / name)
        assert stamp.command.startswith("kklcasadi compare --systems duffing") and stamp.seeds == {"trials": 2026,
                                                                                                   "calibration": 2027}
    assert [s.label for s in comparison.scores] == ["KKL (bank)", "EKF", "MHE N=3", "KKL-primed MHE N=2"]
    cells = [cell for s in comparison.scores for cell in s.results.values()]
    assert len(cells) == 4 and all(cell.n_samples == 10 and len(cell.smape) == 1 for cell in cells)
    table = provenance.strip_markdown((out / "table.md").read_text())
    assert table.strip() == markdown_table(comparison.scores, ("zero",), timing=True)
    assert "| duffing (1 trials) | MHE N=3 |" in table
    # a system's comparison is never written over: refused in one line before any run
    kept = (out / "duffing.json").read_bytes()
    capsys.readouterr()
    assert main(["compare", "--systems", "duffing", "--models-root", str(root), "--out", str(out)]) == 2
    assert capsys.readouterr().err == (f"error: --out: {out / 'duffing.json'} exists and this command does not "
                                       "overwrite; move it away, or choose another --out.\n")
    # a saved comparison the table would gather that cannot be read: refused in one line before any run
    for text, what in (("{", "JSONDecodeError"), ("{}", "KeyError: 'cells'")):
        (out / "vdp.json").write_text(text)
        assert main(["compare", "--systems", "duffing", "--models-root", str(root), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: --out: expected {out / 'vdp.json'} to be a comparison kklcasadi compare "
                              f"wrote, received a file it cannot read ({what}") and err.count("\n") == 1
        assert (out / "duffing.json").read_bytes() == kept


def test_mhe_example_runs_reduced(model_dir_factory, tmp_path, monkeypatch):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "examples" / "mhe_estimation.py"
    spec = importlib.util.spec_from_file_location("mhe_example", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    model = model_dir_factory("autonomous", "duffing", seed=3)
    png = tmp_path / "mhe.png"
    results = example.main(["--model", str(model), "--T", "0.5", "--horizon", "3",
                            "--primed-horizon", "2", "--calibration-trials", "1",
                            "--out", str(png)])
    assert list(results) == ["KKL (autonomous)", "EKF", "MHE N=3", "KKL-primed MHE N=2"]
    assert all(xhat.shape == (10, 2) and np.all(np.isfinite(xhat)) for xhat in results.values())
    assert png.stat().st_size > 0
    first = png.read_bytes()
    with pytest.raises(FileExistsError, match="^--out: .*mhe.png exists and this command does not overwrite"):
        example.main(["--model", str(model), "--out", str(png)])            # refused before any work
    assert png.read_bytes() == first
    # a plot that fails leaves nothing at --out and nothing beside it
    monkeypatch.setattr(example.plt.Figure, "savefig", lambda *a, **k: (_ for _ in ()).throw(OSError("disk")))
    with pytest.raises(OSError, match="disk"):
        example.main(["--model", str(model), "--T", "0.5", "--horizon", "3", "--primed-horizon", "2",
                      "--calibration-trials", "1", "--out", str(tmp_path / "again.png")])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mhe.png"]


def test_the_primed_mhe_takes_the_observers_covariance_as_its_arrival_cost(model_dir_factory):
    """With error_std=None the arrival prior of each window is the observer's own covariance of its estimate
    there, trial by trial (the MHE with guide_cov = Estimate.cov); a diagonal guide_cov is guide_std, bitwise."""
    from test_observer_covariance import with_head

    path, _, _ = with_head(model_dir_factory("bank", hidden=(9, 7)))
    obs = kc.load_observer(path)
    batch = _run(obs.system, T=0.5, noise=0.1)
    primed = KKLPrimedMHE(obs, None, horizon=3)
    run = primed.simulate(batch.t, batch.y, batch.u)
    est = obs.simulate(batch.t, batch.y, batch.u)
    same = primed.mhe.simulate(batch.t, batch.y, batch.u, guide=est.xhat, guide_cov=est.cov)
    np.testing.assert_array_equal(run.xhat, same.xhat)
    std = np.full((batch.t.size, 2), 0.3)
    diagonal = np.broadcast_to(np.eye(2) * 0.09, est.cov.shape)
    np.testing.assert_array_equal(primed.mhe.simulate(batch.t, batch.y, batch.u, guide=est.xhat, guide_std=std).xhat,
                                  primed.mhe.simulate(batch.t, batch.y, batch.u, guide=est.xhat,
                                                      guide_cov=diagonal).xhat)
    assert not np.array_equal(run.xhat, primed.mhe.simulate(batch.t, batch.y, batch.u, guide=est.xhat,
                                                             guide_std=std).xhat)
    with pytest.raises(ValueError, match="error_std: expected the observer's errors' std, or None for a model with "
                                         "a covariance head"):
        KKLPrimedMHE(kc.load_observer(model_dir_factory("bank")), None)
    with pytest.raises(ValueError, match=r"guide_cov: expected positive definite covariances of shape \(2, 10, 2, 2\)"):
        primed.mhe.simulate(batch.t, batch.y, batch.u, guide=est.xhat, guide_cov=est.cov[:, :, :1])
    with pytest.raises(ValueError, match="guide_std, guide_cov: expected one of them"):
        primed.mhe.simulate(batch.t, batch.y, batch.u, guide=est.xhat, guide_std=std, guide_cov=est.cov)
