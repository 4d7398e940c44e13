"""KKLObserver: loading every method, the sample-interval step (exact FOH discretisation, RK4),
bitwise collapse to the autonomous observer at u = 0, simulate (mapaccum / map), the
ca.integrator form, the stateful estimator, the inject model on a plant with a known KKL map,
argument errors, and the closed-loop example (torch-free)."""

import json
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from conftest import write_signed_card
from scipy.linalg import expm, solve_sylvester

import kklcasadi as kc
from kklcasadi import provenance
from kklcasadi.model import variants
from kklcasadi.model.files import CARD_FILE, load_model, save_model
from kklcasadi.nets import builders as casadi_nets
from kklcasadi.observer.kkl import KKLObserver, load_observer, make_inject_model
from kklcasadi.plant.rk4 import rk4_step
from kklcasadi.plant.simulate import time_grid
from kklcasadi.plant.systems import LINEAR_F, LINEAR_H

ROOT = Path(__file__).resolve().parents[1]
METHODS = variants.names()
DT = 0.05


def square_input(t, amplitude=0.7, omega=2.0):
    return amplitude * np.sign(np.sin(omega * t + 0.3))[:, None]


def plant_run(system="duffing", T=4.0, u=None, x0=(0.5, -0.2)):
    plant = kc.systems.get(system)
    t = time_grid(T, DT)
    u = square_input(t) if u is None else u
    return kc.simulate(plant, x0, u, T=T, dt=DT)


def random_step_args(obs, rng):
    return (rng.normal(size=obs.nz), rng.normal(size=obs.memory_shape),
            rng.normal(size=obs.ny), rng.normal(size=obs.ny), rng.normal(size=obs.nu))


# ----------------------------------------------------------------------------- loading

@pytest.mark.parametrize("method", METHODS)
def test_every_method_loads_with_named_functions(model_dir_factory, method):
    obs = kc.load_observer(model_dir_factory(method, base=method != "autonomous"))
    assert isinstance(obs, kc.KKLObserver) and obs.method == method
    window = 3 if obs.variant.windowed else 1                       # a method that reads no window has 1
    assert (obs.nx, obs.nu, obs.ny, obs.nz, obs.window, obs.dt) == (2, 1, 1, 5, window, DT)
    assert obs.discretization == ("exact" if obs.variant.linear else "rk4")
    assert (obs.rhs.name_in(), obs.rhs.name_out()) == (["z", "y", "u", "w"], ["zdot"])
    assert (obs.decode.name_in(), obs.decode.name_out()) == (["z", "w"], ["xhat"])
    assert obs.step.name_in() == ["z", "w", "y", "y_next", "u_next"]
    assert obs.step.name_out() == ["z_next", "w_next", "xhat_next"]
    memory = {"obs_stream": (4 + 1, 1), "dyn_stream": (4 + 1, 1), "bank": (1 + 1, 1)}.get(method, (window, 1))
    assert obs.memory_shape == memory and obs.step.size_in(1) == memory and obs.step.size_out(1) == memory
    assert obs.step.is_a("MXFunction")


def test_system_from_another_plant_is_refused(model_dir_factory):
    path = model_dir_factory("autonomous")
    with pytest.raises(ValueError, match=r"card\.json: 'system\.name'.*'duffing'.*'vdp'"):
        load_observer(path, system=kc.systems.get("vdp"))
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u")
    fake = kc.System("duffing", x, u, [x[1], x[2], -x[0] + u], x[0], [[-1, 1]] * 3)
    with pytest.raises(ValueError, match=r"'system\.nx': the model expects nx = 2.*nx = 3"):
        load_observer(path, system=fake)
    with pytest.raises(TypeError, match="system"):
        KKLObserver(load_model(path), "duffing")
    with pytest.raises(TypeError, match="model"):
        KKLObserver(str(path), kc.systems.get("duffing"))


def test_unregistered_system_needs_the_plant(model_dir_factory):
    path = model_dir_factory("autonomous")
    card = json.loads((path / CARD_FILE).read_text())
    card["system"]["name"] = "pend"
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    pend = kc.System("pend", x, u, [x[1], -ca.sin(x[0]) + u], x[0], [[-1, 1], [-2, 2]])
    card["system"]["fingerprint"] = pend.fingerprint
    write_signed_card(path, card)
    with pytest.raises(ValueError, match=r"'pend' is not a registered system.*system="):
        load_observer(path)
    assert load_observer(path, system=pend).system is pend


