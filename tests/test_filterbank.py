"""The filter-bank latent (exact FOH discretisation) and its decoder in numpy and CasADi."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from kklcasadi.model.variants import bankdecoder as bd
from kklcasadi.model.variants import filterbank as fb
from kklcasadi.nets.specs import DECODER


def _bank() -> fb.FilterBank:
    return fb.FilterBank.design(1, 1, [0.3, 1.0, 5.0], [0.5, 2.0], y_resonators=[(0.3, 1.2)], clock=0.4)


def _decoder_arrays(bank: fb.FilterBank, nx: int, rng: np.random.Generator,
                    scale: np.ndarray) -> tuple[dict, bd.DecoderSpec]:
    sizes = [bank.nz + bank.ny + bank.nu, 7, 6, nx]
    arrays = {f"{DECODER}/in_mean": rng.normal(size=sizes[0]), f"{DECODER}/in_std": rng.uniform(0.5, 2, sizes[0]),
              f"{DECODER}/out_mean": rng.normal(size=nx), f"{DECODER}/out_std": rng.uniform(0.5, 2, nx),
              bd.ASINH_SCALE: scale}
    for i, (d_out, d_in) in enumerate(zip(sizes[1:], sizes[:-1])):
        arrays[f"{DECODER}/W{i}"] = rng.normal(size=(d_out, d_in)) / np.sqrt(d_in)
        arrays[f"{DECODER}/b{i}"] = rng.normal(size=d_out) * 0.1
    arrays.update(fb.bank_arrays(bank))
    return arrays, bd.DecoderSpec.from_card({"sizes": sizes, "activation": "tanh"})


def test_design_layout_and_unit_dc_gain() -> None:
    bank = _bank()
    assert (bank.nz, bank.ny, bank.nu) == (3 + 2 + 2 + 1, 1, 1)
    # steady state of zdot = A z + By y + Bu u + c for constant y = 2, u = -1: filters give y or u, clock 1
    z_ss = -np.linalg.solve(bank.A, bank.By @ [2.0] + bank.Bu @ [-1.0] + bank.c)
    np.testing.assert_allclose(z_ss, [2, 2, 2, 2, 0, -1, -1, 1], atol=1e-12)


def test_discretisation_matches_ode_with_linear_y_and_held_u() -> None:
    bank = _bank()
    dt = 0.05
    m = bank.discretise(dt)
    rng = np.random.default_rng(0)
    z0, y0, y1, u0 = rng.normal(size=bank.nz), rng.normal(size=1), rng.normal(size=1), rng.normal(size=1)

    def rhs(t: float, z: np.ndarray) -> np.ndarray:
        y = y0 + (y1 - y0) * t / dt
        return bank.A @ z + bank.By @ y + bank.Bu @ u0 + bank.c

    ref = solve_ivp(rhs, (0, dt), z0, rtol=1e-12, atol=1e-14).y[:, -1]
    got = m.Ad @ z0 + m.Gy @ y0 + m.Gy_next @ y1 + m.Gu @ u0 + m.g
    np.testing.assert_allclose(got, ref, atol=1e-11)


def test_run_matches_casadi_step_and_starts_at_zero() -> None:
    bank = _bank()
    rng = np.random.default_rng(1)
    y, u = rng.normal(size=(3, 40, 1)), rng.normal(size=(3, 40, 1))
    z = bank.run(y, u, 0.05)
    assert z.shape == (3, 40, bank.nz)
    np.testing.assert_array_equal(z[:, 0], 0.0)
    step = bank.step_function(0.05)
    zc = np.zeros(bank.nz)
    for k in range(39):
        zc = np.asarray(step(zc, y[2, k], y[2, k + 1], u[2, k])).ravel()
    np.testing.assert_allclose(zc, z[2, -1], atol=1e-12)
    np.testing.assert_allclose(bank.run(y[1], u[1], 0.05), z[1], atol=0)


@pytest.mark.parametrize("scale", [np.array([0.0, 0.0]), np.array([0.0, 0.01])])
def test_decoder_numpy_and_casadi_agree(scale: np.ndarray) -> None:
    bank = _bank()
    rng = np.random.default_rng(2)
    arrays, spec = _decoder_arrays(bank, 2, rng, scale)
    dec = bd.decoder_function(spec, arrays)
    feats = rng.normal(size=(50, bank.nz + 2))
    ref = bd.decode(spec, arrays, feats[:, :bank.nz], feats[:, bank.nz:bank.nz + 1], feats[:, -1:])
    got = np.asarray(dec.map(50)(feats[:, :bank.nz].T, feats[:, bank.nz:bank.nz + 1].T, feats[:, -1:].T)).T
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)


def test_asinh_output_round_trips() -> None:
    bank = _bank()
    rng = np.random.default_rng(3)
    scale = np.array([0.0, 0.01])
    arrays, spec = _decoder_arrays(bank, 2, rng, scale)
    plain = dict(arrays)
    plain[bd.ASINH_SCALE] = np.zeros(2)
    z, y, u = rng.normal(size=(20, bank.nz)), rng.normal(size=(20, 1)), rng.normal(size=(20, 1))
    v = bd.decode(spec, plain, z, y, u)                 # the network's raw output
    x = bd.decode(spec, arrays, z, y, u)
    np.testing.assert_array_equal(x[:, 0], v[:, 0])
    np.testing.assert_allclose(np.arcsinh(x[:, 1] / 0.01), v[:, 1], rtol=1e-12)


def test_estimate_is_bank_then_decoder() -> None:
    bank = _bank()
    rng = np.random.default_rng(4)
    arrays, spec = _decoder_arrays(bank, 2, rng, np.array([0.0, 0.5]))
    y, u = rng.normal(size=(2, 30, 1)), rng.normal(size=(2, 30, 1))
    xhat = bd.estimate(spec, arrays, y, u, 0.05)
    z = bank.run(y, u, 0.05)
    np.testing.assert_allclose(xhat, bd.decode(spec, arrays, z, y, u), atol=0)
    np.testing.assert_allclose(bd.estimate(spec, arrays, y[0], u[0], 0.05), xhat[0], atol=0)


def test_validation_errors() -> None:
    with pytest.raises(ValueError, match="Hurwitz"):
        fb.FilterBank(np.array([[0.1]]), np.ones((1, 1)), np.zeros((1, 1)), np.zeros(1))
    with pytest.raises(ValueError, match="distinct"):
        fb.FilterBank.design(1, 1, [1.0, 1.0])
    with pytest.raises(ValueError, match="positive"):
        fb.FilterBank.design(1, 1, [-1.0])
    with pytest.raises(ValueError, match="clock"):
        fb.FilterBank.design(1, 1, [1.0], clock=0.0)
    bank = _bank()
    with pytest.raises(ValueError, match="u must have shape"):
        bank.run(np.zeros((2, 10, 1)), np.zeros((2, 9, 1)), 0.05)
    with pytest.raises(ValueError, match="dt"):
        bank.discretise(0.0)
    arrays, spec = _decoder_arrays(bank, 2, np.random.default_rng(5), np.array([0.0, -1.0]))
    with pytest.raises(ValueError, match="asinh_scale"):
        bd.decode(spec, arrays, np.zeros((1, bank.nz)), np.zeros((1, 1)), np.zeros((1, 1)))


def test_observer_step_reproduces_estimate() -> None:
    bank = _bank()
    rng = np.random.default_rng(6)
    arrays, spec = _decoder_arrays(bank, 2, rng, np.array([0.0, 0.1]))
    y, u = rng.normal(size=(25, 1)), rng.normal(size=(25, 1))
    ref = bd.estimate(spec, arrays, y, u, 0.05)
    step = bd.observer_step(spec, arrays, 0.05)
    traj = step.mapaccum("traj", 24, 2)   # z and w are carried
    z_all, _, xhat = traj(np.zeros(bank.nz), u[0], y[:-1].T, y[1:].T, u[1:].T)
    np.testing.assert_allclose(np.asarray(xhat).T, ref[1:], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(z_all).T, bank.run(y, u, 0.05)[1:], atol=1e-12)


def _angle_bank() -> fb.FilterBank:
    return fb.FilterBank.design(2, 1, [0.5, 3.0], [1.0], y_resonators=[(0.4, 2.0)], clock=0.3)


#: Outputs 0 and 1 are angles; state 0 is output 0, state 2 an angle no output measures (box centre 1.0).
ANGLES = bd.Angles(outputs=(0, 1), measured=((0, 0),), free=((2, 1.0),))


def test_dc_gains_are_one_for_the_filters_of_an_output_and_zero_elsewhere() -> None:
    bank = _angle_bank()
    g = bd.dc_gains(bank)
    # per output: 2 first-order filters, then the resonators (q, qdot/omega) of both, the input filter, the clock
    np.testing.assert_allclose(g[:, 0], [1, 1, 0, 0, 1, 0, 0, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(g[:, 1], [0, 0, 1, 1, 0, 0, 1, 0, 0, 0], atol=1e-12)


def test_angle_features_do_not_change_when_an_angle_history_moves_by_two_pi() -> None:
    """Started at rest at the first sample (z_0 = G y_0), a latent run over a history moved by 2 pi k
    is the latent plus G 2 pi k, which the features subtract again."""
    bank = _angle_bank()
    rng = np.random.default_rng(7)
    y = np.cumsum(rng.normal(0.0, 0.3, (2, 400, 2)), axis=1)
    u = rng.normal(size=(2, 400, 1))
    shift = np.array([2 * np.pi, -4 * np.pi])
    gains = bd.dc_gains(bank)
    decay = np.stack([np.linalg.matrix_power(bank.discretise(0.05).Ad, k) for k in range(400)])   # Ad^k

    def latent(yy: np.ndarray) -> np.ndarray:
        return bank.run(yy, u, 0.05) + np.einsum("kij,jm->mki", decay, gains @ yy[:, 0].T)

    f = bd.decoder_features(latent(y), y, u, angles=ANGLES, gains=gains)
    moved = bd.decoder_features(latent(y + shift), y + shift, u, angles=ANGLES, gains=gains)
    assert f.shape == (2, 400, bank.nz + 2 + 2 + 1)
    np.testing.assert_allclose(moved, f, atol=1e-9)
    np.testing.assert_array_equal(bd.decoder_features(latent(y), y, u), np.concatenate([latent(y), y, u], axis=-1))


def test_angle_targets_and_outputs_are_inverse() -> None:
    rng = np.random.default_rng(8)
    x = rng.uniform(-3, 3, (50, 3))
    x[:, 2] = 1.0 + rng.uniform(-3.1, 3.1, 50)           # the free angle, within its centre +- pi
    y = np.stack([x[:, 0] + rng.normal(0, 0.01, 50) + 2 * np.pi, rng.normal(size=50)], axis=1)
    scale = np.array([0.0, 0.2, 0.0])
    v = bd.decoder_targets(x, y, scale, ANGLES)
    assert v.shape == (50, 4)
    np.testing.assert_allclose(v[:, 0], x[:, 0] - y[:, 0] + 2 * np.pi, atol=1e-12)   # the wrapped deviation
    np.testing.assert_allclose(v[:, 2] ** 2 + v[:, 3] ** 2, 1.0, atol=1e-12)
    back = bd.decoder_outputs(v, y, scale, ANGLES)
    np.testing.assert_allclose(back[:, 1:], x[:, 1:], atol=1e-12)
    np.testing.assert_allclose(back[:, 0], x[:, 0] + 2 * np.pi, atol=1e-12)          # on the measurement's branch


def test_decoder_with_angles_numpy_and_casadi_agree_and_the_card_round_trips() -> None:
    bank = _angle_bank()
    rng = np.random.default_rng(9)
    sizes = [ANGLES.n_features(bank.nz, 2, 1), 7, ANGLES.n_outputs(3)]
    arrays = {f"{DECODER}/in_mean": rng.normal(size=sizes[0]), f"{DECODER}/in_std": rng.uniform(0.5, 2, sizes[0]),
              f"{DECODER}/out_mean": rng.normal(size=sizes[-1]), f"{DECODER}/out_std": rng.uniform(0.5, 2, sizes[-1]),
              bd.ASINH_SCALE: np.array([0.0, 0.1, 0.0]), **fb.bank_arrays(bank)}
    for i, (d_out, d_in) in enumerate(zip(sizes[1:], sizes[:-1])):
        arrays[f"{DECODER}/W{i}"] = rng.normal(size=(d_out, d_in)) / np.sqrt(d_in)
        arrays[f"{DECODER}/b{i}"] = rng.normal(size=d_out) * 0.1
    spec = bd.DecoderSpec.from_card({"sizes": sizes, "activation": "tanh"}, angles=ANGLES)
    z, y, u = rng.normal(size=(30, bank.nz)), rng.normal(size=(30, 2)) * 4, rng.normal(size=(30, 1))
    ref = bd.decode(spec, arrays, z, y, u)
    got = np.asarray(bd.decoder_function(spec, arrays).map(30)(z.T, y.T, u.T)).T
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    assert np.all(np.abs(ref[:, 2] - 1.0) <= np.pi)
    assert bd.Angles.from_card(ANGLES.to_card()) == ANGLES
    with pytest.raises(ValueError, match="angle output"):
        bd.Angles(outputs=(1,), measured=((0, 0),))
    with pytest.raises(ValueError, match="keys"):
        bd.Angles.from_card({"outputs": []})
    with pytest.raises(ValueError, match="angle states"):
        bd.decode(spec, {**arrays, bd.ASINH_SCALE: np.array([0.0, 0.1, 0.5])}, z, y, u)


def test_angles_of_a_plant_find_the_measured_angle_states() -> None:
    import casadi as ca

    import kklcasadi as kc

    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 1)
    plant = kc.System("arm", x, u, [x[2], -ca.sin(x[1]) + u, -x[2]], [x[1], ca.sin(x[0])],
                      [[-1, 3], [0, 6], [-2, 2]], angle_states=(0, 1), angle_outputs=(0,))
    assert bd.Angles.of(plant) == bd.Angles(outputs=(0,), measured=((1, 0),), free=((0, 1.0),))
    assert not bd.Angles.of(kc.systems.get("duffing"))
