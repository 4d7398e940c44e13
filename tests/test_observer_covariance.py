"""The covariance head in the observer: the card holds it, the CasADi step and ``Estimate.cov``/``var`` give the
covariance of every estimate (equal to the numpy reference of :mod:`kklcasadi.model.variants.covariance`, the
estimates bitwise those of the step without it), the stateful estimator the same, and the generated C's
``name_step`` gains the covariance output (bitwise the CasADi VM with the C library's math, within 1e-12 with the
vector kernels)."""

import json
import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest

from kklcasadi.model.files import load_model, save_model
from kklcasadi.model.variants.covariance import COVARIANCE, SCALE, array_shapes, covariance_numpy
from kklcasadi.model.variants.filterbank import decoder_features
from kklcasadi.nets.specs import MLPSpec
from kklcasadi.observer.codegen import generate_c
from kklcasadi.observer.kkl import load_observer

GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc is not installed")


def with_head(path, hidden=(6,), seed=0, scale=(0.7, 1.3), asinh=None):
    """Give the bank model at ``path`` a random covariance head (in place; a test's own directory), and
    optionally the decoder's output map ``asinh`` scales."""
    model = load_model(path)
    nx = model.spec.system.nx
    n_in = model.card["architecture"]["decoder"]["sizes"][0]
    spec = MLPSpec((n_in, *hidden, nx * (nx + 1) // 2))
    rng = np.random.default_rng(seed)
    arrays = {}
    for name, shape in array_shapes(spec, nx).items():
        arrays[name] = (rng.normal(size=shape) / np.sqrt(shape[-1]) if len(shape) == 2
                        else 0.3 * rng.normal(size=shape))
    for name in arrays:
        if name.endswith("_std"):
            arrays[name] = rng.uniform(0.5, 2.0, arrays[name].shape)
    arrays[SCALE] = np.asarray(scale, dtype=float)
    if asinh is not None:
        arrays["decoder/asinh_scale"] = np.asarray(asinh, dtype=float)
    card = json.loads(json.dumps(model.card))
    card["architecture"][COVARIANCE] = spec.to_card()
    return save_model(path, {**model.arrays, **arrays}, card, overwrite=True), spec, arrays


def runs(obs, m=3, n=30, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * obs.dt
    y = np.sin(1.3 * t)[None, :, None] + 0.2 * rng.normal(size=(m, n, obs.ny))
    u = 0.8 * np.sign(np.sin(2.0 * t + rng.uniform(0, 3, (m, 1))))[..., None]
    return t, y, u


@pytest.fixture
def headed(model_dir_factory):
    path, spec, arrays = with_head(model_dir_factory("bank", hidden=(9, 7)))
    return load_observer(path), spec, arrays


def test_the_card_holds_the_head_and_the_observer_gives_the_reference_covariance(model_dir_factory):
    path, spec, arrays = with_head(model_dir_factory("bank", hidden=(9, 7)), asinh=[0.0, 0.4])
    obs = load_observer(path)
    assert obs.model.card["architecture"][COVARIANCE] == spec.to_card()
    t, y, u = runs(obs)
    est = obs.simulate(t, y, u)
    assert est.cov.shape == (3, t.size, 2, 2) and est.var.shape == (3, t.size, 2)
    model = obs.model
    f = decoder_features(est.z, y, u)
    expected = covariance_numpy(spec, arrays, f, est.xhat, model.arrays["decoder/out_std"],
                                model.arrays["decoder/asinh_scale"])
    np.testing.assert_allclose(est.cov, expected, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(est.var, np.diagonal(est.cov, axis1=-2, axis2=-1))
    assert np.all(np.linalg.eigvalsh(est.cov) > 0)
    one = obs.simulate(t, y[1], u[1])                                  # one trial: (N, nx, nx)
    np.testing.assert_array_equal(one.cov, est.cov[1])


def test_the_estimates_are_bitwise_those_of_the_step_without_the_head(headed, model_dir_factory):
    obs, _, _ = headed
    plain = load_observer(model_dir_factory("bank", hidden=(9, 7)))             # same seed: same decoder
    assert plain.covariance is None and plain.step_covariance is None
    t, y, u = runs(obs)
    a, b = obs.simulate(t, y, u), plain.simulate(t, y, u)
    np.testing.assert_array_equal(a.xhat, b.xhat)
    np.testing.assert_array_equal(a.z, b.z)
    assert b.cov is None and b.var is None
    rng = np.random.default_rng(2)
    args = [rng.normal(size=obs.step.size_in(k)) for k in range(5)]
    for x, y_ in zip(obs.step_covariance(*args)[:3], obs.step(*args)):
        np.testing.assert_array_equal(np.array(x), np.array(y_))
    P = np.array(obs.step_covariance(*args)[3])
    z_next, w_next, xhat_next = obs.step(*args)
    np.testing.assert_array_equal(P, np.array(obs.covariance(z_next, w_next, xhat_next)))


def test_the_estimator_gives_the_covariance_of_simulate(headed):
    obs, _, _ = headed
    t, y, u = runs(obs, m=1)
    est = obs.simulate(t, y[0], u[0])
    stepper = obs.estimator()
    assert stepper.cov is None
    for k in range(t.size):
        stepper.make_step(y[0, k], u[0, k])
        np.testing.assert_allclose(stepper.cov, est.cov[k], rtol=1e-13, atol=0)


def test_a_head_with_wrong_sizes_is_refused(model_dir_factory):
    path = model_dir_factory("bank")
    model = load_model(path)
    card = json.loads(json.dumps(model.card))
    card["architecture"][COVARIANCE] = {"sizes": [card["architecture"]["decoder"]["sizes"][0], 4, 2],
                                        "activation": "tanh"}
    (path / "card.json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match=r"architecture\.covariance\.sizes.*nx \(nx \+ 1\) / 2 = 3"):
        load_model(path)
    card["architecture"]["covariances"] = card["architecture"].pop(COVARIANCE)
    (path / "card.json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match=r"'architecture'.*optionally \['covariance'\]"):
        load_model(path)


@needs_gcc
@pytest.mark.parametrize("math, tol", [("libm", 0.0), ("vector", 1e-12)])
def test_the_c_step_gains_the_covariance_output(headed, tmp_path, math, tol):
    obs, _, _ = headed
    files = generate_c(obs, tmp_path, "cov", math=math)
    header = files[1].read_text()
    assert "#define COV_HAS_COVARIANCE 1" in header and "res[3] P_next" in header
    library = tmp_path / "libcov.so"
    subprocess.run([GCC, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-fPIC", "-shared", str(files[0]),
                    "-o", str(library), "-lm"], check=True)
    step = ca.external("cov_step", str(library))
    covariance = ca.external("cov_covariance", str(library))
    assert step.n_out() == 4
    rng = np.random.default_rng(5)
    for scale in (0.5, 3.0, 40.0, 0.5, 3.0):
        args = [scale * rng.normal(size=obs.step.size_in(k)) for k in range(5)]
        pairs = list(zip(step(*args), obs.step_covariance(*args)))
        xhat = scale * rng.normal(size=obs.nx)
        pairs.append((covariance(args[0], args[1], xhat), obs.covariance(args[0], args[1], xhat)))
        for c_out, vm_out in pairs:
            c_out, vm_out = np.array(c_out), np.array(vm_out)
            if tol == 0:
                assert np.array_equal(c_out, vm_out), np.max(np.abs(c_out - vm_out))
            else:
                np.testing.assert_allclose(c_out, vm_out, rtol=tol, atol=tol * np.max(np.abs(vm_out)))


@needs_gcc
def test_the_main_example_still_reproduces_simulate(headed, tmp_path):
    from conftest import c_program_estimates

    obs, _, _ = headed
    t, y, u = runs(obs, m=1)
    np.testing.assert_array_equal(c_program_estimates(obs, tmp_path, "cov", t, y[0], u[0]),
                                  obs.simulate(t, y[0], u[0]).xhat)
