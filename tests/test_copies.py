"""Model copies in the ``bank`` latent: the Kalman-Bucy gains, the copies' step against the exact discretisation
of a linear plant, their split into the card's (A, B) and the input term, and a bank with copies end to end
(trained, loaded, simulated, compiled to C, checked on load)."""

import json
import shutil
from dataclasses import replace

import casadi as ca
import numpy as np
import pytest
import scipy.linalg
from conftest import c_program_estimates

import kklcasadi as kc
from kklcasadi.model.variants.copies import ModelCopies, copy_count
from kklcasadi.nets.hold import foh_matrices
from kklcasadi.plant.systems import LINEAR_F, LINEAR_G, LINEAR_H


@pytest.mark.parametrize("name, weights", [("linear", (1.0,)), ("duffing", (1.0, 100.0)), ("vdp", (0.1, 1e4)),
                                           ("duffing", ((0.0, 8e8), 3.0))])          # one intensity per state
def test_the_gains_solve_the_filter_riccati_equation_and_stabilise_the_linearisation(name, weights):
    system = kc.systems.get(name)
    copies = ModelCopies.design(system, weights)
    r = system.x0_box.mean(axis=1)
    x = ca.SX.sym("x", system.nx)
    F = np.array(ca.Function("F", [x], [ca.jacobian(system.f(x, 0), x)])(r))
    H = np.array(ca.Function("H", [x], [ca.jacobian(system.h(x), x)])(r))
    for w, L in zip(weights, copies.gains):
        # L = P H^T with F P + P F^T - P H^T H P + Q = 0 (Q = w I, or diag(w) per state), P symmetric positive definite
        Q = np.diag(np.broadcast_to(np.asarray(w, dtype=float), (system.nx,)))
        P = scipy.linalg.solve_continuous_are(F.T, H.T, Q, np.eye(system.ny))
        np.testing.assert_allclose(L, P @ H.T, rtol=1e-12)
        residual = F @ P + P @ F.T - P @ H.T @ H @ P + Q
        assert np.abs(residual).max() < 1e-9 * max(1.0, np.max(w))
        assert np.linalg.eigvalsh(P).min() > 0
        assert np.linalg.eigvals(F - L @ H).real.max() < 0
    assert copies.nz == len(weights) * system.nx and np.array_equal(copies.reference, r)
    np.testing.assert_allclose(copies.bound, 10 * 0.5 * (system.x0_box[:, 1] - system.x0_box[:, 0]))


def test_a_faster_copy_trusts_the_measurement_more():
    copies = ModelCopies.design(kc.systems.get("duffing"), (1.0, 100.0, 1e4))
    A, _ = copies.linear_part()
    speeds = [np.abs(np.linalg.eigvals(A[2 * i:2 * i + 2, 2 * i:2 * i + 2])).max() for i in range(3)]
    assert speeds[0] < speeds[1] < speeds[2]
    assert copies.gains[0, 0, 0] < copies.gains[1, 0, 0] < copies.gains[2, 0, 0]


def _linear_reference(L, y, u, dt):
    """The copy on the linear plant by the exact discretisation: xhat' = (F - L H) xhat + L y + G u, y FOH, u held."""
    m = foh_matrices(LINEAR_F - L @ LINEAR_H, L, dt, Bu=LINEAR_G, c=np.zeros(2))
    z = np.zeros((y.shape[0], 2))
    for k in range(y.shape[0] - 1):
        z[k + 1] = m.Ad @ z[k] + m.Gy @ y[k] + m.Gy_next @ y[k + 1] + m.Gu @ u[k] + m.g
    return z


