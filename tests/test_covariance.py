"""The covariance head of a bank decoder: the map (numpy, CasADi), its likelihood fit and its calibration."""

import casadi as ca
import numpy as np
import pytest

from kklcasadi.model.variants import covariance as cov
from kklcasadi.nets.specs import MLPSpec

torch = pytest.importorskip("torch")
from kklcasadi.train.config import LoopConfig  # noqa: E402
from kklcasadi.train.covariance import CovarianceConfig, calibrate, fit_covariance, gaussian_nll  # noqa: E402


def _head(nx, d, rng, hidden=5):
    spec = MLPSpec((d, hidden, cov.n_entries(nx)), "tanh")
    arrays = {f"covariance/{k}": v for k, v in {
        "in_mean": rng.normal(size=d), "in_std": rng.uniform(0.5, 2, d), "out_mean": rng.normal(size=spec.n_out),
        "out_std": rng.uniform(0.5, 2, spec.n_out), "W0": rng.normal(size=(hidden, d)), "b0": rng.normal(size=hidden),
        "W1": rng.normal(size=(spec.n_out, hidden)), "b1": rng.normal(size=spec.n_out)}.items()}
    arrays[cov.SCALE] = rng.uniform(0.5, 2, nx)
    return spec, arrays


def test_factor_layout_by_hand():
    q = np.array([np.log(2.0), np.log(3.0), 0.5])
    np.testing.assert_allclose(cov.factor(q, 2), [[2.0, 0.0], [0.5, 3.0]])
    q3 = np.array([0.0, 0.0, 0.0, 1.0, 2.0, 3.0])                   # below the diagonal: L10, L20, L21
    np.testing.assert_allclose(cov.factor(q3, 3), [[1, 0, 0], [1, 1, 0], [2, 3, 1]])
    assert cov.n_entries(3) == 6


@pytest.mark.parametrize("nx", [1, 2, 3])
def test_numpy_and_casadi_covariances_agree_and_are_positive_definite(nx):
    rng = np.random.default_rng(nx)
    d = 4
    spec, arrays = _head(nx, d, rng)
    out_std = rng.uniform(0.5, 2, nx)
    asinh = np.zeros(nx)
    asinh[-1] = 0.01 if nx > 1 else 0.0                              # one state decoded as s sinh(v)
    f, xhat = rng.normal(size=(7, d)), rng.normal(size=(7, nx))
    P = cov.covariance_numpy(spec, arrays, f, xhat, out_std, asinh)
    assert P.shape == (7, nx, nx)
    np.testing.assert_allclose(P, np.swapaxes(P, -1, -2), rtol=0, atol=0)
    assert np.all(np.linalg.eigvalsh(P) > 0)
    fs, xs = ca.MX.sym("f", d), ca.MX.sym("xhat", nx)
    fun = ca.Function("P", [fs, xs], [cov.covariance_expression(spec, arrays, fs, xs, out_std, asinh)])
    for k in range(7):
        np.testing.assert_allclose(np.array(fun(f[k], xhat[k])), P[k], rtol=1e-13, atol=1e-300)
    # through xhat = s sinh(v): xhat +- 2 sd is as wide as the image of v +- 2 sigma_v (sigma_v the variance of the
    # state decoded as v, calibrated: plain / scale^2), calibrated by the state's factor; the others unchanged
    if nx > 1:
        plain = cov.covariance_numpy(spec, arrays, f, xhat, out_std, np.zeros(nx))
        np.testing.assert_array_equal(P[:, :-1, :-1], plain[:, :-1, :-1])
        vv, scale = np.arcsinh(xhat[:, -1] / 0.01), arrays[cov.SCALE][-1]
        sigma = np.sqrt(plain[:, -1, -1]) / scale
        image = 0.01 * (np.sinh(vv + 2 * sigma) - np.sinh(vv - 2 * sigma))
        np.testing.assert_allclose(4 * np.sqrt(P[:, -1, -1]), scale * image, rtol=1e-12)
        assert np.all(P[:, -1, -1] > plain[:, -1, -1] * (0.01 * np.cosh(vv)) ** 2)    # wider than the delta method


def test_the_likelihood_is_the_gaussian_one():
    q = torch.tensor([[np.log(2.0), np.log(3.0), 0.5]], dtype=torch.float64)
    r = torch.tensor([[1.0, -1.0]], dtype=torch.float64)
    L = np.array([[2.0, 0.0], [0.5, 3.0]])
    P = L @ L.T
    e = np.array([1.0, -1.0])
    expected = 0.5 * e @ np.linalg.solve(P, e) + 0.5 * np.log(np.linalg.det(P))
    assert float(gaussian_nll(q, r)) == pytest.approx(expected, rel=1e-12)


def test_the_head_learns_a_covariance_that_depends_on_the_features():
    """Errors drawn with a known covariance that depends on the feature: std of state 0 is 0.1 exp(f0),
    state 1 correlated with it at 0.6 and half its scale. The fit recovers the stds within 8 % and the
    correlation within 0.08."""
    rng = np.random.default_rng(0)
    n = 20000
    f = rng.uniform(-1, 1, size=(n, 3))
    s0 = 0.1 * np.exp(f[:, 0])
    e0 = rng.normal(size=n)
    e1 = 0.6 * e0 + 0.8 * rng.normal(size=n)
    r = np.stack([s0 * e0, 0.5 * s0 * e1], axis=1)
    config = CovarianceConfig(hidden=(16,), loop=LoopConfig(epochs=15, batch_size=1024, lr=1e-2, schedule="cosine",
                                                           val_fraction=0.05), dtype="float64")
    fit = fit_covariance(f, r, config, seed=0)
    spec = MLPSpec.from_card(fit.arch, "architecture", "covariance")
    test = np.array([[0.0, 0.3, -0.2], [0.7, 0.0, 0.5], [-0.6, -0.7, 0.0]])
    P = cov.covariance_numpy(spec, fit.arrays, test, np.zeros((3, 2)), np.ones(2), np.zeros(2))
    std0 = 0.1 * np.exp(test[:, 0])
    np.testing.assert_allclose(np.sqrt(P[:, 0, 0]), std0, rtol=0.08)
    np.testing.assert_allclose(np.sqrt(P[:, 1, 1]), 0.5 * std0, rtol=0.08)
    np.testing.assert_allclose(P[:, 0, 1] / np.sqrt(P[:, 0, 0] * P[:, 1, 1]), 0.6, atol=0.08)
    # calibration on fresh samples of the same law: factors near 1; on errors twice as large: near 2
    fresh = rng.uniform(-1, 1, size=(n, 3))
    e0 = rng.normal(size=n)
    s0 = 0.1 * np.exp(fresh[:, 0])
    errors = np.stack([s0 * e0, 0.5 * s0 * (0.6 * e0 + 0.8 * rng.normal(size=n))], axis=1)
    xhat = np.zeros((n, 2))
    scale = calibrate(fit.arrays, fit.arch, fresh, xhat, errors, np.ones(2), np.zeros(2))
    np.testing.assert_allclose(scale, 1.0, atol=0.06)
    np.testing.assert_allclose(calibrate(fit.arrays, fit.arch, fresh, xhat, 2 * errors, np.ones(2), np.zeros(2)),
                               2 * scale, rtol=1e-12)