def test_a_plant_with_other_dynamics_is_refused_whatever_its_name(model_dir_factory):
    path = model_dir_factory("autonomous")
    x, u = ca.SX.sym("s", 2), ca.SX.sym("v")
    same = kc.System("duffing", x, u, [x[1], -(x[0] ** 3 + x[0]) + u], x[0], [[-1, 1], [-1, 1]])
    assert load_observer(path, system=same).system is same             # other symbols, same plant
    other = kc.System("duffing", x, u, [x[1], -x[0] - 2 * x[0] ** 3 + u], x[0], [[-1, 1], [-1, 1]])
    with pytest.raises(ValueError, match=r"'system\.fingerprint': .* plant 'duffing' with other"):
        load_observer(path, system=other)
    wider = kc.System("duffing", x, u, [x[1], -x[0] - x[0] ** 3 + u], x[0], [[-2, 2], [-1, 1]])
    with pytest.raises(ValueError, match="fingerprint"):
        load_observer(path, system=wider)
    card = json.loads((path / CARD_FILE).read_text())               # cards without one still load
    del card["system"]["fingerprint"]
    write_signed_card(path, card)
    assert load_observer(path, system=other).system is other


def test_unknown_method_and_bad_options(model_dir_factory):
    path = model_dir_factory("autonomous")
    model = load_model(path)
    duffing = kc.systems.get("duffing")
    card = json.loads((path / CARD_FILE).read_text())
    write_signed_card(path, {**card, "method": "stream"})
    with pytest.raises(ValueError, match=r"'method': expected one of .*'stream'"):
        load_observer(path)
    with pytest.raises(ValueError, match="discretization: expected one of"):
        KKLObserver(model, duffing, discretization="euler")
    with pytest.raises(ValueError, match="substeps"):
        KKLObserver(model, duffing, substeps=0)
    with pytest.raises(TypeError, match="substeps"):
        KKLObserver(model, duffing, substeps=1.5)
    obs_model = load_model(model_dir_factory("obs"))
    with pytest.raises(ValueError, match="'exact' needs linear latent dynamics.*'obs'"):
        KKLObserver(obs_model, duffing, discretization="exact")


def test_model_based_injection_field_is_checked(model_dir_factory):
    with pytest.raises(ValueError, match="model_based_injection': expected true or false"):
        load_observer(model_dir_factory("obs", card_extra={"model_based_injection": "yes"}))
    with pytest.raises(ValueError, match="model_based_injection': expected no such field for method 'dyn'"):
        load_observer(model_dir_factory("dyn", card_extra={"model_based_injection": True}))
    obs = load_observer(model_dir_factory("obs", card_extra={"model_based_injection": True}))
    assert obs.model_based_injection and obs.model_injection is not None
    assert load_observer(model_dir_factory("obs")).model_injection is None


# ----------------------------------------------------------------------------- the latent field

def test_obs_rhs_is_the_exported_injection(model_dir_factory, rng):
    path = model_dir_factory("obs", window=4)
    obs, model = load_observer(path), load_model(path)
    inj = casadi_nets.obs_injection_function(model.spec.architecture.obs, model.arrays, 4)
    for _ in range(3):
        z, w, y, _, u = random_step_args(obs, rng)
        expected = obs.A @ z + obs.B @ y + np.array(inj(z, w, u)).ravel()
        np.testing.assert_allclose(np.array(obs.rhs(z, y, u, w)).ravel(), expected,
                                   rtol=0, atol=1e-13)


def test_inject_term_is_the_encoder_jacobian_times_the_input_effect(model_dir_factory, rng):
    obs = load_observer(model_dir_factory("inject"))
    for _ in range(3):
        z, w, y, _, u = random_step_args(obs, rng)
        xhat = np.array(obs.decode(z, w)).ravel()
        eps = 1e-6      # Duffing: f(x, u) - f(x, 0) = [0, u]; central differences of T along x2
        dT_dx2 = (np.array(obs.encoder(xhat + [0, eps])) - np.array(obs.encoder(xhat - [0, eps])))
        expected = obs.A @ z + obs.B @ y + dT_dx2.ravel() / (2 * eps) * u[0]
        np.testing.assert_allclose(np.array(obs.rhs(z, y, u, w)).ravel(), expected,
                                   rtol=0, atol=1e-7)


