"""The ``bank`` variant end to end: trained by train_observer on a few noisy runs, loaded as a
KKLObserver whose step, simulate and C code reproduce the reference estimator of filterbank."""

import shutil
import subprocess
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("torch")

import casadi as ca  # noqa: E402

import kklcasadi as kc  # noqa: E402
from kklcasadi.model.files import load_model  # noqa: E402
from kklcasadi.model.variants import filterbank as fb  # noqa: E402
from kklcasadi.observer.codegen import generate_c
from kklcasadi.train import LoopConfig, default_config, train_observer  # noqa: E402
from kklcasadi.train.operational import DecoderConfig, RolloutConfig  # noqa: E402


@pytest.fixture(scope="module")
def bank_dir(tmp_path_factory):
    config = replace(default_config("rossler", "bank"), y_poles=(0.5, 2.0), u_poles=(1.0,),
                     rollouts=RolloutConfig(n_traj=8, T=4.0),
                     decoder=DecoderConfig(hidden=(8, 8), asinh_scale=(0.0, 0.0, 0.01),
                                           loop=LoopConfig(epochs=2, batch_size=64, schedule="cosine")))
    return train_observer("rossler", "bank", tmp_path_factory.mktemp("bank") / "bank", config=config,
                          progress=False)


def test_bank_card_records_its_noise_level_design_and_domain(bank_dir):
    model = load_model(bank_dir)
    assert model.method == "bank" and model.base is None and model.spec.measurement_std == 0.1
    assert model.card["architecture"]["bank"] == {"y_poles": [0.5, 2.0], "u_poles": [1.0], "y_resonators": [],
                                                  "clock": 0.2, "time_scale": 1.0}
    training = model.card["training"]
    assert training["measurement_std"] == 0.1 and training["process_std"] == [0.1, 0.1, 0.1]
    assert training["runs"]["runs"] == 8 and training["runs"]["cut"] == 0 and training["runs"]["simulated_s"] == 32.0
    assert model.spec.nz == 2 + 1 + 1 and model.spec.domain is not None
    assert np.array_equal(model.arrays["decoder/asinh_scale"], [0.0, 0.0, 0.01])
    # the hook calibrates the decoder-input monitor on the fitting runs and records their input families
    assert model.spec.monitor.features == 4 + 1 + 1 and model.spec.monitor.calibration["fit_runs"] == 6
    # the default runs: every family, the hull of docs/protocol.md's id and ood ranges
    assert model.spec.fit_families["square"] == {"amplitude": (0.1, 2.0), "omega": (0.5, 4.0)}
    assert model.spec.fit_families["feedback"] == {"gain": (0.5, 3.0), "hold": (2.0, 10.0), "limit": (2.0, 2.0)}
    assert set(model.spec.fit_families) == {"zero", "constant", "sinusoid", "square", "multisine", "feedback"}


def test_bank_observer_equals_the_reference_estimator(bank_dir):
    obs = kc.load_observer(bank_dir)
    assert obs.encoder is None and obs.discretization == "exact" and obs.memory_shape == (2, 1)
    tr = kc.simulate(obs.system, [1.0, -2.0, 0.5], kc.signals.make("square", amplitude=0.5, omega=1.0), T=6.0,
                     dt=obs.dt, process_std=0.1, measurement_std=0.1, seed=3)
    model = load_model(bank_dir)
    arrays = {**model.arrays, "bank/A": model.A, "bank/By": model.B}
    expected = fb.estimate(arrays, model.card["architecture"]["decoder"], tr.y, tr.u, obs.dt)
    est = obs.simulate(tr.t, tr.y, tr.u)
    np.testing.assert_allclose(est.xhat, expected, rtol=1e-10, atol=1e-10)
    live = obs.estimator()
    np.testing.assert_allclose([live.make_step(y, u) for y, u in zip(tr.y, tr.u)], est.xhat, rtol=0, atol=1e-13)
    rk4 = kc.load_observer(bank_dir, discretization="rk4", substeps=4).simulate(tr.t, tr.y, tr.u)
    assert np.abs(rk4.xhat - est.xhat).max() < 1e-3 * (1 + np.abs(est.xhat).max())   # RK4 vs exact


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")
def test_bank_compiles_to_c_that_reproduces_simulate(bank_dir, tmp_path):
    obs = kc.load_observer(bank_dir)
    files = generate_c(obs, tmp_path, "bank", math="libm")
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", str(files[0]), str(files[2]), "-lm",
                    "-o", str(tmp_path / "bank")], check=True)
    tr = kc.simulate(obs.system, [0.0, 1.0, 0.2], kc.signals.make("sinusoid", amplitude=0.4, omega=1.5), T=3.0,
                     dt=obs.dt, measurement_std=0.1, seed=1)
    rows = "\n".join(",".join(repr(float(v)) for v in row) for row in np.column_stack([tr.t, tr.y, tr.u]))
    out = subprocess.run([str(tmp_path / "bank")], input=rows + "\n", capture_output=True, text=True, check=True)
    np.testing.assert_array_equal(np.loadtxt(out.stdout.splitlines(), delimiter=",")[:, 1:],
                                  obs.simulate(tr.t, tr.y, tr.u).xhat)