def test_on_a_linear_plant_the_copy_is_the_exact_filter_to_rk4_order():
    system = kc.systems.get("linear")
    tr = kc.simulate(system, [0.7, -0.3], kc.signals.make("sinusoid", amplitude=0.8, omega=1.3), T=10.0, dt=0.05,
                     measurement_std=0.05, seed=2)
    base = ModelCopies.design(system, (30.0,))
    exact = _linear_reference(base.gains[0], tr.y, tr.u, 0.05)
    errors = []
    for substeps in (1, 2, 4):
        z = replace(base, substeps=substeps).run(tr.y[None], tr.u[None], 0.05)[0]
        errors.append(np.abs(z - exact).max())
    assert errors[0] < 1e-4
    # fourth order: halving the step divides the error by about 16
    assert 10 < errors[0] / errors[1] < 22 and 10 < errors[1] / errors[2] < 22


def test_the_card_design_and_the_input_term_add_up_to_the_copies_field():
    system = kc.systems.get("vdp")
    copies = ModelCopies.design(system, (1.0, 100.0))
    A, B = copies.linear_part()
    rng = np.random.default_rng(0)
    z, y, u = ca.SX.sym("z", copies.nz), ca.SX.sym("y", 1), ca.SX.sym("u", 1)
    field = ca.Function("field", [z, y, u], [copies.field(z, y, u)])
    rest = ca.Function("rest", [z, u], [copies.remainder(z, u)])
    for _ in range(5):
        zv, yv, uv = rng.normal(size=copies.nz), rng.normal(size=1), rng.normal(size=1)
        xhat = copies.reference + zv.reshape(2, 2)
        expected = np.concatenate([np.asarray(system.f(xi, uv)).ravel()
                                   + L @ (yv - np.asarray(system.h(xi)).ravel()) for xi, L in zip(xhat, copies.gains)])
        np.testing.assert_allclose(np.asarray(field(zv, yv, uv)).ravel(), expected, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(A @ zv + B @ yv + np.asarray(rest(zv, uv)).ravel(), expected, rtol=1e-12,
                                   atol=1e-12)


def test_a_copy_thrown_off_comes_back_inside_its_bound():
    system = kc.systems.get("duffing")
    copies = ModelCopies.design(system, (1.0,))
    y = np.full((1, 40, 1), 1e3)                 # a measurement far beyond the box
    z = copies.run(y, np.zeros((1, 40, 1)), 0.05)
    assert np.all(np.isfinite(z)) and np.all(np.abs(z) <= copies.bound + 1e-12)
    assert np.isclose(np.abs(z[0, -1, 0]), copies.bound[0])


@pytest.mark.parametrize("kwargs, match", [
    ({"weights": (0.0,)}, "weights: expected one or more finite process intensities > 0"),
    ({"weights": ((0.0, 0.0),)}, r"or per copy nx = 2 of them >= 0, not all 0"),
    ({"weights": ((1.0, -1.0),)}, "weights: expected one or more finite process intensities > 0"),
    ({"weights": ((1.0, 1.0, 1.0),)}, "weights: expected one or more finite process intensities > 0"),
    ({"weights": ()}, "weights: expected one or more"),
    ({"weights": (1.0,), "bound_scale": -1.0}, "bound_scale: expected a finite number > 0"),
])
def test_design_rejects_bad_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ModelCopies.design(kc.systems.get("duffing"), **kwargs)


def test_copies_need_a_detectable_plant():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    blind = kc.System("blind", x, u, [x[1], x[1] + u], x[0] * 0 + x[1] ** 3, [[-1, 1], [-1, 1]])
    with pytest.raises(ValueError, match="not detectable from y"):
        ModelCopies.design(blind, (1.0,))


def test_a_copys_angle_follows_its_measurement_turn_for_turn():
    """A pendulum's copy stepped from its state and measurements one turn on lands one turn on (its field is
    periodic in the angle), so the decoder's features ``z - G_a y_a`` (:func:`latent_gains`: 1 on the copy's
    measured angle, the filters' DC gains, 0 elsewhere) do not see the turn."""
    from kklcasadi.model.variants import bankdecoder as bd
    from kklcasadi.model.variants import filterbank as fb

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    pend = kc.System("pend", x, u, [x[1], -ca.sin(x[0]) - 0.3 * x[1] + u], x[0], [[-1.5, 1.5], [-1.5, 1.5]],
                     angle_states=[0], angle_outputs=[0])
    copies = ModelCopies.design(pend, (4.0, 400.0))
    step = copies.step_function(0.05)
    rng = np.random.default_rng(3)
    turn = np.tile([2 * np.pi, 0.0], 2)
    for _ in range(5):
        z, y, y1, uu = rng.uniform(-1, 1, 4), rng.uniform(-1, 1, 1), rng.uniform(-1, 1, 1), rng.uniform(-1, 1, 1)
        np.testing.assert_allclose(np.asarray(step(z + turn, y + 2 * np.pi, y1 + 2 * np.pi, uu)).ravel(),
                                   np.asarray(step(z, y, y1, uu)).ravel() + turn, rtol=0, atol=1e-12)
    bank = fb.FilterBank.design(1, 1, [0.5, 2.0], [1.0])
    angles = bd.Angles.of(pend)
    gains = bd.latent_gains(bank, bank.nz + copies.nz, pend.nx, angles)
    np.testing.assert_array_equal(gains[bank.nz:, 0], [1.0, 0.0, 1.0, 0.0])
    np.testing.assert_array_equal(gains[:bank.nz], bd.dc_gains(bank))
    zz = np.concatenate([rng.uniform(-1, 1, bank.nz), z])[None]
    shifted = zz + 2 * np.pi * gains[:, 0]
    np.testing.assert_allclose(bd.decoder_features(shifted, y[None] + 2 * np.pi, uu[None], angles=angles, gains=gains),
                               bd.decoder_features(zz, y[None], uu[None], angles=angles, gains=gains), atol=1e-12)
    for nz, nx in ((bank.nz + 3, 2), (bank.nz - 1, 2), (bank.nz + 2, None)):
        with pytest.raises(ValueError, match="nz: expected the filters' 3 latents and whole model copies"):
            bd.latent_gains(bank, nz, nx, angles)


def test_model_copies_validate_their_arrays():
    system = kc.systems.get("duffing")
    copies = ModelCopies.design(system, (1.0,))
    with pytest.raises(ValueError, match="gains: expected finite gains of shape"):
        replace(copies, gains=np.zeros((1, 3, 1)))
    with pytest.raises(ValueError, match="bound: expected half-widths > 0"):
        replace(copies, bound=np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match="substeps: expected a positive integer"):
        replace(copies, substeps=0)
    with pytest.raises(ValueError, match=r"arrays: expected the model copies' arrays"):
        ModelCopies.from_arrays({"copies/gains": copies.gains}, system, 2)
    assert copy_count(copies.arrays()) == 2 and copy_count({}) == 0


# ---------------------------------------------------------------------- a bank with copies end to end
@pytest.fixture(scope="module")
def copies_dir(tmp_path_factory):
    pytest.importorskip("torch")
    from kklcasadi.plant.runs import RolloutConfig
    from kklcasadi.train import LoopConfig, default_config, train_observer
    from kklcasadi.train.decoder import DecoderConfig

    config = replace(default_config("duffing", "bank"), y_poles=(0.5, 2.0), u_poles=(1.0,), members=2,
                     copies=(1.0, 1e4), rollouts=RolloutConfig(n_traj=8, T=6.0),
                     decoder=DecoderConfig(hidden=(8, 8), loop=LoopConfig(epochs=2, batch_size=64)))
    return train_observer("duffing", "bank", tmp_path_factory.mktemp("copies") / "bank", config=config, seed=3,
                          progress=False)


def test_the_card_records_the_copies_and_their_linear_part(copies_dir):
    from kklcasadi.model.files import load_model

    model = load_model(copies_dir)
    spec = model.spec.architecture
    assert model.card["architecture"]["bank"]["copies"] == {"weights": [1.0, 10000.0], "substeps": 5}
    assert spec.n_copies == 2 and spec.n_filters == 2 + 1 + 1 and model.A.shape == (8, 8)
    assert model.card["architecture"]["decoder"]["sizes"][0] == 8 + 1 + 1
    copies = spec.model_copies(model.arrays, kc.systems.get("duffing"))
    A, B = copies.linear_part()
    np.testing.assert_array_equal(model.A[4:, 4:], A)
    np.testing.assert_array_equal(model.B[4:], B)
    assert model.spec.monitor.features == 8 + 2


def test_the_observer_with_copies_equals_the_reference_and_its_c_code(copies_dir, tmp_path):
    from kklcasadi.model.files import load_model
    from kklcasadi.model.variants import bankdecoder as bd

    obs = kc.load_observer(copies_dir)
    tr = kc.simulate(obs.system, [0.4, -0.6], kc.signals.make("square", amplitude=0.7, omega=1.0), T=5.0, dt=obs.dt,
                     process_std=0.1, measurement_std=0.1, seed=4)
    model = load_model(copies_dir)
    spec = model.spec.architecture
    copies = spec.model_copies(model.arrays, obs.system)
    expected = bd.estimate(spec.decoder_spec, spec.filter_arrays(model.arrays), tr.y, tr.u, obs.dt, copies=copies)
    est = obs.simulate(tr.t, tr.y, tr.u)
    np.testing.assert_allclose(est.xhat, expected, rtol=1e-10, atol=1e-10)
    live = obs.estimator()
    np.testing.assert_allclose([live.make_step(y, u) for y, u in zip(tr.y, tr.u)], est.xhat, rtol=0, atol=1e-12)
    # the whole field A z + B y + input term, integrated by RK4, is the same observer up to the step's accuracy
    rk4 = kc.load_observer(copies_dir, discretization="rk4", substeps=8).simulate(tr.t, tr.y, tr.u)
    assert np.abs(rk4.xhat - est.xhat).max() < 1e-4 * (1 + np.abs(est.xhat).max())
    with pytest.raises(ValueError, match="copies: expected the ModelCopies"):
        bd.estimate(spec.decoder_spec, spec.filter_arrays(model.arrays), tr.y, tr.u, obs.dt)
    if shutil.which("gcc") is None:
        return
    np.testing.assert_array_equal(c_program_estimates(obs, tmp_path, "bank", tr.t, tr.y, tr.u), est.xhat)


def test_a_card_whose_copies_do_not_match_its_design_is_refused(copies_dir, tmp_path):
    from kklcasadi.model.files import load_model, save_model

    model = load_model(copies_dir)
    arrays = dict(model.arrays)
    arrays["copies/gains"] = arrays["copies/gains"] * 1.5
    save_model(tmp_path / "m", arrays, model.card, overwrite=True)
    with pytest.raises(ValueError, match="design: expected the model copies' rows of A and B"):
        kc.load_observer(tmp_path / "m")
    card = json.loads(json.dumps(model.card))
    card["architecture"]["bank"]["copies"] = {"weights": [1.0], "substeps": 0}
    with pytest.raises(ValueError, match="architecture.bank.copies"):
        save_model(tmp_path / "n", model.arrays, card, overwrite=True)
        kc.load_observer(tmp_path / "n")


@pytest.mark.parametrize("field, value, match", [
    ("copies", (0.0,), "copies: expected a tuple of process intensities > 0"),
    ("copies", 1.0, "copies: expected a tuple"),
    ("copy_substeps", 0, "copy_substeps: expected a positive integer"),
])
def test_bank_config_rejects_bad_copies(field, value, match):
    pytest.importorskip("torch")
    from kklcasadi.train.bank import BankConfig

    with pytest.raises(ValueError, match=match):
        BankConfig(**{field: value})


def test_design_copies_takes_enough_substeps_for_the_fastest_copy():
    pytest.importorskip("torch")
    from kklcasadi.train.bank import BankConfig, design_copies

    system = kc.systems.get("duffing")
    assert design_copies(system, BankConfig(), 0.05) is None
    assert design_copies(system, BankConfig(copies=(1.0,)), 0.05).substeps == 1
    assert design_copies(system, BankConfig(copies=(1.0, 1e4)), 0.05).substeps == 5      # |eig| 100 rad/s
    assert design_copies(system, BankConfig(copies=(1.0, 1e4)), 0.01).substeps == 1
    assert design_copies(system, BankConfig(copies=(1.0,), copy_substeps=3), 0.05).substeps == 3


PLANTS = '''import casadi as ca
import kklcasadi as kc


def blind():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    return kc.System("blind", x, u, [x[1], x[1] + u], x[1] ** 3, [[-1, 1], [-1, 1]])
'''


@pytest.mark.parametrize("plant, message", [
    ("blind", "error: --copies: expected weights with a stabilising Kalman-Bucy gain, received 1, with no stabilising "
              "Kalman-Bucy gain: blind linearised at its box centre"),
])
def test_kklcasadi_train_refuses_copies_the_plant_cannot_take_before_training(plant, message, tmp_path, capsys):
    pytest.importorskip("torch")
    from kklcasadi.cli import main

    (tmp_path / "plants.py").write_text(PLANTS)
    code = main(["train", "--plant", f"{tmp_path / 'plants.py'}:{plant}", "--copies", "1", "--out",
                 str(tmp_path / "m"), "--quiet"])
    assert code == 2 and message in capsys.readouterr().err and not (tmp_path / "m").exists()


# ---------------------------------------------------------------------- copies at parameter values of their own
def test_a_copy_at_its_own_parameters_is_the_copy_of_that_plant():
    family = kc.systems.get("duffing", param_spread=0.3)
    values = np.array([[0.7, 1.3], [1.3, 0.7], family.param_nominal])
    copies = ModelCopies.design(family, (1.0, 100.0, 1.0), params=values)
    A, B = copies.linear_part()
    for i, (w, p) in enumerate(zip((1.0, 100.0, 1.0), values)):
        own = ModelCopies.design(kc.systems.get("duffing", param_spread=0.3).at(p), (w,))
        np.testing.assert_array_equal(copies.gains[i], own.gains[0])
        A_own, B_own = own.linear_part()
        np.testing.assert_array_equal(A[2 * i:2 * i + 2, 2 * i:2 * i + 2], A_own)
        np.testing.assert_array_equal(B[2 * i:2 * i + 2], B_own)
    # the field: copy i is f(r + z_i, u; p_i) + L_i (y - h(r + z_i; p_i)), written out by hand (Duffing:
    # x1' = x2, x2' = -alpha x1 - beta x1^3 + u, y = x1)
    rng = np.random.default_rng(0)
    z, y, u = rng.normal(size=6), rng.normal(size=1), rng.normal(size=1)
    got = np.array(ca.Function("fld", [], [copies.field(ca.DM(z), ca.DM(y), ca.DM(u))])()["o0"]).ravel()
    r = copies.reference
    for i, (a, b) in enumerate(values):
        x = r + z[2 * i:2 * i + 2]
        want = np.array([x[1], -a * x[0] - b * x[0] ** 3 + u[0]]) + copies.gains[i] @ (y - x[:1])
        np.testing.assert_allclose(got[2 * i:2 * i + 2], want, rtol=1e-13, atol=1e-13)
    # the card's (A, B) and the input term add up to the field at the copies' own parameters
    rest = np.array(ca.Function("rem", [], [copies.remainder(ca.DM(z), ca.DM(u))])()["o0"]).ravel()
    np.testing.assert_allclose(A @ z + B @ y + rest, got, rtol=1e-12, atol=1e-12)


def test_copies_at_the_nominal_values_step_bitwise_as_copies_without_parameters():
    family = kc.systems.get("duffing", param_spread=0.3)
    nominal = family.at(family.param_nominal)
    plain = ModelCopies.design(nominal, (1.0, 1e4))
    at = ModelCopies.design(family, (1.0, 1e4), params=[family.param_nominal] * 2)
    np.testing.assert_array_equal(plain.gains, at.gains)
    rng = np.random.default_rng(1)
    y, u = rng.normal(size=(3, 40, 1)), rng.normal(size=(3, 40, 1))
    np.testing.assert_array_equal(plain.run(y, u, 0.05), at.run(y, u, 0.05))
    assert nominal.family is family and kc.systems.get("duffing").family is None


def test_copies_at_parameters_need_the_family_and_one_row_per_copy():
    family = kc.systems.get("duffing", param_spread=0.3)
    with pytest.raises(ValueError, match=r"params: expected None for plant 'duffing', which declares no parameters"):
        ModelCopies.design(kc.systems.get("duffing"), (1.0,), params=[[1.0, 1.0]])
    with pytest.raises(ValueError, match=r"params: expected finite parameter values of shape \(m = 2 copies, "
                                         r"n_params = 2\)"):
        ModelCopies.design(family, (1.0, 2.0), params=[[1.0, 1.0]])
    with pytest.raises(ValueError, match=r"params: expected finite parameter values"):
        ModelCopies.design(family, (1.0,), params=[[1.0, np.nan]])
    # a plant fixed from the family takes copies at other values (load_observer's nominal plant)
    copies = ModelCopies.design(family.at(family.param_nominal), (1.0,), params=[[0.7, 0.7]])
    np.testing.assert_array_equal(copies.gains, ModelCopies.design(family, (1.0,), params=[[0.7, 0.7]]).gains)


def test_corner_copies_sit_at_the_corners_of_the_box_before_the_nominal_ones():
    pytest.importorskip("torch")
    from kklcasadi.train.bank import BankConfig, copy_plan, design_copies

    family = kc.systems.get("vdp", param_spread=0.3)
    weights, params = copy_plan(family, BankConfig(copies=(1.0, 1e4), corner_copies=(3.0,)))
    assert weights == [3.0] * 8 + [1.0, 1e4]
    box = family.param_box
    np.testing.assert_array_equal(params[:8], [[a, b, k] for a in box[0] for b in box[1] for k in box[2]])
    np.testing.assert_array_equal(params[8:], [family.param_nominal] * 2)
    assert copy_plan(family, BankConfig(copies=(1.0,))) == ([1.0], None)
    assert design_copies(family, BankConfig(corner_copies=(1.0,)), 0.05).m == 8
    with pytest.raises(ValueError, match=r"corner_copies: expected \(\) for plant 'vdp', which declares no "
                                         r"parameters"):
        copy_plan(kc.systems.get("vdp"), BankConfig(corner_copies=(1.0,)))
    for bad in ((0.0,), 1.0, ((1.0, 2.0),)):
        with pytest.raises(ValueError, match="corner_copies: expected a tuple of process intensities > 0"):
            BankConfig(corner_copies=bad)


@pytest.fixture(scope="module")
def corner_dir(tmp_path_factory):
    pytest.importorskip("torch")
    from kklcasadi.plant.runs import RolloutConfig
    from kklcasadi.train import LoopConfig, default_config, train_observer
    from kklcasadi.train.decoder import DecoderConfig

    config = replace(default_config("duffing", "bank"), y_poles=(0.5, 2.0), u_poles=(1.0,), members=1,
                     copies=(1.0,), corner_copies=(100.0,), rollouts=RolloutConfig(n_traj=8, T=6.0),
                     decoder=DecoderConfig(hidden=(8, 8), loop=LoopConfig(epochs=2, batch_size=64)))
    return train_observer(kc.systems.get("duffing", param_spread=0.3), "bank",
                          tmp_path_factory.mktemp("corners") / "bank", config=config, seed=3, progress=False)


def test_a_bank_with_corner_copies_records_them_and_equals_its_reference_and_c_code(corner_dir, tmp_path):
    from kklcasadi.model.files import load_model
    from kklcasadi.model.variants import bankdecoder as bd

    model = load_model(corner_dir)
    corners = [[0.7, 0.7], [0.7, 1.3], [1.3, 0.7], [1.3, 1.3]]
    assert model.card["architecture"]["bank"]["copies"] == {"weights": [100.0] * 4 + [1.0], "substeps": 1,
                                                           "params": corners + [[1.0, 1.0]]}
    obs = kc.load_observer(corner_dir)          # the family rebuilt from the card's box, taken at its nominal values
    assert obs.system.fingerprint == kc.systems.get("duffing").fingerprint and obs.system.family is not None
    family = kc.systems.get("duffing", param_spread=0.3)
    same = kc.load_observer(corner_dir, system=family)
    tr = kc.simulate(family, [0.4, -0.6], kc.signals.make("square", amplitude=0.7, omega=1.0), T=5.0, dt=obs.dt,
                     process_std=0.1, measurement_std=0.1, seed=4, params=[1.3, 0.7])
    spec = model.spec.architecture
    copies = spec.model_copies(model.arrays, family)
    np.testing.assert_array_equal(copies.params, corners + [[1.0, 1.0]])
    expected = bd.estimate(spec.decoder_spec, spec.filter_arrays(model.arrays), tr.y, tr.u, obs.dt, copies=copies)
    est = obs.simulate(tr.t, tr.y, tr.u)
    np.testing.assert_allclose(est.xhat, expected, rtol=1e-10, atol=1e-10)
    np.testing.assert_array_equal(same.simulate(tr.t, tr.y, tr.u).xhat, est.xhat)
    with pytest.raises(ValueError, match="params: expected None for plant 'duffing'"):
        spec.model_copies(model.arrays, kc.systems.get("duffing"))
    if shutil.which("gcc") is None:
        return
    np.testing.assert_array_equal(c_program_estimates(obs, tmp_path, "bank", tr.t, tr.y, tr.u), est.xhat)


@pytest.mark.parametrize("params, match", [
    ([[1.0, 1.0]], "architecture.bank.copies"),                             # one row for five copies
    ([[0.7, 0.7], [0.7, 1.3], [1.3, 0.7], [1.3, 1.3], [1.0, "x"]], "architecture.bank.copies"),
    ([[0.7], [0.7], [1.3], [1.3], [1.0]], "params: expected finite parameter values of shape"),   # n_params 1
    ([[0.8, 0.7], [0.7, 1.3], [1.3, 0.7], [1.3, 1.3], [1.0, 1.0]], "design: expected the model copies' rows"),
])
def test_a_card_with_bad_copy_parameters_is_refused(corner_dir, tmp_path, params, match):
    from kklcasadi.model.files import load_model, save_model

    model = load_model(corner_dir)
    card = json.loads(json.dumps(model.card))
    card["architecture"]["bank"]["copies"]["params"] = params
    with pytest.raises(ValueError, match=match):
        save_model(tmp_path / "m", model.arrays, card, overwrite=True)
        kc.load_observer(tmp_path / "m")


def test_kklcasadi_train_refuses_corner_copies_without_a_family_before_training(tmp_path, capsys):
    pytest.importorskip("torch")
    from kklcasadi.cli import main

    code = main(["train", "--system", "duffing", "--corner-copies", "1", "--out", str(tmp_path / "m"), "--quiet"])
    assert code == 2 and not (tmp_path / "m").exists()
    assert "error: --corner-copies: expected () for plant 'duffing', which declares no parameters" \
        in capsys.readouterr().err


def test_kklcasadi_train_over_a_family_with_corner_copies_ends_with_its_summary(tmp_path, capsys):
    """The closing summary loads the model with the family's nominal plant (it refused the family's fingerprint)."""
    pytest.importorskip("torch")
    from kklcasadi.cli import main

    out = tmp_path / "m"
    code = main(["train", "--system", "duffing", "--param-spread", "0.3", "--corner-copies", "1", "--runs", "6",
                 "--epochs", "1", "--members", "1", "--threads", "1", "--out", str(out), "--quiet"])
    assert code == 0, capsys.readouterr().err
    assert "RMSE" in capsys.readouterr().out
    card = json.loads((out / "card.json").read_text())
    assert card["architecture"]["bank"]["copies"]["params"][:4] == [[0.7, 0.7], [0.7, 1.3], [1.3, 0.7], [1.3, 1.3]]
    assert card["system"]["fingerprint"] == kc.systems.get("duffing").fingerprint