def test_dyn_decoder_is_the_exported_lora_decoder(model_dir_factory, rng):
    path = model_dir_factory("dyn", window=4)
    obs, model = load_observer(path), load_model(path)
    arch = model.spec.architecture
    lora = casadi_nets.lora_mlp_function(arch.encoder, arch.decoder, arch.hyper, model.arrays, 1, 4)
    plain = casadi_nets.mlp_function(arch.decoder, model.arrays, "decoder")
    z, w = rng.normal(size=5), rng.normal(size=(4, 1))
    assert np.array_equal(np.array(obs.decode(z, w)), np.array(lora(z, w)))
    assert np.abs(np.array(obs.decode(z, w)) - np.array(plain(z))).max() > 1e-3


# ----------------------------------------------------------------------------- the step

@pytest.mark.parametrize("method", METHODS)
def test_step_updates_the_memory_and_decodes_the_new_state(model_dir_factory, rng, method):
    obs = load_observer(model_dir_factory(method, window=4))
    z, w, y, y_next, u_next = random_step_args(obs, rng)
    z_next, w_next, xhat_next = obs.step(z, w, y, y_next, u_next)
    assert np.array_equal(np.array(w_next), np.array(obs.memory.next(w, y_next, u_next)))
    if obs.memory_shape == (obs.window, 1) and method not in ("bank", "obs_stream", "dyn_stream"):  # it shifts
        assert np.array_equal(np.array(w_next), np.vstack([w[1:], u_next[None]]))
    elif method == "bank":                                             # [y_k+1; u_k+1]
        assert np.array_equal(np.array(w_next).ravel(), np.r_[y_next, u_next])
    else:                                                              # [h; u]: one GRU cell
        assert obs.memory_shape == (5, 1) and np.array_equal(np.array(w_next)[4:], u_next[None])
    assert np.array_equal(np.array(xhat_next), np.array(obs.decode(z_next, w_next)))


@pytest.mark.parametrize("method", ["obs", "inject"])
def test_rk4_step_holds_u_at_the_newest_window_entry_and_interpolates_y(model_dir_factory, rng,
                                                                         method):
    obs = load_observer(model_dir_factory(method, window=4), substeps=2)
    z, w, y, y_next, u_next = random_step_args(obs, rng)
    expected = rk4_step(lambda s, zz: obs.rhs(zz, y + s * (y_next - y), w[-1], w),
                        ca.DM(z), DT, 2)
    np.testing.assert_allclose(np.array(obs.step(z, w, y, y_next, u_next)[0]), np.array(expected),
                               rtol=0, atol=1e-14)


def test_exact_discretisation_matches_the_closed_form(model_dir_factory, rng):
    obs = load_observer(model_dir_factory("autonomous"))
    A, B = obs.A, obs.B
    Ad, inv = expm(A * DT), np.linalg.inv(A)
    # z(dt) = e^{A dt} z0 + int_0^dt e^{A(dt-s)} B (y0 + s/dt (y1 - y0)) ds
    g0 = inv @ (Ad - np.eye(5)) @ B
    g1 = (inv @ inv @ (Ad - np.eye(5)) - DT * inv) @ B / DT
    for _ in range(3):
        z, w, y, y_next, u_next = random_step_args(obs, rng)
        expected = Ad @ z + g0 @ y + g1 @ (y_next - y)
        np.testing.assert_allclose(np.array(obs.step(z, w, y, y_next, u_next)[0]).ravel(),
                                   expected, rtol=1e-12, atol=1e-13)


def test_rk4_converges_to_the_exact_step_at_fourth_order(model_dir_factory, rng):
    path = model_dir_factory("autonomous")
    exact = load_observer(path)
    args = random_step_args(exact, rng)
    reference = np.array(exact.step(*args)[0])
    errors = [np.abs(np.array(load_observer(path, discretization="rk4", substeps=n).step(*args)[0])
                     - reference).max() for n in (1, 2, 4)]
    assert errors[0] < 1e-4
    for coarse, fine in zip(errors, errors[1:]):
        assert 12 < coarse / fine < 20                      # 2^4 = 16 per halving of the step


# ----------------------------------------------------------------------------- exact collapse

@pytest.mark.parametrize("method,extra", [("obs", None), ("dyn", None), ("inject", None),
                                          ("obs", {"model_based_injection": True}),
                                          ("obs_stream", None), ("dyn_stream", None)])
