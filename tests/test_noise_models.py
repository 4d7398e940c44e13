"""Noise as it is (issue 46.3): each measurement-noise model's samples against its distribution, the
strings that name them, and the simulator's measurements."""

import numpy as np
import pytest
from scipy import stats

import kklcasadi as kc
from kklcasadi.plant import signals as sig
from kklcasadi.plant.noise import GAUSS, NoiseModel, noise_model

N = 200_000
ALPHA = 1e-3          # a correct sampler fails one of these KS tests once in a thousand seeds


def draws(model, std=0.1, seed=0):
    return model.sample(np.random.default_rng(seed), (N, 1), std).ravel()


@pytest.mark.parametrize("spec, cdf", [
    ("gauss", lambda v: stats.norm.cdf(v, scale=0.1)),
    ("student-t:2", lambda v: stats.t.cdf(v, 2, scale=0.1)),
    ("student-t:5", lambda v: stats.t.cdf(v, 5, scale=0.1)),
    ("outliers:0.05,10", lambda v: 0.95 * stats.norm.cdf(v, scale=0.1) + 0.05 * stats.norm.cdf(v, scale=1.0)),
    ("student-t:3+outliers:0.1,5", lambda v: 0.9 * stats.t.cdf(v, 3, scale=0.1) + 0.1 * stats.t.cdf(v, 3, scale=0.5)),
])
def test_samples_follow_their_distribution(spec, cdf):
    v = draws(noise_model(spec))
    assert stats.kstest(v, cdf).pvalue > ALPHA
    # and a wrong distribution is told apart (the test can fail)
    assert stats.kstest(v * 1.05, cdf).pvalue < ALPHA


def test_moments():
    assert abs(draws(GAUSS).std() / 0.1 - 1) < 0.01
    # Student-t with nu = 5: variance sigma^2 nu / (nu - 2)
    assert abs(draws(noise_model("student-t:5")).var() / (0.01 * 5 / 3) - 1) < 0.05
    # outliers: variance (1 - p) sigma^2 + p (k sigma)^2, and the share of large draws
    v = draws(noise_model("outliers:0.05,10"))
    assert abs(v.var() / (0.95 * 0.01 + 0.05 * 1.0) - 1) < 0.03
    share = 0.95 * 2 * stats.norm.sf(0.6 / 0.1) + 0.05 * 2 * stats.norm.sf(0.6 / 1.0)
    assert abs(np.mean(np.abs(v) > 0.6) / share - 1) < 0.1


def test_quantised_measurements():
    model = noise_model("quantised:0.2")
    clean = np.linspace(-1.0, 1.0, N)[:, None]
    y = model.measure(clean + model.sample(np.random.default_rng(1), (N, 1), 0.1))
    np.testing.assert_allclose(y / 0.2, np.round(y / 0.2), rtol=0, atol=1e-9)           # on the grid
    # the rounding error of noise-free values is uniform on [-step/2, step/2)
    err = model.measure(clean) - clean
    assert err.min() >= -0.1 - 1e-12 and err.max() <= 0.1 + 1e-12
    assert stats.kstest(err.ravel(), stats.uniform(loc=-0.1, scale=0.2).cdf).pvalue > ALPHA
    # with noise: P(y = k step | x) = Phi((k step + step/2 - x) / sigma) - Phi((k step - step/2 - x) / sigma)
    x0 = 0.03
    yq = model.measure(x0 + model.sample(np.random.default_rng(2), (N,), 0.1))
    levels = np.arange(-4, 5) * 0.2
    observed = np.array([np.sum(np.isclose(yq, c)) for c in levels])
    expected = N * (stats.norm.cdf(levels + 0.1, x0, 0.1) - stats.norm.cdf(levels - 0.1, x0, 0.1))
    assert observed.sum() == N
    assert stats.chisquare(observed, expected * N / expected.sum()).pvalue > ALPHA


