"""Plants with uncertain parameters: kc.System(..., params=, param_box=, param_nominal=), the registry's
parameterised forms, simulation with parameter values (issue 46.1)."""

import json
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.plant import signals as sig

ROOT = Path(__file__).resolve().parents[1]


def hand_written(name, values=None):
    """Today's plant, written out (values: the coefficients; None: the unit ones, as the registry had them)."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    if name == "duffing":
        if values is None:
            xdot = [x[1], -x[0] - x[0] ** 3 + u]
        else:
            alpha, beta = values
            xdot = [x[1], -alpha * x[0] - beta * x[0] ** 3 + u]
        return kc.System("duffing", x, u, xdot, x[0], [[-1, 1], [-1, 1]])
    if values is None:
        xdot = [x[1], (1 - x[0] ** 2) * x[1] - x[0] + u]
    else:
        a, b, k = values
        xdot = [x[1], (a - b * x[0] ** 2) * x[1] - k * x[0] + u]
    return kc.System("vdp", x, u, xdot, x[0], [[-3, 3], [-3, 3]])


def parametric_pendulum(box=((0.5, 1.5), (0.0, 0.4)), nominal=None):
    x, u, p = ca.SX.sym("x", 2), ca.SX.sym("u"), ca.vertcat(ca.SX.sym("g"), ca.SX.sym("c"))
    return kc.System("pend", x, u, [x[1], -p[0] * ca.sin(x[0]) - p[1] * x[1] + u], p[0] * x[0],
                     [[-1, 1], [-2, 2]], params=p, param_box=box, param_nominal=nominal)


@pytest.mark.parametrize("name", ["duffing", "vdp"])
def test_registry_nominal_is_bitwise_todays_plant(name):
    rng = np.random.default_rng(3)
    x, u = rng.uniform(-3, 3, (20000, 2)), rng.uniform(-2, 2, (20000, 1))
    old = hand_written(name)
    family = kc.systems.get(name, param_spread=0.3)
    for plant in (kc.systems.get(name), family, family.at(family.param_nominal)):
        np.testing.assert_array_equal(plant.f_batch(x, u), old.f_batch(x, u))
        np.testing.assert_array_equal(plant.h_batch(x), old.h_batch(x))
        for a, b in zip(plant.f_jac(x[0], u[0]), old.f_jac(x[0], u[0])):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    plain = kc.systems.get(name)
    assert plain.n_params == 0 and plain.param_box is None
    assert plain.fingerprint == old.fingerprint
    # so the shipped models (cards written before parameters existed) still load
    for card in sorted((ROOT / "models" / name).glob("*/card.json")):
        assert json.loads(card.read_text())["system"]["fingerprint"] == plain.fingerprint, card


@pytest.mark.parametrize("name, names", [("duffing", ("alpha", "beta")), ("vdp", ("a", "b", "k"))])
def test_family_box_and_values(name, names):
    family = kc.systems.get(name, param_spread=0.3)
    assert family.param_names == names
    np.testing.assert_allclose(family.param_box, [[0.7, 1.3]] * len(names), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(family.param_nominal, np.ones(len(names)))
    rng = np.random.default_rng(4)
    p = family.sample_params(5, seed=1)
    assert p.shape == (5, len(names)) and np.all((p >= 0.7) & (p <= 1.3))
    x, u = rng.uniform(-2, 2, (5, 2)), rng.uniform(-1, 1, (5, 1))
    for i in range(5):
        np.testing.assert_allclose(family.f_batch(x[i:i + 1], u[i:i + 1], params=p[i]),
                                   hand_written(name, p[i]).f_batch(x[i:i + 1], u[i:i + 1]), rtol=1e-15, atol=1e-15)
        np.testing.assert_allclose(family.at(p[i]).f_batch(x, u), hand_written(name, p[i]).f_batch(x, u),
                                   rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(family.f_batch(x, u, params=p),
                               np.vstack([hand_written(name, p[i]).f_batch(x[i:i + 1], u[i:i + 1]) for i in range(5)]),
                               rtol=1e-15, atol=1e-15)


def test_fingerprint_covers_the_parameters():
    base = parametric_pendulum()
    assert base.fingerprint == parametric_pendulum().fingerprint
    np.testing.assert_array_equal(base.param_nominal, [1.0, 0.2])         # the box centre by default
    assert parametric_pendulum(box=((0.5, 1.6), (0.0, 0.4))).fingerprint != base.fingerprint
    assert parametric_pendulum(nominal=(1.1, 0.2)).fingerprint != base.fingerprint
    assert base.at(base.param_nominal).fingerprint != base.fingerprint    # the family is not its nominal member
    assert kc.systems.get("duffing", param_spread=0.3).fingerprint != kc.systems.get("duffing",
                                                                                     param_spread=0.2).fingerprint
    assert base.definition_digest != parametric_pendulum(box=((0.5, 1.6), (0.0, 0.4))).definition_digest
    # h may use the parameters: y = g x1
    np.testing.assert_allclose(base.h_batch([[0.5, 0.0]], params=[1.4, 0.0]), [[0.7]], rtol=1e-15)
    np.testing.assert_allclose(base.h_batch([[0.5, 0.0]]), [[0.5]], rtol=1e-15)


@pytest.mark.parametrize("method", ["cvodes", "rk"])
def test_simulation_with_parameters_matches_a_hand_built_plant(method):
    family = kc.systems.get("vdp", param_spread=0.3)
    values = np.array([[1.3, 0.7, 0.85], [0.7, 1.2, 1.3], [1.0, 1.0, 1.0]])
    x0 = np.array([[1.0, -0.5], [-2.0, 1.0], [0.3, 0.3]])
    inputs = [sig.make("sinusoid", amplitude=0.8, omega=1.3, phase=0.1), sig.make("square", amplitude=0.5,
                                                                                  omega=0.9, phase=0.0),
              sig.make("zero")]
    kw = dict(T=10.0, dt=0.05, process_std=0.1, measurement_std=0.1, seed=[5, 6, 7], method=method)
    batch = kc.simulate_batch(family, x0, inputs, params=values, **kw)
    assert batch.ok.all()
    for i in range(3):
        ref = kc.simulate(hand_written("vdp", values[i]), x0[i], inputs[i], T=10.0, dt=0.05, process_std=0.1,
                          measurement_std=0.1, seed=kw["seed"][i], method=method)
        np.testing.assert_allclose(batch.x[i], ref.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(batch.y[i], ref.y, rtol=1e-9, atol=1e-9)
        one = kc.simulate(family, x0[i], inputs[i], T=10.0, dt=0.05, process_std=0.1, measurement_std=0.1,
                          seed=kw["seed"][i], method=method, params=values[i])
        np.testing.assert_array_equal(one.x, batch.x[i])
    # no values: the nominal plant, bitwise today's
    nominal = kc.simulate_batch(family, x0, inputs, **kw)
    np.testing.assert_array_equal(nominal.x, kc.simulate_batch(hand_written("vdp"), x0, inputs, **kw).x)
    # the last trial's values are the nominal ones
    np.testing.assert_allclose(batch.x[2], nominal.x[2], rtol=1e-10, atol=1e-10)


def test_closed_loop_with_parameters_and_parameters_in_h():
    plant = parametric_pendulum()
    law = sig.PDFeedback(sig.make("constant", value=0.3), kp=1.0, kd=0.5, tau=0.2, u_max=1.0)
    values = np.array([1.4, 0.05])
    a = kc.simulate(plant, [0.2, 0.0], law, T=5.0, dt=0.05, measurement_std=0.05, seed=3, method="rk",
                    params=values)
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    fixed = kc.System("pend", x, u, [x[1], -1.4 * ca.sin(x[0]) - 0.05 * x[1] + u], 1.4 * x[0],
                      [[-1, 1], [-2, 2]])
    b = kc.simulate(fixed, [0.2, 0.0], law, T=5.0, dt=0.05, measurement_std=0.05, seed=3, method="rk")
    np.testing.assert_allclose(a.x, b.x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.u, b.u, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.y, b.y, rtol=1e-12, atol=1e-12)


def test_bad_parameters_are_named():
    x, u, p = ca.SX.sym("x", 2), ca.SX.sym("u"), ca.SX.sym("p")
    with pytest.raises(ValueError, match=r"param_box: expected shape \(n_params, 2\) = \(1, 2\)"):
        kc.System("p", x, u, [x[1], -p * x[0]], x[0], [[-1, 1], [-1, 1]], params=p, param_box=[1, 2])
    with pytest.raises(ValueError, match=r"param_nominal: expected values inside param_box"):
        kc.System("p", x, u, [x[1], -p * x[0]], x[0], [[-1, 1], [-1, 1]], params=p, param_box=[[1, 2]],
                  param_nominal=[3.0])
    with pytest.raises(ValueError, match=r"xdot, y: expected expressions in the symbols of x and u only"):
        kc.System("p", x, u, [x[1], -p * x[0]], x[0], [[-1, 1], [-1, 1]])
    with pytest.raises(ValueError, match=r"params: expected a casadi.SX symbol of the parameters"):
        kc.System("p", x, u, [x[1], -x[0]], x[0], [[-1, 1], [-1, 1]], param_box=[[1, 2]])
    duffing = kc.systems.get("duffing")
    with pytest.raises(ValueError, match=r"params: expected None for plant 'duffing', which declares no parameters"):
        kc.simulate(duffing, [0.1, 0.0], sig.make("zero"), T=1.0, params=[1.0, 1.0])
    family = kc.systems.get("duffing", param_spread=0.3)
    with pytest.raises(ValueError, match=r"params: expected shape \(2,\) or \(3, 2\)"):
        kc.simulate_batch(family, np.zeros((3, 2)), sig.make("zero"), T=1.0, params=np.ones((2, 2)))
    with pytest.raises(ValueError, match=r"param_spread: expected None for 'rossler', which has no parameterised"):
        kc.systems.get("rossler", param_spread=0.3)
    with pytest.raises(ValueError, match=r"param_spread: expected a relative uncertainty 0 < s < 1"):
        kc.systems.get("vdp", param_spread=1.5)
    assert kc.systems.families() == ["duffing", "vdp"]


def test_estimators_use_the_nominal_values_unless_told_otherwise():
    family = kc.systems.get("duffing", param_spread=0.3)
    run = kc.simulate(family, [0.5, -0.2], sig.make("sinusoid", amplitude=0.5, omega=1.0, phase=0.0), T=5.0,
                      dt=0.05, process_std=0.1, measurement_std=0.1, seed=1, method="rk", params=[1.2, 0.8])
    plain = kc.EKF(kc.systems.get("duffing"), 0.05).simulate(run.t, run.y, run.u).xhat
    np.testing.assert_array_equal(kc.EKF(family, 0.05).simulate(run.t, run.y, run.u).xhat, plain)
    told = kc.EKF(family, 0.05, params=[1.2, 0.8]).simulate(run.t, run.y, run.u).xhat
    hand = kc.EKF(hand_written("duffing", [1.2, 0.8]), 0.05).simulate(run.t, run.y, run.u).xhat
    np.testing.assert_allclose(told, hand, rtol=1e-13, atol=1e-13)
    assert np.abs(told - plain).max() > 1e-3
    from kklcasadi.estimators import ParticleFilter
    pf = ParticleFilter(family, 0.05, n_particles=50, params=[1.2, 0.8], jit=False)
    ref = ParticleFilter(hand_written("duffing", [1.2, 0.8]), 0.05, n_particles=50, jit=False)
    np.testing.assert_allclose(pf.simulate(run.t, run.y, run.u).xhat, ref.simulate(run.t, run.y, run.u).xhat,
                               rtol=1e-12, atol=1e-12)
    mhe = kc.MHE(family, 0.05, 5, params=[1.2, 0.8])
    np.testing.assert_allclose(np.asarray(mhe.phi([0.3, 0.1], 0.2, [0.0, 0.0])),
                               np.asarray(kc.MHE(hand_written("duffing", [1.2, 0.8]), 0.05, 5).phi([0.3, 0.1], 0.2,
                                                                                                   [0.0, 0.0])),
                               rtol=1e-15, atol=1e-15)


def test_a_model_loads_against_its_family():
    """A family is taken at its nominal values: the shipped models load against it."""
    from kklcasadi.observer.kkl import load_observer

    obs = load_observer(ROOT / "models" / "duffing" / "bank", system=kc.systems.get("duffing", param_spread=0.3))
    assert obs.system.n_params == 0 and obs.system.fingerprint == kc.systems.get("duffing").fingerprint
    with pytest.raises(ValueError, match=r"'system.fingerprint': the model was trained for a plant 'duffing'"):
        load_observer(ROOT / "models" / "duffing" / "bank",
                      system=hand_written("duffing", [1.1, 1.0]))