def test_collapses_bitwise_to_the_autonomous_observer_at_zero_input(model_dir_factory, method,
                                                                    extra):
    tr = plant_run(u=np.zeros((80, 1)))
    discretization = "exact" if method.startswith("dyn") else "rk4"
    auto = load_observer(model_dir_factory("autonomous", window=5, seed=7),
                         discretization=discretization)
    other = load_observer(model_dir_factory(method, window=5, seed=7, card_extra=extra))
    assert other.discretization == discretization
    a, b = auto.simulate(tr.t, tr.y, tr.u), other.simulate(tr.t, tr.y, tr.u)
    assert np.array_equal(a.z, b.z) and np.array_equal(a.xhat, b.xhat)
    driven = square_input(tr.t)                    # the comparison is not vacuous
    assert not np.array_equal(auto.simulate(tr.t, tr.y, driven).xhat,
                              other.simulate(tr.t, tr.y, driven).xhat)


# ----------------------------------------------------------------------------- streaming

@pytest.mark.parametrize("method", ["obs_stream", "dyn_stream"])
def test_streaming_context_is_the_window_gru_over_the_whole_history(model_dir_factory, method):
    """After k + 1 samples the streamed context equals the window GRU run over u_0..u_k (no
    padding), so the streaming observer is the windowed one with an ever-growing window."""
    stream = load_observer(model_dir_factory(method, seed=3))
    tr = plant_run(T=0.6)
    n = tr.t.size
    windowed = load_observer(model_dir_factory(method.split("_")[0], window=n, seed=3))
    w = stream.memory_init(tr.y[0], tr.u[0])
    for k in range(1, n):
        w = stream.memory.next(w, tr.y[k], tr.u[k])
    h = np.array(w)[:-1]
    if method == "obs_stream":
        expected = windowed._context(tr.u)
        np.testing.assert_allclose(np.array(stream._context(w)), np.array(expected), rtol=0, atol=1e-14)
    z = np.linspace(-1, 1, 5)
    np.testing.assert_allclose(np.array(stream.decode(z, w)), np.array(windowed.decode(z, tr.u)),
                               rtol=0, atol=1e-14)
    assert np.abs(h).max() > 1e-3


# ----------------------------------------------------------------------------- simulate

@pytest.mark.parametrize("method", METHODS)
def test_simulate_is_the_step_repeated_from_zero(model_dir_factory, method):
    obs = load_observer(model_dir_factory(method, window=4))
    tr = plant_run(T=1.0)
    est = obs.simulate(tr.t, tr.y, tr.u)
    assert np.array_equal(est.t, tr.t) and est.xhat.shape == (20, 2) and est.z.shape == (20, 5)
    z, w = np.zeros(5), obs.memory_init(tr.y[0], tr.u[0])
    if obs.variant.windowed or method in ("autonomous", "curriculum", "inject"):
        assert np.array_equal(np.array(w), np.repeat(tr.u[:1], obs.window, axis=0))      # filled with u_0
    assert np.array_equal(est.z[0], z)
    assert np.array_equal(est.xhat[0], np.array(obs.decode(z, w)).ravel())
    for k in range(1, 20):
        z, w, xhat = obs.step(z, w, tr.y[k - 1], tr.y[k], tr.u[k])
        assert np.array_equal(est.z[k], np.array(z).ravel())
        assert np.array_equal(est.xhat[k], np.array(xhat).ravel())


@pytest.mark.parametrize("method", ["obs", "dyn", "inject"])
def test_two_inputs_and_outputs(model_dir_factory, mimo_plant, method):
    """Window layout (window, nu), the integrator's p = [y; y_next; u; vec(w)] (CVODES vs RK4
    with 16 substeps: 1e-8, measured ~2e-9), the estimator."""
    obs = load_observer(model_dir_factory(method, system=mimo_plant, window=3),
                        system=mimo_plant, substeps=16)
    assert (obs.nu, obs.ny, obs.nz) == (2, 2, 10)
    rng = np.random.default_rng(5)
    t, y, u = np.arange(15) * DT, rng.normal(size=(15, 2)), rng.normal(size=(15, 2))
    est = obs.simulate(t, y, u)
    z, w = np.zeros(10), np.repeat(u[:1], obs.window, axis=0)
    estimator = obs.estimator()
    assert np.array_equal(estimator.make_step(y[0], u[0]), est.xhat[0])
    for k in range(1, 15):
        z_next, w_next, xhat = obs.step(z, w, y[k - 1], y[k], u[k])
        assert np.array_equal(np.array(w_next), np.vstack([w[1:], u[k]]))
        p = np.concatenate([y[k - 1], y[k], w[-1], w.ravel(order="F")])
        zf = obs.integrator("cvodes", reltol=1e-10, abstol=1e-12)(x0=z, p=p)["xf"]
        np.testing.assert_allclose(np.array(zf), np.array(z_next), rtol=0, atol=1e-8)
        z, w = np.array(z_next).ravel(), np.array(w_next)
        assert np.array_equal(est.xhat[k], np.array(xhat).ravel())
        assert np.array_equal(estimator.make_step(y[k], u[k]), est.xhat[k])