def test_spelling_round_trips_and_errors():
    for spec in ["gauss", "student-t:2", "gauss+outliers:0.05,10", "student-t:3+outliers:0.1,5+quantised:0.2",
                 "gauss+quantised:0.05"]:
        assert str(noise_model(spec)) == spec
        assert noise_model(str(noise_model(spec))) == noise_model(spec)
    assert noise_model("outliers:0.05,10") == NoiseModel(outlier_p=0.05, outlier_k=10.0)
    assert noise_model(None) is GAUSS and GAUSS.gaussian and not noise_model("quantised:0.1").gaussian
    for bad, message in [("laplace", r"parts among \['gauss', 'student-t:NU'"),
                         ("student-t", r"student-t:NU \(1 number after ':'\)"),
                         ("outliers:0.1", r"outliers:P,K \(2 numbers after ':'\)"),
                         ("outliers:1.5,3", r"outliers:P,K with 0 <= P < 1 and K >= 1"),
                         ("quantised:0", r"quantised:STEP with STEP > 0"),
                         ("gauss+student-t:3", r"each part once and one base distribution"),
                         ("student-t:-1", r"student-t:NU with NU > 0")]:
        with pytest.raises(ValueError, match=r"noise_model: expected " + message):
            noise_model(bad)


def test_log_density_is_the_distributions():
    v = np.linspace(-2, 2, 41)
    for spec, pdf in [("gauss", stats.norm(scale=0.3).pdf), ("student-t:2", stats.t(2, scale=0.3).pdf),
                      ("outliers:0.1,4", lambda x: 0.9 * stats.norm.pdf(x, scale=0.3)
                       + 0.1 * stats.norm.pdf(x, scale=1.2))]:
        got = noise_model(spec).log_density(v, 0.3)
        ref = np.log(pdf(v))
        np.testing.assert_allclose(got - got[20], ref - ref[20], rtol=1e-12, atol=1e-12)


def test_simulator_measurements():
    s = kc.systems.get("duffing")
    u = sig.make("sinusoid", amplitude=0.5, omega=1.0, phase=0.0)
    kw = dict(T=50.0, dt=0.05, process_std=0.1, measurement_std=0.1, seed=4, method="rk")
    plain = kc.simulate(s, [0.3, 0.0], u, **kw)
    np.testing.assert_array_equal(kc.simulate(s, [0.3, 0.0], u, noise_model="gauss", **kw).y, plain.y)
    heavy = kc.simulate(s, [0.3, 0.0], u, noise_model="student-t:2", **kw)
    np.testing.assert_array_equal(heavy.x, plain.x)                   # the process noise is drawn first
    v = heavy.y - s.h_batch(heavy.x)
    assert stats.kstest(v.ravel(), stats.t(2, scale=0.1).cdf).pvalue > ALPHA
    q = kc.simulate(s, [0.3, 0.0], u, noise_model="quantised:0.2", **kw)
    np.testing.assert_array_equal(q.y, 0.2 * np.floor(plain.y / 0.2 + 0.5))
    # closed loop: the law reads the quantised measurement (the PD law of docs/protocol.md, in numpy)
    law = sig.PDFeedback(sig.make("constant", value=0.2), kp=1.0, kd=0.5, tau=0.2, u_max=1.0)
    loop = kc.simulate(s, [0.3, 0.0], law, noise_model="quantised:0.2", **kw)
    np.testing.assert_allclose(loop.y / 0.2, np.round(loop.y / 0.2), atol=1e-9)
    y, alpha, yf_prev = loop.y[:, 0], 1 - np.exp(-0.05 / 0.2), loop.y[0, 0]
    for k in range(len(y)):
        yf = yf_prev + alpha * (y[k] - yf_prev)
        assert loop.u[k, 0] == pytest.approx(np.clip(1.0 * (0.2 - y[k]) - 0.5 * (yf - yf_prev) / 0.05, -1, 1),
                                             abs=1e-12)
        yf_prev = yf
