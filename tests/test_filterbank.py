"""The filter-bank latent (exact FOH discretisation) and its decoder in numpy and CasADi."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from kklcasadi.model.variants import filterbank as fb
from kklcasadi.nets.specs import DECODER


def _bank() -> fb.FilterBank:
    return fb.FilterBank.design(1, 1, [0.3, 1.0, 5.0], [0.5, 2.0], y_resonators=[(0.3, 1.2)], clock=0.4)


def _decoder_arrays(bank: fb.FilterBank, nx: int, rng: np.random.Generator,
                    scale: np.ndarray) -> tuple[dict, dict]:
    sizes = [bank.nz + bank.ny + bank.nu, 7, 6, nx]
    arrays = {f"{DECODER}/in_mean": rng.normal(size=sizes[0]), f"{DECODER}/in_std": rng.uniform(0.5, 2, sizes[0]),
              f"{DECODER}/out_mean": rng.normal(size=nx), f"{DECODER}/out_std": rng.uniform(0.5, 2, nx),
              fb.ASINH_SCALE: scale}
    for i, (d_out, d_in) in enumerate(zip(sizes[1:], sizes[:-1])):
        arrays[f"{DECODER}/W{i}"] = rng.normal(size=(d_out, d_in)) / np.sqrt(d_in)
        arrays[f"{DECODER}/b{i}"] = rng.normal(size=d_out) * 0.1
    arrays.update(fb.bank_arrays(bank))
    return arrays, {"sizes": sizes, "activation": "tanh"}


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
    arrays, arch = _decoder_arrays(bank, 2, rng, scale)
    dec = fb.decoder_function(arrays, arch)
    feats = rng.normal(size=(50, bank.nz + 2))
    ref = fb.decode(arrays, arch, feats)
    got = np.asarray(dec.map(50)(feats[:, :bank.nz].T, feats[:, bank.nz:bank.nz + 1].T, feats[:, -1:].T)).T
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)


def test_asinh_output_round_trips() -> None:
    bank = _bank()
    rng = np.random.default_rng(3)
    scale = np.array([0.0, 0.01])
    arrays, arch = _decoder_arrays(bank, 2, rng, scale)
    plain = dict(arrays)
    plain[fb.ASINH_SCALE] = np.zeros(2)
    feats = rng.normal(size=(20, bank.nz + 2))
    v = fb.decode(plain, arch, feats)                 # the network's raw output
    x = fb.decode(arrays, arch, feats)
    np.testing.assert_array_equal(x[:, 0], v[:, 0])
    np.testing.assert_allclose(np.arcsinh(x[:, 1] / 0.01), v[:, 1], rtol=1e-12)


def test_estimate_is_bank_then_decoder() -> None:
    bank = _bank()
    rng = np.random.default_rng(4)
    arrays, arch = _decoder_arrays(bank, 2, rng, np.array([0.0, 0.5]))
    y, u = rng.normal(size=(2, 30, 1)), rng.normal(size=(2, 30, 1))
    xhat = fb.estimate(arrays, arch, y, u, 0.05)
    z = bank.run(y, u, 0.05)
    np.testing.assert_allclose(xhat, fb.decode(arrays, arch, np.concatenate([z, y, u], axis=-1)), atol=0)
    np.testing.assert_allclose(fb.estimate(arrays, arch, y[0], u[0], 0.05), xhat[0], atol=0)


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
    arrays, arch = _decoder_arrays(bank, 2, np.random.default_rng(5), np.array([0.0, -1.0]))
    with pytest.raises(ValueError, match="asinh_scale"):
        fb.decode(arrays, arch, np.zeros((1, bank.nz + 2)))


def test_observer_step_reproduces_estimate() -> None:
    bank = _bank()
    rng = np.random.default_rng(6)
    arrays, arch = _decoder_arrays(bank, 2, rng, np.array([0.0, 0.1]))
    y, u = rng.normal(size=(25, 1)), rng.normal(size=(25, 1))
    ref = fb.estimate(arrays, arch, y, u, 0.05)
    step = fb.observer_step(arrays, arch, 0.05)
    traj = step.mapaccum("traj", 24, 2)   # z and w are carried
    z_all, _, xhat = traj(np.zeros(bank.nz), u[0], y[:-1].T, y[1:].T, u[1:].T)
    np.testing.assert_allclose(np.asarray(xhat).T, ref[1:], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(z_all).T, bank.run(y, u, 0.05)[1:], atol=1e-12)
