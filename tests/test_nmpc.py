"""Output-feedback NMPC: set points, constraints, warm starts, failures, the EKF in the loop, the example."""

import importlib.util
import shutil
from pathlib import Path

import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.estimators.ekf import EKF
from kklcasadi.estimators.nmpc import NMPC, EKFEstimator, TrueState, closed_loop, plant_step, steady_state

DT = 0.05
EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "nmpc_output_feedback.py"


@pytest.mark.parametrize("name, r, u_expected", [("duffing", 0.8, 0.8 + 0.8 ** 3),
                                                  ("vdp", -1.0, -1.0)])
def test_steady_state_solves_f_equal_zero(name, r, u_expected):
    x_ref, u_ref = steady_state(kc.systems.get(name), r)
    np.testing.assert_allclose(x_ref, [r, 0.0], atol=1e-12)
    np.testing.assert_allclose(u_ref, [u_expected], atol=1e-12)


def test_steady_state_needs_a_single_input(mimo_plant):
    with pytest.raises(ValueError, match="nu = 2"):
        steady_state(mimo_plant, 0.5)


def _regulate(name, **options):
    plant = kc.systems.get(name)
    target = steady_state(plant, 0.5)
    ctl = NMPC(plant, DT, 8, state_bounds={1: (-0.6, 0.6)}, **options)
    run = closed_loop(ctl, TrueState(), lambda t: target, [-0.5, 0.0], 3.0, process_std=0.0,
                      measurement_std=0.0)
    return ctl, run, target


@pytest.mark.parametrize("name", ["duffing", "vdp"])
def test_true_state_nmpc_reaches_the_set_point_within_bounds(name):
    ctl, run, (x_ref, _u_ref) = _regulate(name)
    assert np.all(run.u >= -2.0 - 1e-9) and np.all(run.u <= 2.0 + 1e-9)
    assert abs(run.x[-1, 0] - x_ref[0]) < 0.05
    assert run.violation.max() < 0.02                 # soft bound |x2| <= 0.6
    assert not run.failed.any()
    assert run.solve_time.shape == run.iterations.shape == (run.t.size - 1,)
    assert run.statuses == {"Solve_Succeeded": run.t.size - 1}
    assert run.cost == pytest.approx(np.mean(run.stage_cost))


def test_warm_start_cuts_iterations():
    ctl, run, _ = _regulate("duffing")
    assert run.iterations[0] > np.median(run.iterations[10:])


def test_failed_solve_applies_the_previous_plan_and_is_reported():
    _, run, _ = _regulate("duffing", max_iter=2)
    assert run.failed.any()
    assert sum(v for k, v in run.statuses.items() if k != "Solve_Succeeded") == run.failed.sum()
    assert np.all(np.abs(run.u) <= 2.0 + 1e-9)


def test_ekf_estimator_equals_the_batch_ekf():
    plant = kc.systems.get("vdp")
    tr = kc.simulate(plant, [1.0, -0.5], kc.signals.make("sinusoid", amplitude=0.5, omega=1.0),
                     T=2.0, dt=DT, process_std=0.1, measurement_std=0.1, seed=2)
    est = EKFEstimator(plant, DT)
    stepped = np.array([est.make_step(y, u) for y, u in zip(tr.y, tr.u)])
    np.testing.assert_allclose(stepped, EKF(plant, DT).simulate(tr.t, tr.y, tr.u).xhat,
                               rtol=0, atol=1e-10)


def test_plant_step_matches_simulate():
    plant = kc.systems.get("duffing")
    tr = kc.simulate(plant, [0.3, 0.1], np.full((3, 1), 0.4), T=3 * DT, dt=DT)
    x1 = np.asarray(plant_step(plant, DT)(tr.x[0], 0.4, np.zeros(2))).ravel()
    np.testing.assert_allclose(x1, tr.x[1], rtol=0, atol=1e-9)


@pytest.mark.parametrize("kwargs, error, fragment", [
    ({"horizon": 0}, ValueError, "horizon"),
    ({"u_bounds": (1.0, -1.0)}, ValueError, "u_bounds"),
    ({"state_bounds": {5: (0, 1)}}, ValueError, "state_bounds"),
    ({"state_bounds": {1: (1.0, 0.0)}}, ValueError, r"state_bounds\[1\]"),
    ({"Q": np.eye(3)}, ValueError, "Q"),
])
def test_bad_arguments_are_named(kwargs, error, fragment):
    with pytest.raises(error, match=fragment):
        NMPC(kc.systems.get("duffing"), DT, **kwargs)


def test_closed_loop_checks_its_estimator():
    ctl = NMPC(kc.systems.get("duffing"), DT, 3)
    with pytest.raises(TypeError, match="make_step"):
        closed_loop(ctl, object(), lambda t: (np.zeros(2), np.zeros(1)), [0, 0], 1.0)