def test_simulate_maps_trials_and_accepts_one_sample(model_dir_factory, rng):
    obs = load_observer(model_dir_factory("obs", window=4))
    t = np.arange(30) * DT
    y, u = rng.normal(size=(3, 30, 1)), rng.normal(size=(3, 30, 1))
    batch = obs.simulate(t, y, u)
    assert batch.xhat.shape == (3, 30, 2) and batch.z.shape == (3, 30, 5)
    for i in range(3):
        single = obs.simulate(t, y[i], u[i])
        assert np.array_equal(batch.xhat[i], single.xhat) and np.array_equal(batch.z[i], single.z)
    assert np.array_equal(obs.simulate(t, y, u, n_threads=1).xhat, batch.xhat)
    with pytest.raises(ValueError, match="n_threads: expected a positive int, received 0"):
        obs.simulate(t, y, u, n_threads=0)
    one = obs.simulate(t[:1], y[0, :1], u[0, :1])
    assert one.xhat.shape == (1, 2) and np.array_equal(one.xhat[0], batch.xhat[0, 0])
    flat = obs.simulate(t, y[0, :, 0], u[0, :, 0])               # (N,) allowed for ny = nu = 1
    assert np.array_equal(flat.xhat, batch.xhat[0])


def test_simulate_from_a_given_latent_state(model_dir_factory, rng):
    obs = load_observer(model_dir_factory("inject"))
    t, y, u = np.arange(12) * DT, rng.normal(size=(2, 12, 1)), rng.normal(size=(2, 12, 1))
    z0 = rng.normal(size=(2, 5))
    batch = obs.simulate(t, y, u, z0=z0)
    assert np.array_equal(batch.z[:, 0], z0)
    for i in range(2):
        single = obs.simulate(t, y[i], u[i], z0=z0[i])
        assert np.array_equal(single.xhat, batch.xhat[i])
        w0 = np.repeat(u[i, :1], obs.window, axis=0)
        assert np.array_equal(single.xhat[0], np.array(obs.decode(z0[i], w0)).ravel())
    shared = obs.simulate(t, y, u, z0=z0[1])
    assert np.array_equal(shared.xhat[1], batch.xhat[1])
    with pytest.raises(ValueError, match=r"z0: expected shape \(5,\) or \(M, 5\) = \(2, 5\), "
                                         r"received \(3, 5\)"):
        obs.simulate(t, y, u, z0=np.zeros((3, 5)))
    with pytest.raises(ValueError, match=r"z0: expected shape \(5,\), received \(1, 5\)"):
        obs.simulate(t, y[0], u[0], z0=np.zeros((1, 5)))
    with pytest.raises(ValueError, match="z0: expected finite values"):
        obs.simulate(t, y[0], u[0], z0=[0, 0, np.inf, 0, 0])


def test_simulate_rejects_bad_shapes_and_times(model_dir_factory):
    obs = load_observer(model_dir_factory("autonomous"))
    t, y, u = np.arange(10) * DT, np.zeros((10, 1)), np.zeros((10, 1))
    with pytest.raises(ValueError, match=r"y: expected shape \(N, 1\) or \(M, N, 1\) with N = 10"
                                         r".*received \(10, 2\)"):
        obs.simulate(t, np.zeros((10, 2)), u)
    with pytest.raises(ValueError, match=r"u: expected .*received \(9, 1\)"):
        obs.simulate(t, y, np.zeros((9, 1)))
    with pytest.raises(ValueError, match="y and u: expected the same number of trials"):
        obs.simulate(t, np.zeros((2, 10, 1)), np.zeros((3, 10, 1)))
    with pytest.raises(ValueError, match="y and u: expected the same number of trials"):
        obs.simulate(t, np.zeros((1, 10, 1)), u)
    with pytest.raises(ValueError, match=r"t: expected sample times of shape \(N,\)"):
        obs.simulate(t[:, None], y, u)
    with pytest.raises(ValueError, match=r"t: expected samples spaced by the observer's dt = 0.05"):
        obs.simulate(t * 2, y, u)


