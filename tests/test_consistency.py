"""kklcasadi.consistency: NEES, coverage and likelihood against hand computations and a Gaussian sample."""

import numpy as np
import pytest
import scipy.stats

from kklcasadi import consistency as cs


def test_nees_by_hand_diagonal_and_full():
    x, xhat = np.array([1.0, 2.0]), np.zeros(2)
    assert cs.nees(x, xhat, np.array([1.0, 4.0])) == pytest.approx(1.0 + 1.0, rel=1e-14)
    P = np.array([[2.0, 1.0], [1.0, 2.0]])                       # P^-1 = [[2, -1], [-1, 2]] / 3
    assert cs.nees(np.array([1.0, 0.0]), xhat, P) == pytest.approx(2.0 / 3.0, rel=1e-14)
    assert cs.nees(np.array([1.0, 1.0]), xhat, P) == pytest.approx(2.0 / 3.0, rel=1e-14)   # (2 - 2 + 2) / 3


def test_log_likelihood_is_the_gaussian_density():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(3)
    x, xhat = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    expected = [scipy.stats.multivariate_normal(xhat[i], P[i]).logpdf(x[i]) for i in range(5)]
    np.testing.assert_allclose(cs.log_likelihood(x, xhat, P), expected, rtol=1e-12)
    # one state: -0.5 (e^2 / s^2 + log s^2 + log 2 pi)
    assert cs.log_likelihood(np.array([1.0]), np.array([0.0]), np.array([4.0])) == pytest.approx(
        -0.5 * (0.25 + np.log(4.0) + np.log(2 * np.pi)), rel=1e-14)


def test_coverage_by_hand():
    x = np.array([[0.5, 0.0], [1.5, 0.0], [2.5, 0.0]])
    xhat = np.zeros_like(x)
    var = np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0]])
    np.testing.assert_allclose(cs.coverage(x, xhat, var, 1.0), [1 / 3, 1.0])
    np.testing.assert_allclose(cs.coverage(x, xhat, var, 2.0), [2 / 3, 1.0])
    full = np.broadcast_to(np.diag([1.0, 1.0]), (3, 2, 2))
    np.testing.assert_allclose(cs.coverage(x, xhat, full, 2.0), [2 / 3, 1.0])


def test_angle_errors_are_wrapped():
    x, xhat = np.array([np.pi - 0.1]), np.array([-np.pi + 0.1])      # 0.2 apart on the circle
    assert cs.nees(x, xhat, np.array([0.04]), angles=[0]) == pytest.approx(1.0, rel=1e-12)
    assert cs.nees(x, xhat, np.array([0.04])) == pytest.approx((2 * np.pi - 0.2) ** 2 / 0.04, rel=1e-12)


def test_nees_band_is_the_chi_square_quantile_of_the_mean():
    lo, hi = cs.nees_band(1, 1)
    assert (lo, hi) == pytest.approx((scipy.stats.chi2.ppf(0.025, 1), scipy.stats.chi2.ppf(0.975, 1)), rel=1e-12)
    lo, hi = cs.nees_band(100, 2)                                  # Bar-Shalom's band for 100 runs of 2 states
    assert lo == pytest.approx(1.6, abs=0.05) and hi == pytest.approx(2.4, abs=0.05)
    with pytest.raises(ValueError, match="n: expected a positive integer"):
        cs.nees_band(0, 2)


@pytest.mark.parametrize("scale, consistent", [(1.0, True), (2.0, False)])
def test_a_gaussian_error_of_the_stated_covariance_is_consistent(scale, consistent):
    rng = np.random.default_rng(1)
    m, n = 100, 400
    A = np.array([[1.0, 0.0], [0.8, 0.5]])
    P = A @ A.T                                                     # correlated states
    e = rng.normal(size=(m, n, 2)) @ A.T
    x = rng.normal(size=(m, n, 2))
    result = cs.consistency(x, x - e, np.broadcast_to(scale * P, (m, n, 2, 2)))
    assert result.nees == pytest.approx(2.0 / scale, rel=0.02)
    assert result.nees_in_band is consistent
    if consistent:
        assert result.in_band == pytest.approx(0.95, abs=0.03)
        for level, expected in zip(result.coverage, cs.GAUSSIAN_COVERAGE):
            np.testing.assert_allclose(level, expected, atol=0.01)
        assert result.log_likelihood == pytest.approx(
            -0.5 * (2.0 + np.log(np.linalg.det(P)) + 2 * np.log(2 * np.pi)), abs=0.02)
    else:
        assert result.in_band < 0.01
    record = result.to_json()
    assert record["coverage"]["2sigma"] == list(result.coverage[1]) and record["trials"] == m


def test_settle_time_and_bad_input():
    x = np.zeros((2, 4, 1))
    var = np.ones((2, 4, 1))
    xhat = x.copy()
    xhat[:, :2] = 10.0                                              # the transient: far off
    settled = cs.consistency(x, xhat, var, t=np.arange(4.0), t_settle=2.0)
    assert settled.nees == 0.0 and settled.samples == 2
    assert cs.consistency(x, xhat, var).nees == pytest.approx(50.0)
    with pytest.raises(ValueError, match="cov: expected finite variances > 0"):
        cs.nees(x, xhat, np.zeros_like(var))
    with pytest.raises(ValueError, match="cov: expected covariances of shape"):
        cs.nees(x, xhat, np.ones((2, 4, 3)))
    with pytest.raises(ValueError, match="cov: expected positive definite covariances"):
        cs.nees(np.zeros(2), np.ones(2), np.array([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(ValueError, match="xhat: expected the shape of x_true"):
        cs.nees(x, xhat[:, :3], var)