def _arm() -> kc.System:
    """A damped pendulum on a cart-free arm: x = (phi, theta, omega), y = (theta, sin phi); phi and theta
    are angles, theta is measured, phi only through sin phi (a free angle state)."""
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 1)
    return kc.System("arm", x, u, [0.5 * x[2], x[2], -4.0 * ca.sin(x[1]) - 0.3 * x[2] + u],
                     [x[1], ca.sin(x[0])], [[-1.0, 1.0], [-1.5, 1.5], [-2.0, 2.0]], angle_states=(0, 1),
                     angle_outputs=(0,))


@pytest.fixture(scope="module")
def arm_dir(tmp_path_factory):
    config = replace(default_config("arm", "bank", epochs=2), measurement_std=0.01, process_std=(0.0, 0.0, 0.2),
                     rollouts=RolloutConfig(n_traj=8, T=3.0),
                     decoder=DecoderConfig(hidden=(8,), loop=LoopConfig(epochs=2, batch_size=64)))
    return train_observer(_arm(), "bank", tmp_path_factory.mktemp("arm") / "bank", config=config, dt=0.02,
                          progress=False)


def test_a_new_plant_gets_its_own_time_scale_and_its_angles(arm_dir):
    from kklcasadi.plant.design import time_scales

    model = load_model(arm_dir)
    bank = model.card["architecture"]["bank"]
    rate = time_scales(_arm())[0]
    assert bank["time_scale"] == pytest.approx(rate) and rate != 1.0
    np.testing.assert_allclose(bank["y_poles"], np.multiply(default_config("arm", "bank").y_poles, rate))
    assert bank["angles"] == {"outputs": [0], "measured": [[1, 0]], "free": [[0, 0.0]]}
    assert model.spec.nz == 2 * 8 + 5 + 1 and model.card["architecture"]["decoder"]["sizes"] == [22 + 2 + 1 + 1, 8, 4]
    assert model.card["training"]["process_std"] == [0.0, 0.0, 0.2]


def test_the_angle_observer_equals_the_reference_and_its_c_code(arm_dir, tmp_path):
    obs = kc.load_observer(arm_dir, system=_arm())
    tr = kc.simulate(obs.system, [0.3, 1.0, 0.0], kc.signals.make("sinusoid", amplitude=0.5, omega=2.0), T=3.0,
                     dt=obs.dt, measurement_std=0.01, seed=4)
    model = load_model(arm_dir)
    arrays = {**model.arrays, "bank/A": model.A, "bank/By": model.B}
    expected = fb.estimate(arrays, model.card["architecture"]["decoder"], tr.y, tr.u, obs.dt,
                           angles=model.spec.architecture.angles)
    est = obs.simulate(tr.t, tr.y, tr.u)
    np.testing.assert_allclose(est.xhat, expected, rtol=1e-10, atol=1e-10)
    assert np.all(np.abs(est.xhat[:, 0]) <= np.pi)              # the free angle, about its box centre 0
    # theta measured on another branch: theta + 2 pi, up to the start of the filters from z(0) = 0
    moved = obs.simulate(tr.t, tr.y + [2 * np.pi, 0.0], tr.u).xhat
    np.testing.assert_allclose(moved[:, 1] - est.xhat[:, 1], 2 * np.pi, atol=1e-2)
    if shutil.which("gcc") is None:
        return
    files = generate_c(obs, tmp_path, "arm", math="libm")
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", str(files[0]), str(files[2]), "-lm",
                    "-o", str(tmp_path / "arm")], check=True)
    rows = "\n".join(",".join(repr(float(v)) for v in row) for row in np.column_stack([tr.t, tr.y, tr.u]))
    out = subprocess.run([str(tmp_path / "arm")], input=rows + "\n", capture_output=True, text=True, check=True)
    np.testing.assert_allclose(np.loadtxt(out.stdout.splitlines(), delimiter=",")[:, 1:], est.xhat, rtol=0,
                               atol=1e-12)


def test_a_single_process_std_acts_where_process_on_says():
    from kklcasadi.train.bank import BankConfig, process_stds

    arm = _arm()                                   # theta' = omega is kinematic, phi' = 0.5 omega is not
    assert default_config("arm", "bank").process_on == "forced"
    assert default_config("duffing", "bank").process_on == "all"
    np.testing.assert_array_equal(process_stds(arm, BankConfig(process_std=0.3, process_on="forced")), [0.3, 0, 0.3])
    np.testing.assert_array_equal(process_stds(arm, BankConfig(process_std=0.3)), [0.3, 0.3, 0.3])
    np.testing.assert_array_equal(process_stds(arm, BankConfig(process_std=(0.1, 0.2, 0.0))), [0.1, 0.2, 0.0])
    with pytest.raises(ValueError, match="process_std"):
        process_stds(arm, BankConfig(process_std=(0.1, 0.2)))
    with pytest.raises(ValueError, match="process_on"):
        BankConfig(process_on="some")
