"""One estimate type: the observer, the EKF, the particle filter and the MHEs return the same frozen Estimate
(their own fields set, the others None) and give a step estimator whose make_step is their simulate sample by
sample; the NMPC loop takes any of them."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.estimate import Estimate, StepEstimator, check_sample
from kklcasadi.estimators import KKLPrimedMHE, ParticleFilter
from kklcasadi.estimators.augmented import AugmentedEKF, ParameterPF
from kklcasadi.estimators.ekf import EKFEstimate, EKFEstimator
from kklcasadi.estimators.mhe import MHEEstimate, MHEStats
from kklcasadi.estimators.nmpc import NMPC, TrueState, closed_loop, steady_state
from kklcasadi.estimators.nmpc import EKFEstimator as LoopEKF
from kklcasadi.estimators.pf import PFEstimate, PFEstimator, PFStats
from kklcasadi.estimators.tuned import TunedEKF

ROOT = Path(__file__).resolve().parents[1]
DT = 0.05


@pytest.fixture(scope="module")
def record():
    plant = kc.systems.get("duffing")
    tr = kc.simulate(plant, [0.8, -0.4], kc.signals.make("square", amplitude=0.5, omega=1.0), T=1.5, dt=DT,
                     process_std=0.1, measurement_std=0.1, seed=7)
    return plant, tr


@pytest.fixture(scope="module")
def observer():
    return kc.load_observer(ROOT / "models" / "duffing" / "bank")


def _steps(estimator, tr):
    return np.array([estimator.make_step(y, u) for y, u in zip(tr.y, tr.u)])


def test_every_estimator_returns_the_one_frozen_estimate(record, observer):
    plant, tr = record
    runs = {"observer": observer.simulate(tr.t, tr.y, tr.u),
            "ekf": kc.EKF(plant, DT).simulate(tr.t, tr.y, tr.u),
            "pf": ParticleFilter(plant, DT, n_particles=100).simulate(tr.t, tr.y, tr.u),
            "mhe": kc.MHE(plant, DT, 5).simulate(tr.t[:8], tr.y[:8], tr.u[:8])}
    assert EKFEstimate is PFEstimate is MHEEstimate is kc.Estimate is Estimate
    given = {name: {f.name for f in dataclasses.fields(run) if getattr(run, f.name) is not None}
             for name, run in runs.items()}
    head = set() if observer.covariance is None else {"cov", "var"}    # a covariance head (issue 49): var its diagonal
    assert given == {"observer": {"t", "xhat", "z", "in_domain"} | head, "ekf": {"t", "xhat", "var"},
                     "pf": {"t", "xhat", "var", "stats"}, "mhe": {"t", "xhat", "stats"}}
    if head:
        cov = runs["observer"].cov
        assert cov.shape == (tr.t.size, plant.nx, plant.nx)
        np.testing.assert_array_equal(runs["observer"].var, np.diagonal(cov, axis1=-2, axis2=-1))
    assert isinstance(runs["pf"].stats, PFStats) and isinstance(runs["mhe"].stats, MHEStats)
    for run in runs.values():
        assert isinstance(run, Estimate) and run.xhat.shape == (run.t.size, plant.nx)
        with pytest.raises(dataclasses.FrozenInstanceError):
            run.xhat = None


def test_the_ekf_step_estimator_is_its_simulate_bitwise(record):
    plant, tr = record
    ekf = kc.EKF.for_noise(plant, DT, process_std=0.1, measurement_std=0.1)
    est = ekf.estimator()
    assert isinstance(est, (EKFEstimator, StepEstimator))
    run = ekf.simulate(tr.t, tr.y, tr.u)
    np.testing.assert_array_equal(_steps(est, tr), run.xhat)
    np.testing.assert_array_equal(est.stats["var"], run.var[-1])
    assert est.stats["k"] == tr.t.size
    est.reset()
    np.testing.assert_array_equal(est.make_step(tr.y[0], tr.u[0]), run.xhat[0])
    with pytest.raises(ValueError, match=r"^y: expected shape \(1,\) at sample 1, received \(2,\)"):
        est.make_step([0.0, 1.0], [0.0])
    with pytest.raises(ValueError, match=r"^u: expected finite values at sample 1"):
        est.make_step([0.0], [np.nan])
    assert est.k == 1                                            # a refused sample changes nothing


def test_the_particle_filter_step_estimator_is_its_first_trial_bitwise(record):
    plant, tr = record
    pf = ParticleFilter(plant, DT, n_particles=200, ess_threshold=0.9, roughening=0.6, seed=3)
    batch = pf.simulate(tr.t, np.stack([tr.y, tr.y + 0.05]), np.stack([tr.u, tr.u]))
    est = pf.estimator()
    np.testing.assert_array_equal(_steps(est, tr), batch.xhat[0])
    assert est.stats["ess"] == batch.stats.ess[0, -1] and np.array_equal(est.stats["var"], batch.var[0, -1])
    assert np.mean(batch.stats.ess[0] < 0.9 * 200) > 0.05                   # resampling happened on the way
    est.reset()
    np.testing.assert_array_equal(_steps(est, tr), batch.xhat[0])            # reset: the same stream again


def test_the_robustness_baselines_return_the_one_estimate_and_step_bitwise(record):
    """The tuned EKF, the augmented EKF and the particle filter over states and parameters (issue 46.4) are an
    EKF and a particle filter: the same Estimate (the augmented state where they augment) and step estimators
    that are their simulate sample by sample, the parameter filter's kernel shrinkage included."""
    _, tr = record
    family = kc.systems.get("duffing", param_spread=0.3)
    filters = {"tuned": TunedEKF(family, DT, process_std=0.1, measurement_std=0.1, q_scale=4.0, r_scale=0.5),
               "augmented": AugmentedEKF(family, DT, param_walk=0.01, input_disturbance=True),
               "parameter_pf": ParameterPF(family, DT, n_particles=200, ess_threshold=0.9, roughening=0.3, seed=5)}
    n_states = {"tuned": 2, "augmented": 5, "parameter_pf": 4}
    for name, flt in filters.items():
        run = flt.simulate(tr.t, tr.y, tr.u)
        assert isinstance(run, Estimate) and run.xhat.shape == (tr.t.size, n_states[name]), name
        assert run.var is not None and run.var.shape == run.xhat.shape and run.z is None, name
        est = flt.estimator()
        inner = est.inner if name != "tuned" else est
        assert isinstance(est, StepEstimator) and isinstance(inner, PFEstimator if name == "parameter_pf"
                                                             else EKFEstimator), name
        if name == "tuned":
            np.testing.assert_array_equal(_steps(est, tr), run.xhat, err_msg=name)
            np.testing.assert_array_equal(est.stats["var"], run.var[-1], err_msg=name)
            continue
        # the augmented filters' step estimators give the plant's states (what a control loop takes), the
        # parameters and the disturbance beside them: bitwise the parts of their simulate
        x, p, d = flt.split(run.xhat)
        assert est.augmented is None and est.params is None and est.k == 0
        np.testing.assert_array_equal(_steps(est, tr), x, err_msg=name)
        np.testing.assert_array_equal(est.augmented, run.xhat[-1], err_msg=name)
        np.testing.assert_array_equal(est.params, p[-1], err_msg=name)
        np.testing.assert_array_equal(est.disturbance, d[-1], err_msg=name)
        np.testing.assert_array_equal(est.stats["var"], run.var[-1, :2], err_msg=name)
        np.testing.assert_array_equal(est.stats["var_augmented"], run.var[-1], err_msg=name)
        assert est.k == tr.t.size
        if name == "augmented":
            P = est.inner.cov
            assert P.shape == (5, 5) and np.array_equal(est.cov, P[:2, :2])
        else:
            assert not hasattr(est, "cov")                      # the particle filter reports no covariance
        est.reset()
        assert est.augmented is None and est.k == 0
        np.testing.assert_array_equal(_steps(est, tr), x, err_msg=name)       # reset: the same estimates again
    pf_run = filters["parameter_pf"].simulate(tr.t, tr.y, tr.u)
    assert isinstance(pf_run.stats, PFStats) and np.mean(pf_run.stats.ess < 0.9 * 200) > 0.05   # resampled
    x, _, _ = filters["augmented"].split(filters["augmented"].simulate(tr.t, tr.y, tr.u).xhat)
    np.testing.assert_array_equal(filters["augmented"](tr.t, tr.y[None], tr.u[None])[0], x)


