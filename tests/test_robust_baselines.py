"""The fair baselines of issue 46.4: the tuned EKF, the augmented EKF, the particle filter over states and
parameters, and the particle filter's likelihood under each noise model."""

import casadi as ca
import numpy as np
import pytest
from scipy import stats

import kklcasadi as kc
from kklcasadi.estimators.augmented import AugmentedEKF, ParameterPF
from kklcasadi.estimators.tuned import TunedEKF, grid_search
from kklcasadi.plant import signals as sig
from kklcasadi.plant.augment import augmented, forced_rows, perturbed
from kklcasadi.plant.noise import noise_model

TRUE = np.array([1.25, 0.75])


@pytest.fixture(scope="module")
def family():
    return kc.systems.get("duffing", param_spread=0.3)


def runs(plant, seed, n=8, **kw):
    x0 = plant.sample_box(n, seed)
    inputs = [sig.make("sinusoid", amplitude=1.0, omega=w, phase=0.0) for w in np.linspace(0.7, 2.0, n)]
    return kc.simulate_batch(plant, x0, inputs, T=50.0, dt=0.05, process_std=0.1, measurement_std=0.1, seed=seed,
                             **kw)


def test_augmented_plant(family):
    aug = augmented(family, input_disturbance=True)
    assert (aug.nx, aug.n_params) == (5, 0)
    np.testing.assert_array_equal(aug.x0_box, [[-1, 1], [-1, 1], [0.7, 1.3], [0.7, 1.3], [-1, 1]])
    rng = np.random.default_rng(0)
    x, p, d, u = rng.uniform(-1, 1, (6, 2)), family.sample_params(6, 1), rng.uniform(-0.3, 0.3, (6, 1)), \
        rng.uniform(-1, 1, (6, 1))
    f = aug.f_batch(np.hstack([x, p, d]), u)
    np.testing.assert_allclose(f[:, :2], family.f_batch(x, u + d, params=p), rtol=1e-15, atol=1e-15)
    np.testing.assert_array_equal(f[:, 2:], 0.0)
    with pytest.raises(ValueError, match=r"system: expected a plant with parameters, or input_disturbance=True"):
        augmented(kc.systems.get("duffing"))