def test_simulate_names_the_trial_and_sample_of_a_nan_or_inf(model_dir_factory):
    obs = load_observer(model_dir_factory("inject"))
    t = np.arange(10) * DT
    y, u = np.zeros((3, 10, 1)), np.zeros((3, 10, 1))
    y[1, 7, 0] = np.nan
    with pytest.raises(ValueError, match=r"y: expected finite values.*trial 1, sample 7 \(t = 0.35"):
        obs.simulate(t, y, u)
    u[2, 4, 0] = np.inf
    with pytest.raises(ValueError, match=r"u: expected finite values.*trial 2, sample 4"):
        obs.simulate(t, np.zeros((3, 10, 1)), u)
    with pytest.raises(ValueError, match=r"u: .*at sample 4 \(t"):
        obs.simulate(t, np.zeros((10, 1)), u[2])


# ----------------------------------------------------------------------------- integrator

@pytest.mark.parametrize("method", ["obs", "inject", "dyn", "obs_stream"])
def test_cvodes_agrees_with_the_step(model_dir_factory, rng, method):
    """CVODES (reltol 1e-10, abstol 1e-12) vs the step: 1e-9 for the exact discretisation,
    1e-8 for RK4 with 8 substeps per interval (its error on these random networks is ~2e-9;
    with 1 substep ~1e-5)."""
    obs = load_observer(model_dir_factory(method, window=4), substeps=8)
    integ = obs.integrator("cvodes", reltol=1e-10, abstol=1e-12)
    for _ in range(2):
        z, w, y, y_next, u_next = random_step_args(obs, rng)
        p = np.concatenate([y, y_next, np.array(obs.memory.held(ca.DM(w))).ravel(), w.ravel(order="F")])
        zf = np.array(integ(x0=z, p=p)["xf"])
        tol = 1e-9 if obs.discretization == "exact" else 1e-8
        np.testing.assert_allclose(zf, np.array(obs.step(z, w, y, y_next, u_next)[0]),
                                   rtol=0, atol=tol)


def test_other_integrator_plugins_and_a_bad_one(model_dir_factory, rng):
    obs = load_observer(model_dir_factory("inject"), substeps=16)
    z, w, y, y_next, u_next = random_step_args(obs, rng)
    p = np.concatenate([y, y_next, w[-1], w.ravel(order="F")])
    reference = np.array(obs.step(z, w, y, y_next, u_next)[0])         # RK4 error ~1e-10
    for solver, opts in [("rk", {"number_of_finite_elements": 4}),
                         ("collocation", {"number_of_finite_elements": 4}),
                         ("idas", {"reltol": 1e-10, "abstol": 1e-12})]:
        zf = np.array(obs.integrator(solver, **opts)(x0=z, p=p)["xf"])
        np.testing.assert_allclose(zf, reference, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="solver: expected one of"):
        obs.integrator("euler")


# ----------------------------------------------------------------------------- estimator

@pytest.mark.parametrize("method", ["dyn", "obs", "obs_stream"])
def test_estimator_equals_simulate_sample_by_sample(model_dir_factory, method):
    obs = load_observer(model_dir_factory(method, window=4))
    tr = plant_run(T=1.0)
    expected = obs.simulate(tr.t, tr.y, tr.u).xhat
    est = obs.estimator()
    assert est.z is None
    for _ in range(2):                                             # and again after reset()
        for k in range(tr.t.size):
            assert np.array_equal(est.make_step(tr.y[k], tr.u[k]), expected[k])
        assert est.k == tr.t.size and est.z.shape == (5,) and est.w.shape == obs.memory_shape
        est.reset()


def test_estimator_rejects_bad_samples_and_keeps_its_state(model_dir_factory):
    est = load_observer(model_dir_factory("inject")).estimator()
    est.make_step([0.1], [0.2])
    z = est.z
    with pytest.raises(ValueError, match=r"y: expected shape \(1,\) at sample 1, received \(2,\)"):
        est.make_step([0.1, 0.2], [0.0])
    with pytest.raises(ValueError, match=r"u: expected finite values at sample 1"):
        est.make_step([0.1], [np.nan])
    assert np.array_equal(est.z, z) and est.k == 1
    with pytest.raises(TypeError, match="observer"):
        kc.observer.kkl.Estimator("obs")


# ----------------------------------------------------------------------------- inject: exact on a linear plant

