"""kklcasadi.observer.guard: guarded_simulate is simulate's run bitwise on clean data (across its chunks, the
memory carried), holds a non-finite or absurd sample (the previous sample fed in its place, the middle of the box
before any), and restarts where a step leaves the latent's box, as simulate started again there computes it."""

import numpy as np
import pytest

from kklcasadi.model import variants
from kklcasadi.observer import guard as guard_module
from kklcasadi.observer.guard import HELD, RESTARTED, SampleGuard, guarded_simulate, training_box
from kklcasadi.observer.kkl import load_observer
from kklcasadi.plant.envelope import output_ranges
from kklcasadi.plant.systems import get

DT = 0.05


def run_data(n=120, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    return t, (np.sin(1.1 * t) + 0.05 * rng.normal(size=n))[:, None], np.cos(0.7 * t)[:, None]


def domain(obs):
    return {"domain": {"x_lo": [-1.5] * obs.nx, "x_hi": [1.5] * obs.nx, "z_lo": [-3.0] * obs.nz,
                       "z_hi": [3.0] * obs.nz}}


@pytest.mark.parametrize("method", variants.names())
def test_a_clean_run_is_simulate_bitwise_across_chunks(model_dir_factory, monkeypatch, method):
    obs = load_observer(model_dir_factory(method, base=method == "curriculum", window=3))
    t, y, u = run_data()
    expected = obs.simulate(t, y, u)
    for chunk in (4096, 7, 1):                                # the memory (window, context) carried between chunks
        monkeypatch.setattr(guard_module, "_CHUNK", chunk)
        est, status = guarded_simulate(obs, t, y, u)
        np.testing.assert_array_equal(est.xhat, expected.xhat)
        np.testing.assert_array_equal(est.z, expected.z)
        assert not status.any() and not est.xhat.flags.writeable
    if expected.in_domain is not None:
        np.testing.assert_array_equal(est.in_domain, expected.in_domain)


def test_held_samples_and_the_first_one(model_dir_factory):
    obs = load_observer(model_dir_factory("obs", window=3))
    t, y, u = run_data(60, seed=1)
    bad_y, bad_u = y.copy(), u.copy()
    bad_y[0, 0], bad_y[1, 0] = np.nan, 1e9          # before any sample is fed: the middle of the box (0), u = 0
    bad_u[30, 0], bad_y[31, 0] = np.inf, -1e9       # later: the sample fed before
    est, status = guarded_simulate(obs, t, bad_y, bad_u)
    assert np.flatnonzero(status).tolist() == [0, 1, 30, 31] and set(status[[0, 1, 30, 31]]) == {HELD}
    fed_y, fed_u = y.copy(), u.copy()
    fed_y[0:2], fed_u[0:2] = 0.0, 0.0
    fed_y[30:32], fed_u[30:32] = y[29], u[29]
    np.testing.assert_array_equal(est.xhat, obs.simulate(t, fed_y, fed_u).xhat)


def test_a_step_out_of_the_latent_box_restarts_there(model_dir_factory):
    """An input of 1e6 (inputs have no guard box) throws the latent out: the run restarts at the next sample, as
    simulate started there computes it."""
    probe = load_observer(model_dir_factory("inject", window=3))
    obs = load_observer(model_dir_factory("inject", window=3, card_extra=domain(probe)))
    t, y, u = run_data(80, seed=2)
    spiked = u.copy()
    spiked[40, 0] = 1e6
    est, status = guarded_simulate(obs, t, y, spiked)
    assert np.flatnonzero(status).tolist() == [41] and status[41] == RESTARTED
    before = obs.simulate(t[:41], y[:41], spiked[:41])
    after = obs.simulate(t[41:], y[41:], spiked[41:])
    np.testing.assert_array_equal(est.xhat[:41], before.xhat)
    np.testing.assert_array_equal(est.xhat[41:], after.xhat)
    np.testing.assert_array_equal(est.z[41], np.zeros(obs.nz))


def test_the_guard_boxes_come_from_the_training_domain(model_dir_factory):
    plant = get("duffing")
    probe = load_observer(model_dir_factory("autonomous"))
    obs = load_observer(model_dir_factory("autonomous", card_extra=domain(probe)))
    np.testing.assert_array_equal(training_box(obs), [[-1.5, 1.5], [-1.5, 1.5]])
    np.testing.assert_array_equal(training_box(probe), plant.x0_box)
    np.testing.assert_allclose(output_ranges(plant, [[-1.5, 1.5], [-4.0, 4.0]]), [[-1.5, 1.5]])   # y = x1
    guard = SampleGuard.of(obs, widths=2.0)
    np.testing.assert_allclose([guard.y_lo, guard.y_hi], [[-7.5], [7.5]])
    np.testing.assert_allclose([guard.z_lo, guard.z_hi], [[-15.0] * 5, [15.0] * 5])
    np.testing.assert_array_equal(guard.u_lo, [-np.inf])
    np.testing.assert_array_equal(guard.accepts(np.array([[7.5], [7.6], [np.nan], [0.0]]),
                                                np.array([[1e300], [0.0], [0.0], [-np.inf]])),
                                  [True, False, False, False])
    with pytest.raises(ValueError, match=r"^widths: expected a finite number >= 0"):
        SampleGuard.of(obs, widths=-1.0)
    with pytest.raises(ValueError, match=r"^y: expected shape \(N, 1\) with N = 3"):
        guarded_simulate(obs, np.arange(3) * DT, np.zeros((2, 1)), np.zeros((3, 1)))
    with pytest.raises(ValueError, match=r"^t: expected samples spaced by the observer's dt"):
        guarded_simulate(obs, np.arange(3) * 0.1, np.zeros((3, 1)), np.zeros((3, 1)))


def test_a_plant_that_declares_its_inputs_guards_them(model_dir_factory):
    """With ``u_box`` [-2, 3] the inputs' guard is [-52, 53]: an input of 60 is held, not fed (without it, fed)."""
    import casadi as ca

    import kklcasadi as kc

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    plant = kc.System("boxed", x, u, [x[1], -x[0] - 0.4 * x[1] + u], x[0], [[-1, 1], [-1, 1]], u_box=[[-2.0, 3.0]])
    obs = load_observer(model_dir_factory("inject", system=plant, window=3), system=plant)
    guard = SampleGuard.of(obs)
    np.testing.assert_allclose([guard.u_lo, guard.u_hi], [[-52.0], [53.0]])
    t, y, u = run_data(40, seed=3)
    spiked = u.copy()
    spiked[20, 0] = 60.0
    est, status = guarded_simulate(obs, t, y, spiked)
    assert np.flatnonzero(status).tolist() == [20] and status[20] == HELD
    held_y, held_u = y.copy(), u.copy()
    held_y[20], held_u[20] = y[19], u[19]                  # the whole sample: the last one fed
    np.testing.assert_array_equal(est.xhat, obs.simulate(t, held_y, held_u).xhat)
