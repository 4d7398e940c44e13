"""The ``bank`` variant end to end: trained by train_observer on a few noisy runs, loaded as a
KKLObserver whose step, simulate and C code reproduce the reference estimator of filterbank."""

import shutil
import subprocess
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("torch")

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
                                                  "clock": 0.2}
    assert model.spec.nz == 2 + 1 + 1 and model.spec.domain is not None
    assert np.array_equal(model.arrays["decoder/asinh_scale"], [0.0, 0.0, 0.01])
    # the hook calibrates the decoder-input monitor on the fitting runs and records their input families
    assert model.spec.monitor.features == 4 + 1 + 1 and model.spec.monitor.calibration["fit_runs"] == 6
    assert model.spec.fit_families["square"] == {"amplitude": (0.1, 1.0), "omega": (0.5, 2.0)}
    assert set(model.spec.fit_families) == {"zero", "constant", "sinusoid", "square"}


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