def exact_linear_models(tmp_path):
    """Encoder T (Sylvester) and decoder pinv(T) of the linear test plant, as identity MLPs."""
    plant = kc.systems.get("linear")
    nz = 5
    A, B = -np.diag(np.arange(1.0, nz + 1)), np.ones((nz, 1))
    T = solve_sylvester(-A, LINEAR_F, B @ LINEAR_H)                # T F - A T = B H
    arrays = {}
    for prefix, W in (("encoder", T), ("decoder", np.linalg.pinv(T))):
        arrays.update({f"{prefix}/W0": W, f"{prefix}/b0": np.zeros(W.shape[0]),
                       f"{prefix}/in_mean": np.zeros(W.shape[1]),
                       f"{prefix}/in_std": np.ones(W.shape[1]),
                       f"{prefix}/out_mean": np.zeros(W.shape[0]),
                       f"{prefix}/out_std": np.ones(W.shape[0])})
    card = {"method": "autonomous", "system": {"name": "linear", "nx": 2, "nu": 1, "ny": 1},
            "design": {"A": A.tolist(), "B": B.tolist()}, "dt": DT, "window": 1,
            "architecture": {"encoder": {"sizes": [2, nz], "activation": "identity"},
                             "decoder": {"sizes": [nz, 2], "activation": "identity"}},
            "base": None, "noise": {"measurement_std": 0.0}, "training": {}}
    auto = save_model(tmp_path / "autonomous", arrays, card)
    return plant, auto, make_inject_model(auto, tmp_path / "inject")


def test_inject_recovers_the_exact_observer_of_a_linear_plant(tmp_path):
    plant, auto_dir, inject_dir = exact_linear_models(tmp_path)
    inject_model = load_model(inject_dir)
    assert inject_model.method == "inject" and inject_model.window == 1
    derived = inject_model.card["training"]["derived_from"]                 # self-contained: no base to load
    assert inject_model.base is None and derived["path"] == "../autonomous" and derived["method"] == "autonomous"
    assert derived["weights_sha256"] == load_model(auto_dir).card["weights_sha256"]
    tr = kc.simulate(plant, [0.8, -0.5], square_input(np.arange(200) * DT, 1.0, 1.5), T=10.0,
                     dt=DT)
    auto, inject = load_observer(auto_dir), load_observer(inject_dir, substeps=2)
    late = tr.t >= 5.0
    rmse = {name: np.sqrt(np.mean((obs.simulate(tr.t, tr.y, tr.u).xhat - tr.x)[late] ** 2))
            for name, obs in (("auto", auto), ("inject", inject))}
    # z = T x solves zdot = A z + B y + T G u exactly: what remains is the first-order hold of y
    # (measured: inject 1.8e-3, autonomous 0.41)
    assert rmse["inject"] < 5e-3
    assert rmse["auto"] > 50 * rmse["inject"]


def test_make_inject_model_needs_a_phase1_base(model_dir_factory, tmp_path):
    with pytest.raises(ValueError, match=r"'method': expected one of \['autonomous', 'curriculum'\].*'obs'"):
        make_inject_model(model_dir_factory("obs"), tmp_path / "inject")


# ----------------------------------------------------------------------------- deployment

def test_step_serialises_for_the_cli(model_dir_factory, tmp_path, rng):
    obs = load_observer(model_dir_factory("obs", window=4))
    obs.step.save(str(tmp_path / "step.casadi"))
    loaded = ca.Function.load(str(tmp_path / "step.casadi"))
    args = random_step_args(obs, rng)
    for a, b in zip(loaded(*args), obs.step(*args)):
        assert np.array_equal(np.array(a), np.array(b))


def test_deploy_side_does_not_import_torch():
    code = ("import sys, kklcasadi, kklcasadi.observer.kkl, kklcasadi.observer.codegen, kklcasadi.observer.interop; "
            "sys.exit('torch was imported' if 'torch' in sys.modules else 0)")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_closed_loop_example_writes_a_png(model_dir_factory, tmp_path, monkeypatch, capsys):
    out = tmp_path / "plots" / "closed_loop.png"
    monkeypatch.setattr(sys, "argv", ["closed_loop.py", "--model",
                                      str(model_dir_factory("inject")), "--out", str(out),
                                      "--T", "2", "--measurement-std", "0.01"])
    runpy.run_path(str(ROOT / "examples" / "closed_loop.py"), run_name="__main__")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "inject observer in the loop" in capsys.readouterr().out
    assert provenance.read(out).seeds == {"noise": 0}
    first = out.read_bytes()
    with pytest.raises(FileExistsError, match="^--out: .*closed_loop.png exists and this command does not overwrite"):
        runpy.run_path(str(ROOT / "examples" / "closed_loop.py"), run_name="__main__")     # before any work
    assert out.read_bytes() == first
    # a plot that fails leaves nothing at --out and nothing beside it
    import matplotlib.figure

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda *a, **k: (_ for _ in ()).throw(OSError("disk")))
    monkeypatch.setattr(sys, "argv", [*sys.argv[:4], str(tmp_path / "plots" / "again.png"), *sys.argv[5:]])
    with pytest.raises(OSError, match="disk"):
        runpy.run_path(str(ROOT / "examples" / "closed_loop.py"), run_name="__main__")
    assert sorted(p.name for p in out.parent.iterdir()) == ["closed_loop.png"]