def test_example_runs_reduced(model_dir_factory, tmp_path):
    """examples/nmpc_output_feedback.py end to end: a few steps, all three feeds, table and PNG."""
    root = tmp_path / "models"
    shutil.copytree(model_dir_factory("inject", "duffing", seed=1), root / "duffing" / "inject")
    spec = importlib.util.spec_from_file_location("nmpc_example", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    out = tmp_path / "out"
    result = example.main(["--systems", "duffing", "--models-root", str(root), "--T", "0.5",
                           "--horizon", "4", "--trials", "1", "--settle", "0.2",
                           "--out", str(out)])
    feeds = [row["feed"] for row in result["rows"]]
    assert feeds == ["true state", "EKF", "KKL (inject)"]
    assert (out / "nmpc.png").stat().st_size > 0
    assert "| duffing | KKL (inject) |" in (out / "nmpc_table.md").read_text()
    for row in result["rows"]:
        assert row["u_max"] <= 2.0 + 1e-9 and np.isfinite(row["cost"])
    # the three files are one artefact: written in one step, every one stamped, nothing left beside them
    from kklcasadi import provenance

    assert sorted(p.name for p in out.iterdir()) == ["nmpc.json", "nmpc.png", "nmpc_table.md"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    assert {provenance.read(out / name).seeds["initial_states_and_noise"] for name in
            ("nmpc.json", "nmpc.png", "nmpc_table.md")} == {0}
    # never written over: a second run to the same --out is refused before any run
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(FileExistsError, match="^--out: .*nmpc_table.md exists and this command does not overwrite"):
        example.main(["--systems", "duffing", "--models-root", str(root), "--out", str(out)])
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_example_tightens_the_bound_by_k_sigma_of_a_covariance_head(model_dir_factory, tmp_path):
    from test_observer_covariance import with_head

    root = tmp_path / "models"
    path, _, _ = with_head(model_dir_factory("bank", "duffing", seed=1))
    shutil.copytree(path, root / "duffing" / "bank")
    spec = importlib.util.spec_from_file_location("nmpc_example", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    result = example.main(["--systems", "duffing", "--models-root", str(root), "--method", "bank", "--T", "0.3",
                           "--horizon", "4", "--trials", "1", "--settle", "0.2", "--tighten", "2",
                           "--out", str(tmp_path / "out")])
    assert [row["feed"] for row in result["rows"]][-1] == "KKL (bank), x2 bound - 2 sigma"


def test_a_margin_tightens_the_soft_state_bounds():
    """``solve(margin=m)``: the plan keeps ``|x2| <= 0.3 - m`` (the slack's exact L1 penalty keeps it at the
    tightened bound), where without the margin it reaches 0.3."""
    plant = kc.systems.get("duffing")
    x_ref, u_ref = steady_state(plant, 0.8)
    peaks = []
    for m in (0.0, 0.2):
        ctl = NMPC(plant, DT, 10, state_bounds={1: (-0.3, 0.3)})
        assert not ctl.solve([0.0, 0.0], x_ref, u_ref, margin=[m]).fallback
        peaks.append(np.max(np.abs(ctl._plan[0][1])))
    assert peaks[0] == pytest.approx(0.3, abs=1e-3) and peaks[1] == pytest.approx(0.1, abs=1e-3)
    with pytest.raises(ValueError, match="margin: expected tightenings >= 0"):
        ctl.solve([0.0, 0.0], x_ref, u_ref, margin=[-0.1])


def test_the_closed_loop_tightens_by_k_sigma_of_the_estimate():
    """``tighten=k`` passes ``k sqrt(P_ii)`` of the estimator's covariance as the margin at every sample (the
    EKF's here; a learned observer's covariance head the same way), and refuses an estimator without one."""
    plant = kc.systems.get("duffing")
    target = steady_state(plant, 0.5)
    margins = []

    class Recording(NMPC):
        def solve(self, x_init, x_ref, u_ref, *, margin=None):
            margins.append(margin)
            return super().solve(x_init, x_ref, u_ref, margin=margin)

    ctl = Recording(plant, DT, 8, state_bounds={1: (-0.6, 0.6)})
    ekf = EKFEstimator(plant, DT)
    stds = []
    original = ekf.make_step

    def make_step(y, u):
        xhat = original(y, u)
        stds.append(np.sqrt(ekf.cov[1, 1]))
        return xhat

    ekf.make_step = make_step
    closed_loop(ctl, ekf, lambda t: target, [-0.5, 0.0], 0.5, tighten=2.0)
    np.testing.assert_array_equal(np.ravel(margins), 2.0 * np.array(stds[:-1]))
    with pytest.raises(ValueError, match="tighten: expected an estimator that reports its covariance"):
        closed_loop(ctl, TrueState(), lambda t: target, [-0.5, 0.0], 0.5, tighten=1.0)
