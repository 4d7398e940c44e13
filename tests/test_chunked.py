"""evaluation.chunked: an observer and the EKF over a record of any length through the compiled step, a chunk at a
time: bitwise KKLObserver.simulate and EKF.simulate with the C library's exp/tanh (across chunk boundaries and the
padded last chunk, the domain monitor's flags too), within the vector-math tolerance with the default kernels, the
same values in the CasADi VM (no compiler); the sizes compiled; bad arguments."""

import shutil

import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.evaluation.chunked import BITWISE, CHUNK, FAST, ChunkedEKF, ChunkedObserver
from kklcasadi.model import variants
from kklcasadi.model.files import load_model, save_model
from kklcasadi.observer.kkl import load_observer

needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc is not installed")
METHODS = variants.names()


def record(n, seed=0, zero_until=0):
    """A measured output and a square-wave input (0 for the first ``zero_until`` samples: the injection skipped)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.05
    y = np.sin(1.3 * t)[:, None] + 0.1 * rng.normal(size=(n, 1))
    u = 0.8 * np.sign(np.sin(2.0 * t + 0.4))[:, None]
    u[:zero_until] = 0.0
    return t, y, u


def with_domain(path, t, y, u):
    """The model at ``path`` with a training domain that its estimates on ``(t, y, u)`` leave now and then: the
    middle 60 % of each estimated state and latent (the flags change along the record)."""
    est = load_observer(path).simulate(t, y, u)
    model = load_model(path)
    (x_lo, x_hi), (z_lo, z_hi) = (np.quantile(a, [0.2, 0.8], axis=0).tolist() for a in (est.xhat, est.z))
    card = {**model.card, "domain": {"x_lo": x_lo, "x_hi": x_hi, "z_lo": z_lo, "z_hi": z_hi}}
    save_model(path, model.arrays, card, overwrite=True)
    return load_observer(path)


@needs_gcc
@pytest.mark.parametrize("method", METHODS)
def test_chunks_are_bitwise_simulate(model_dir_factory, method):
    """37 chunks of 16 steps and a padded last one (n = 600): estimates, latent states and flags as simulate's."""
    t, y, u = record(600, zero_until=45)
    obs = with_domain(model_dir_factory(method, window=4), t, y, u)
    expected = obs.simulate(t, y, u)
    xhat, z, flags = ChunkedObserver(obs, compiler=BITWISE, chunk=16).estimate(y, u)
    np.testing.assert_array_equal(xhat, expected.xhat)
    np.testing.assert_array_equal(z, expected.z)
    np.testing.assert_array_equal(flags, expected.in_domain)
    assert 0 < flags.mean() < 1
    fast, _, _ = ChunkedObserver(obs, compiler=FAST, chunk=16).estimate(y, u)
    np.testing.assert_allclose(fast, expected.xhat, rtol=0, atol=1e-12)


@needs_gcc
def test_the_monitored_bank_flags_as_simulate(monitored_bank):
    """The decoder-input monitor and the ensemble's spread compiled with the step: simulate's flags."""
    path, _ = monitored_bank
    obs = load_observer(path)
    t, y, u = record(300, seed=1)
    expected = obs.simulate(t, y, u)
    xhat, z, flags = ChunkedObserver(obs, compiler=BITWISE, chunk=64).estimate(y, u)
    np.testing.assert_array_equal(xhat, expected.xhat)
    np.testing.assert_array_equal(flags, expected.in_domain)


@needs_gcc
def test_the_shipped_bank_runs_its_members_once_for_the_estimate_and_the_spread():
    """duffing/bank's monitor tests the ensemble's spread: the chunk decodes once for the estimate and the spread
    (KKLObserver.decoded), with simulate's estimates, latent states and flags bit for bit."""
    obs = load_observer("duffing/bank")
    assert obs.monitor.spec.spread is not None and obs.decoded is not None
    chunked = ChunkedObserver(obs, compiler=BITWISE, chunk=64)
    assert chunked._monitored_step() is not None
    t, y, u = record(300, seed=2)
    expected = obs.simulate(t, y, u, vm=True)
    for got, want in zip(chunked.estimate(y, u), (expected.xhat, expected.z, expected.in_domain)):
        np.testing.assert_array_equal(got, want)
    z, w = expected.z[-1], obs.memory_init(y[-1], u[-1])
    xhat, spread = obs.decoded(z, w)
    assert float(spread) == float(obs.spread(z, w))
    np.testing.assert_array_equal(np.asarray(xhat), np.asarray(obs.decode(z, w)))


def test_the_vm_runs_the_same_chunks(model_dir_factory):
    obs = load_observer(model_dir_factory("inject", window=4))
    t, y, u = record(150, zero_until=20)
    xhat, z, flags = ChunkedObserver(obs, compiler=None, chunk=32).estimate(y, u)
    expected = obs.simulate(t, y, u)
    np.testing.assert_array_equal(xhat, expected.xhat)
    np.testing.assert_array_equal(z, expected.z)
    assert flags is None and expected.in_domain is None


@needs_gcc
@pytest.mark.parametrize("n", [2, 65, 200])
def test_the_ekf_in_chunks_is_bitwise_simulate(n):
    plant = kc.systems.get("vdp")
    ekf = kc.EKF.for_noise(plant, 0.05, process_std=0.1, measurement_std=0.1)
    t, y, u = record(n, seed=2)
    (xhat,) = ChunkedEKF(ekf, compiler=BITWISE, chunk=64).run(y, u)
    np.testing.assert_array_equal(xhat, ekf.simulate(t, y, u).xhat)


def test_sizes_and_arguments(model_dir_factory):
    obs = load_observer(model_dir_factory("autonomous"))
    chunked = ChunkedObserver(obs, compiler=None)
    assert [chunked.size(n) for n in (1, 2, 65, 66, 1000, 10**6)] == [64, 64, 64, 128, 1024, CHUNK]
    assert ChunkedObserver(obs, compiler=None, chunk=100).size(10**6) == 100
    xhat, z, _ = chunked.estimate(np.array([[0.3]]), np.array([[0.0]]))     # one sample: the start alone
    np.testing.assert_array_equal(xhat, obs.simulate([0.0], [[0.3]], [[0.0]]).xhat)
    with pytest.raises(ValueError, match=r"^chunk: expected a positive int"):
        ChunkedObserver(obs, chunk=0)
    with pytest.raises(TypeError, match=r"^compiler: expected a kklcasadi.evaluation.compiled.Compiler or None"):
        ChunkedObserver(obs, compiler="gcc")
    with pytest.raises(ValueError, match=r"^y: expected shape \(N, 1\) with N >= 1, received \(5, 2\)"):
        chunked.run(np.zeros((5, 2)), np.zeros((5, 1)))
    with pytest.raises(ValueError, match=r"^u: expected shape \(5, 1\), received \(4, 1\)"):
        chunked.run(np.zeros((5, 1)), np.zeros((4, 1)))