def test_perturbed_plant(family):
    assert forced_rows(family) == [1]
    plant = perturbed(family, damping=0.3, input_gain=0.7)
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    ref = kc.System("ref", x, u, [x[1], -1.1 * x[0] - 0.9 * x[0] ** 3 + 0.7 * u - 0.3 * x[1]], x[0],
                    [[-1, 1], [-1, 1]])
    rng = np.random.default_rng(1)
    xs, us = rng.uniform(-1, 1, (20, 2)), rng.uniform(-1, 1, (20, 1))
    np.testing.assert_allclose(plant.f_batch(xs, us, params=[1.1, 0.9]), ref.f_batch(xs, us), rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(perturbed(family).f_batch(xs, us), family.f_batch(xs, us))


def test_augmented_ekf_recovers_constant_parameters(family):
    data = runs(family, 2, params=TRUE)
    ekf = AugmentedEKF(family, 0.05, param_walk=0.003)
    x, p, d = ekf.split(ekf.simulate(data.t, data.y, data.u).xhat)
    assert d.shape[-1] == 0
    # the last 10 s: every trial within 0.08 of the truth (the box is +-0.3), their mean within 0.03, and the
    # state better than the nominal EKF's
    late = p[:, -200:].mean(axis=1)
    np.testing.assert_allclose(late, np.tile(TRUE, (8, 1)), atol=0.08)
    np.testing.assert_allclose(late.mean(axis=0), TRUE, atol=0.03)
    nominal = kc.metrics.smape(data.x, kc.EKF(family, 0.05).simulate(data.t, data.y, data.u).xhat).mean()
    assert kc.metrics.smape(data.x, x).mean() < 0.7 * nominal
    np.testing.assert_array_equal(ekf(data.t, data.y, data.u), x)
    # the offset-free option: a constant input disturbance of 0.3 on the nominal plant
    biased = runs(kc.systems.get("duffing"), 3, n=4)
    shifted = kc.simulate_batch(family, biased.x[:, 0], [np.asarray(b + 0.3) for b in biased.u], T=50.0, dt=0.05,
                                process_std=0.1, measurement_std=0.1, seed=3)
    with_d = AugmentedEKF(family, 0.05, param_walk=0.003, input_disturbance=True, disturbance_walk=0.003)
    _, p, d = with_d.split(with_d.simulate(shifted.t, shifted.y, biased.u).xhat)
    np.testing.assert_allclose(d[:, -200:].mean(axis=1), 0.3, atol=0.08)


def test_parameter_pf_recovers_constant_parameters(family):
    data = runs(family, 2, n=4, params=TRUE)
    pf = ParameterPF(family, 0.05, n_particles=1000, roughening=0.6, seed=0, n_threads=1)
    x, p, _ = pf.split(pf.simulate(data.t, data.y, data.u).xhat)
    np.testing.assert_allclose(p[:, -200:].mean(axis=1), np.tile(TRUE, (4, 1)), atol=0.1)
    prior = pf.prior(np.random.default_rng(0))
    assert prior.shape == (1000, 4) and np.all((prior[:, 2:] >= 0.7) & (prior[:, 2:] <= 1.3))
    # the parameters' move keeps the cloud's mean and variance
    cloud = np.random.default_rng(5).normal([0, 0, 1.0, 1.0], [0.1, 0.1, 0.05, 0.02], (200_000, 4))
    before = cloud[:, 2:].copy()
    pf.roughen(cloud, np.random.default_rng(6))
    np.testing.assert_allclose(cloud[:, 2:].mean(axis=0), before.mean(axis=0), atol=1e-3)
    np.testing.assert_allclose(cloud[:, 2:].std(axis=0), before.std(axis=0), rtol=0.01)


def test_tuned_ekf_chooses_on_tuning_trials(family):
    # a plant outside the nominal model: the EKF with the simulator's Q follows it worse than an inflated one
    corner = [1.3, 1.3]
    tuning = runs(family, 11, n=6, params=corner)
    tuned = TunedEKF.fit(family, 0.05, tuning, process_std=0.1, measurement_std=0.1)
    result = tuned.tuning
    assert result.n_trials == 6 and len(result.points) == 40
    assert tuned.q_scale == result.best["q_scale"] > 1.0
    grid = dict(zip(result.points, result.scores))
    assert result.best_score == min(result.scores) < grid[(1.0, 1.0)]
    # the chosen filter is the one scored, and it does better on other trials of the same plant
    scored = runs(family, 12, n=6, params=corner)
    again = kc.metrics.smape(tuning.x, tuned.simulate(tuning.t, tuning.y, tuning.u).xhat).mean()
    assert again == pytest.approx(result.best_score, rel=1e-12)
    nominal = kc.EKF.for_noise(family, 0.05, process_std=0.1, measurement_std=0.1)
    assert kc.metrics.smape(scored.x, tuned.simulate(scored.t, scored.y, scored.u).xhat).mean() < \
        kc.metrics.smape(scored.x, nominal.simulate(scored.t, scored.y, scored.u).xhat).mean()
    np.testing.assert_allclose(tuned.Q, np.eye(2) * (tuned.q_scale * 0.1 * 0.05) ** 2, rtol=1e-15)
    np.testing.assert_allclose(tuned.R, np.eye(1) * (tuned.r_scale * 0.1) ** 2, rtol=1e-15)
    with pytest.raises(ValueError, match=r"tuning: expected at least one trial that did not escape"):
        grid_search(lambda q: None, {"q": [1.0]}, (tuning.t, tuning.x[:0], tuning.y[:0], tuning.u[:0]))


def test_augmented_ekf_fit(family):
    tuning = runs(family, 11, n=4, params=TRUE)
    aekf = AugmentedEKF.fit(family, 0.05, tuning, q_scales=(1.0, 4.0), r_scales=(1.0,), param_walks=(0.003, 0.3))
    assert len(aekf.tuning.points) == 4 and aekf.param_walk == aekf.tuning.best["param_walk"]


@pytest.mark.parametrize("spec", ["quantised:0.2", "outliers:0.05,10+quantised:0.2"])
def test_quantised_likelihood_is_the_cells_probability(spec):
    model = noise_model(spec)
    y, h = 0.4, np.linspace(-0.5, 1.2, 35)
    lo, hi = y - 0.1, y + 0.1
    prob = 0.95 * (stats.norm.cdf(hi, h, 0.1) - stats.norm.cdf(lo, h, 0.1)) + \
        0.05 * (stats.norm.cdf(hi, h, 1.0) - stats.norm.cdf(lo, h, 1.0)) if "outliers" in spec else \
        stats.norm.cdf(hi, h, 0.1) - stats.norm.cdf(lo, h, 0.1)
    # erf's differences cancel in the far tails: the probability to 1e-15, its log where it is above 1e-9
    ys, hs = ca.SX.sym("y"), ca.SX.sym("h")
    f = ca.Function("ll", [ys, hs], [model.log_likelihood(ys, hs, 0.1)])
    for got in (model.log_likelihood(y, h, 0.1), np.asarray(f(y, h[None, :])).ravel()):
        np.testing.assert_allclose(np.exp(got), prob, rtol=0, atol=1e-15)
        np.testing.assert_allclose(got[prob > 1e-9], np.log(prob[prob > 1e-9]), rtol=1e-7)


def test_particle_filter_with_the_noise_models_likelihood():
    """Under Student-t noise with outliers, the filter that weighs by the right density beats the Gaussian one."""
    plant = kc.systems.get("duffing")
    x0 = plant.sample_box(6, 4)
    inputs = [sig.make("sinusoid", amplitude=0.5, omega=1.0, phase=p) for p in np.linspace(0, 3, 6)]
    data = kc.simulate_batch(plant, x0, inputs, T=20.0, dt=0.05, process_std=0.1, measurement_std=0.1, seed=4,
                             noise_model="student-t:2+outliers:0.05,10")
    kw = dict(n_particles=500, roughening=0.6, seed=0, n_threads=1)
    right = kc.estimators.ParticleFilter(plant, 0.05, noise_model="student-t:2+outliers:0.05,10", **kw)
    gauss = kc.estimators.ParticleFilter(plant, 0.05, **kw)
    score = [kc.metrics.smape(data.x, pf(data.t, data.y, data.u)).mean() for pf in (right, gauss)]
    assert score[0] < 0.8 * score[1]