def test_the_mhe_step_estimators_are_their_simulate(record, observer):
    plant, tr = record
    n = 12
    t, y, u = tr.t[:n], tr.y[:n], tr.u[:n]
    mhe = kc.MHE(plant, DT, 4)
    run = mhe.simulate(t, y, u)
    est = mhe.estimator()
    np.testing.assert_array_equal(_steps(est, kc.Trajectory(t, None, u, y)), run.xhat)        # bitwise
    assert est.stats["k"] == n and est.stats["failed"] == run.stats.n_failed
    primed = KKLPrimedMHE(observer, np.full(plant.nx, 0.2), 3)
    guided = primed.simulate(t, y, u)
    live = primed.estimator()
    # the observer's step one sample at a time equals its simulate to rounding, and so does the guided MHE
    np.testing.assert_allclose(_steps(live, kc.Trajectory(t, None, u, y)), guided.xhat, rtol=0, atol=1e-7)


def test_the_nmpc_loop_takes_any_estimator(observer):
    plant = kc.systems.get("duffing")
    target = steady_state(plant, 0.5)
    x0 = [0.2, 0.0]

    def loop(estimator):
        return closed_loop(NMPC(plant, DT, 5), estimator, lambda _t: target, x0, 0.5, seed=3)

    ekf = kc.EKF(plant, DT)
    reference = loop(LoopEKF(plant, DT))                    # the NMPC examples' name: EKF(plant, dt).estimator()
    for estimator in (ekf, ekf.estimator()):
        run = loop(estimator)
        np.testing.assert_array_equal(run.xhat, reference.xhat)
        np.testing.assert_array_equal(run.u, reference.u)
    used = ekf.estimator()
    used.make_step([1.0], [0.0])
    np.testing.assert_array_equal(loop(used).xhat, reference.xhat)           # the loop resets it first
    family = kc.systems.get("duffing", param_spread=0.3)
    augmented_filters = (AugmentedEKF(family, DT, input_disturbance=True),
                         ParameterPF(family, DT, n_particles=100, seed=2))
    for estimator in (observer, ParticleFilter(plant, DT, n_particles=100), kc.MHE(plant, DT, 3), TrueState(),
                      *augmented_filters):
        run = loop(estimator)
        assert run.xhat.shape == (10, 2) and np.all(np.isfinite(run.xhat)) and np.all(np.isfinite(run.u))
        assert run.estimation_rmse < 0.5
    with pytest.raises(TypeError, match="estimator: expected an object with make_step"):
        loop(object())


def test_check_sample_names_the_argument_and_the_sample():
    np.testing.assert_array_equal(check_sample(2.0, "y", 1, 0), [2.0])
    with pytest.raises(ValueError, match=r"^u: expected shape \(2,\) at sample 5, received \(3,\)"):
        check_sample([1, 2, 3], "u", 2, 5)