# ----------------------------------------------------------------------------- domain monitor

def _with_domain(path, x_lo, x_hi, z_lo, z_hi):
    card = json.loads((path / CARD_FILE).read_text())
    card["domain"] = {"x_lo": x_lo, "x_hi": x_hi, "z_lo": z_lo, "z_hi": z_hi}
    write_signed_card(path, card)
    return path


def test_domain_monitor_flags_estimates_outside_the_trained_domain(model_dir_factory, rng):
    path = model_dir_factory("autonomous")
    assert load_observer(path).in_domain(np.zeros(2), np.zeros(5)) is None      # no domain recorded
    obs = load_observer(_with_domain(path, [-1, -1], [1, 1], [-50] * 5, [50] * 5))
    # the margin is DOMAIN_MARGIN of the range: x1 in [-1.2, 1.2]
    assert obs.in_domain([1.19, 0.0], np.zeros(5)) and not obs.in_domain([1.21, 0.0], np.zeros(5))
    assert not obs.in_domain([0.0, 0.0], [0, 0, 0, 0, 61.0])
    points = rng.uniform(-1.5, 1.5, (40, 2))
    flags = obs.in_domain(points, np.zeros((40, 5)))
    checked = [bool(np.asarray(obs.domain_check(np.zeros(5), np.zeros(obs.memory_shape), p))) for p in points]
    assert flags.tolist() == checked and 0 < flags.sum() < 40
    tr = plant_run(T=2.0)
    est = obs.simulate(tr.t, tr.y, tr.u)
    assert est.in_domain.shape == (40,)
    np.testing.assert_array_equal(est.in_domain, obs.in_domain(est.xhat, est.z))
    batch = obs.simulate(tr.t, np.stack([tr.y, tr.y]), np.stack([tr.u, tr.u]))
    assert batch.in_domain.shape == (2, 40)
    live = obs.estimator()
    for k in range(tr.t.size):
        live.make_step(tr.y[k], tr.u[k])
        assert live.stats["in_domain"] == est.in_domain[k]
    assert live.stats == {"k": 40, "in_domain": bool(est.in_domain[-1]),
                          "out_of_domain_steps": int((~est.in_domain).sum()), "status": 0, "held_steps": 0,
                          "restarts": 0}


def test_a_bad_domain_entry_names_the_field(model_dir_factory):
    path = _with_domain(model_dir_factory("autonomous"), [1, 1], [-1, -1], [0] * 5, [1] * 5)
    with pytest.raises(ValueError, match=r"'domain': expected lo <= hi"):
        load_observer(path)
    path = _with_domain(model_dir_factory("autonomous"), [1], [2], [0] * 5, [1] * 5)
    with pytest.raises(ValueError, match=r"'domain\.x_lo': expected a list of 2 finite numbers"):
        load_observer(path)


def test_float32_sample_times_are_accepted_within_their_rounding(model_dir_factory):
    obs = load_observer(model_dir_factory("autonomous"))
    tr = plant_run(T=50.0)
    t32 = np.arange(tr.t.size, dtype=np.float32) * np.float32(DT)
    np.testing.assert_array_equal(obs.simulate(t32, tr.y, tr.u).xhat, obs.simulate(tr.t, tr.y, tr.u).xhat)
    with pytest.raises(ValueError, match="t: expected samples spaced by the observer's dt"):
        obs.simulate(t32 * np.float32(1.001), tr.y, tr.u)


def test_an_inject_model_deploys_without_its_base(tmp_path):
    plant, auto_dir, inject_dir = exact_linear_models(tmp_path)
    moved = tmp_path / "deployed" / "inject"
    moved.parent.mkdir()
    inject_dir.rename(moved)
    shutil.rmtree(auto_dir)
    obs = load_observer(moved)
    assert obs.method == "inject" and obs.model_injection is not None
