import json
import shutil

import casadi as ca
import numpy as np
import pytest
from scipy.linalg import expm

import kklcasadi
import kklcasadi as kc
from kklcasadi.estimate import Estimate
from kklcasadi.estimators.ekf import EKF
from kklcasadi.estimators.pf import ROUGHENING, ParticleFilter, PFEstimate, PFStats
from kklcasadi.evaluation.protocol import Protocol, evaluate
from kklcasadi.plant import signals as sig
from kklcasadi.plant.simulate import step_function

DT = 0.05


def kalman_filter(F, G, H, dt, q, r, x0, P0, y, u):
    """Exact KF for ``xdot = F x + G u + w`` (u and w held per interval, w ~ N(0, q^2 I)), ``y = H x + v``.

    Discretised with one matrix exponential: ``expm([[F, G, I], [0, 0, 0]] dt)`` holds ``Ad``, ``Bd``
    and ``Gw = int_0^dt expm(F s) ds``, so ``x+ = Ad x + Bd u + Gw w`` and ``Qd = q^2 Gw Gw^T``.
    Returns the filtered means and the diagonals of the filtered covariances, each (N, nx).
    """
    nx, nu = G.shape
    aug = np.zeros((2 * nx + nu, 2 * nx + nu))
    aug[:nx, :nx], aug[:nx, nx:nx + nu], aug[:nx, nx + nu:] = F, G, np.eye(nx)
    E = expm(aug * dt)
    Ad, Bd, Gw = E[:nx, :nx], E[:nx, nx:nx + nu], E[:nx, nx + nu:]
    Qd, R = q ** 2 * Gw @ Gw.T, r ** 2 * np.eye(H.shape[0])
    x, P = np.array(x0, float), np.array(P0, float)
    means, variances = [], []
    for k in range(len(y)):
        if k:
            x, P = Ad @ x + Bd @ u[k - 1], Ad @ P @ Ad.T + Qd
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        x = x + K @ (y[k] - H @ x)
        I_KH = np.eye(nx) - K @ H
        P = I_KH @ P @ I_KH.T + K @ R @ K.T
        means.append(x)
        variances.append(np.diag(P).copy())
    return np.array(means), np.array(variances)


def test_pf_on_a_linear_gaussian_plant_is_the_kalman_filter_to_monte_carlo_error():
    """16 independent PF runs (one per trial stream) on the same record against the exact KF.

    Errors are in units of the KF's posterior std. The runs' own spread ``sigma`` (about 1/sqrt(ESS),
    0.05 here) sets the tolerance: the mean of the 16 runs must sit within 2 sigma / sqrt(16) of
    the KF (RMS over time and states), and so must the variance ratio within 2x its own standard
    error. Measured: bias 0.7 standard errors, variance ratio 1.0002; a PF with 1.5x the process
    noise misses by 0.23 sigma (16 of its standard errors) and its variance ratio is 1.66.
    """
    s = kc.systems.get("linear")
    F, G, H = kc.systems.LINEAR_F, kc.systems.LINEAR_G, kc.systems.LINEAR_H
    q, r, runs = 0.3, 0.1, 16
    m0, P0 = np.array([0.5, -0.3]), np.array([[0.04, 0.01], [0.01, 0.09]])
    tr = kc.simulate(s, [0.6, -0.1], sig.make("sinusoid", amplitude=0.5, omega=1.5, phase=0.0), T=10.0, dt=DT,
                     process_std=q, measurement_std=r, seed=5, method="rk")
    mean_kf, var_kf = kalman_filter(F, G, H, DT, q, r, m0, P0, tr.y, tr.u)
    pf = ParticleFilter(s, DT, n_particles=2000, process_std=q, measurement_std=r, x0_mean=m0, x0_cov=P0,
                        substeps=2)
    est = pf.simulate(tr.t, np.tile(tr.y, (runs, 1, 1)), np.tile(tr.u, (runs, 1, 1)))
    z = (est.xhat - mean_kf) / np.sqrt(var_kf)                         # (runs, N, nx)
    sigma = np.sqrt(np.mean(np.var(z, axis=0, ddof=1)))
    assert 0.01 < sigma < 0.1                                          # independent runs, ESS ~ 1400
    bias = np.sqrt(np.mean(z.mean(axis=0) ** 2))
    assert bias < 2 * sigma / np.sqrt(runs)
    ratio = est.var / var_kf
    ratio_se = np.sqrt(np.mean(np.var(ratio, axis=0, ddof=1))) / np.sqrt(runs)
    assert np.sqrt(np.mean((ratio.mean(axis=0) - 1) ** 2)) < 2 * ratio_se
    assert abs(ratio.mean() - 1) < 0.02


def test_pf_on_duffing_benchmark_trials_is_close_to_the_ekf():
    """Noisy protocol trials (first 4 of the sinusoid cell): SMAPE of PF (1000 particles) vs EKF.

    Measured here: PF / EKF = 1.019 on the mean, 1.006-1.048 per trial (Monte-Carlo noise of 1000
    particles); benchmarks/pf_vs_ekf.py on 100 trials per cell: 1.0006-1.0028.
    """
    s = kc.systems.get("duffing")
    batch = Protocol(n_trials=4).trials(s, "sinusoid")
    smape_pf = kc.metrics.smape(batch.x, ParticleFilter(s, DT)(batch.t, batch.y, batch.u))
    smape_ekf = kc.metrics.smape(batch.x, EKF(s, DT).simulate(batch.t, batch.y, batch.u).xhat)
    assert abs(smape_pf.mean() / smape_ekf.mean() - 1) < 0.03
    np.testing.assert_allclose(smape_pf, smape_ekf, rtol=0.06)


def test_roughening_keeps_the_filter_level_with_the_ekf_at_low_noise():
    """Roessler at noise 0.05 (4 trials from the X0 box, zero input, 30 s): the resampled copies of
    1000 particles stay together and the plain bootstrap filter loses the state; roughening
    (:data:`kklcasadi.estimators.pf.ROUGHENING`) keeps it at the EKF's SMAPE.

    Measured: PF / EKF 0.976 with roughening 0.6, 3.68 without (docs/protocol.md, "Estimators").
    """
    s, noise = kc.systems.get("rossler"), 0.05
    b = kc.simulate_batch(s, s.sample_box(4, 3), sig.make("zero"), T=30.0, dt=DT, process_std=noise,
                          measurement_std=noise, seed=4, method="rk")
    ekf = EKF(s, DT, Q=np.eye(3) * (noise * DT) ** 2, R=np.eye(1) * noise ** 2)
    ekf_smape = kc.metrics.smape(b.x, ekf.simulate(b.t, b.y, b.u).xhat).mean()

    def ratio(roughening):
        pf = ParticleFilter(s, DT, process_std=noise, measurement_std=noise, substeps=4, roughening=roughening)
        return kc.metrics.smape(b.x, pf(b.t, b.y, b.u)).mean() / ekf_smape

    assert ratio(ROUGHENING) < 1.1
    assert ratio(0.0) > 1.5


@pytest.fixture(scope="module")
def duffing_record():
    s = kc.systems.get("duffing")
    b = kc.simulate_batch(s, s.sample_box(3, 1), sig.make("sinusoid", amplitude=0.5, omega=1.0, phase=0.3),
                          T=3.0, dt=DT, process_std=0.1, measurement_std=0.1, seed=2, method="rk")
    return s, b


@pytest.mark.parametrize("roughening", [0.0, 0.6])
def test_same_seed_same_estimates_and_trials_are_independent_of_the_batch(duffing_record, roughening):
    s, b = duffing_record
    pf = ParticleFilter(s, DT, n_particles=300, ess_threshold=0.9, roughening=roughening)
    first = pf.simulate(b.t, b.y, b.u)
    again = ParticleFilter(s, DT, n_particles=300, ess_threshold=0.9, roughening=roughening).simulate(b.t, b.y, b.u)
    for name in ("xhat", "var"):
        np.testing.assert_array_equal(getattr(first, name), getattr(again, name))
        np.testing.assert_array_equal(getattr(pf.simulate(b.t, b.y, b.u), name), getattr(first, name))
    np.testing.assert_array_equal(first.stats.ess, again.stats.ess)
    prefix = pf.simulate(b.t, b.y[:2], b.u[:2])
    np.testing.assert_array_equal(prefix.xhat, first.xhat[:2])
    single = pf.simulate(b.t, b.y[0], b.u[0])
    np.testing.assert_array_equal(single.xhat, first.xhat[0])
    other = ParticleFilter(s, DT, n_particles=300, ess_threshold=0.9, roughening=roughening,
                           seed=1).simulate(b.t, b.y, b.u)
    assert not np.array_equal(other.xhat, first.xhat)
    assert np.abs(other.xhat - first.xhat).mean() < 0.05               # the same posterior, Monte-Carlo apart
    assert not np.array_equal(first.xhat[0], first.xhat[1])            # distinct trials, distinct streams


@pytest.mark.parametrize("resample", ["systematic", "stratified", "multinomial"])
def test_compiled_step_is_bitwise_the_casadi_vm(duffing_record, resample):
    s, b = duffing_record
    opts = dict(n_particles=200, resample=resample, ess_threshold=0.8)
    jit, vm = ParticleFilter(s, DT, **opts), ParticleFilter(s, DT, jit=False, **opts)
    assert jit.jit and not vm.jit
    a, c = jit.simulate(b.t, b.y, b.u), vm.simulate(b.t, b.y, b.u)
    np.testing.assert_array_equal(a.xhat, c.xhat)
    np.testing.assert_array_equal(a.stats.ess, c.stats.ess)
    assert np.mean(a.stats.ess < 0.8 * 200) > 0.05                            # resampling happened


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")
def test_the_compiled_path_is_bitwise_the_jit_on_any_thread_count(duffing_record, tmp_path):
    """The evaluation's compiler (a cached library) instead of the jit, the trials on 2 threads: the same bits."""
    from kklcasadi.evaluation.compiled import Compiler, pf_estimator

    s, b = duffing_record
    opts = dict(n_particles=200, ess_threshold=0.8)
    jit = ParticleFilter(s, DT, n_threads=1, **opts)
    compiled = pf_estimator(s, DT, compiler=Compiler(cache_dir=tmp_path), n_threads=2, **opts)
    assert jit.jit and not compiled.jit and compiled.compile is not None
    assert sorted(p.suffix for p in tmp_path.glob("pf_duffing_n200_*")) == [".c", ".c", ".so", ".so"]
    a, c = jit.simulate(b.t, b.y, b.u), compiled.simulate(b.t, b.y, b.u)
    for name in ("xhat", "var"):
        np.testing.assert_array_equal(getattr(a, name), getattr(c, name))
    np.testing.assert_array_equal(a.stats.ess, c.stats.ess)
    cached = pf_estimator(s, DT, compiler=Compiler(cache_dir=tmp_path), **opts)     # from the library cache
    np.testing.assert_array_equal(cached(b.t, b.y, b.u), a.xhat)
    np.testing.assert_array_equal(pf_estimator(s, DT, compiler=None, **opts)(b.t, b.y, b.u), a.xhat)


def test_evaluate_scores_the_pf_on_the_noisy_cells(model_dir_factory, capsys, tmp_path):
    from kklcasadi.cli import main

    model = str(model_dir_factory("autonomous"))
    assert main(["evaluate", model, "--trials", "2", "--kinds", "zero", "--pf", "50", "--ekf", "--profile",
                 "--out", str(tmp_path)]) == 0
    assert {p.name for p in tmp_path.iterdir()} >= {"duffing_smape_clean.png", "duffing_smape_noisy.png"}
    captured = capsys.readouterr()
    rows = {line.split("|")[1].strip(): line.split("|")[2:4] for line in captured.out.splitlines()
            if line.startswith("| duffing")}
    assert rows["duffing PF N=50"][0].strip() == "" and float(rows["duffing PF N=50"][1]) > 0   # noisy only
    assert "| estimate |" in captured.err and "| total |" in captured.err and "load average" in captured.err
    assert main(["evaluate", model, "--trials", "1", "--noise", "off", "--pf", "50"]) == 2
    assert "--pf: the particle filter runs on the noisy cells only" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["evaluate", model, "--trials", "1", "--pf", "50", "--pf-roughening", "-1"])
    assert "--pf-roughening" in capsys.readouterr().err


def test_shapes_and_the_protocol_estimator(duffing_record):
    s, b = duffing_record
    pf = ParticleFilter(s, DT, n_particles=100)
    est = pf.simulate(b.t, b.y, b.u)
    assert isinstance(est, Estimate) and PFEstimate is Estimate and isinstance(est.stats, PFStats)
    assert est.z is None and est.in_domain is None
    assert est.xhat.shape == est.var.shape == (3, b.t.size, 2) and est.stats.ess.shape == (3, b.t.size)
    assert np.all(est.var > 0) and np.all((est.stats.ess >= 1 - 1e-9) & (est.stats.ess <= 100 + 1e-9))
    one = pf.simulate(b.t, b.y[0], b.u[0])
    assert one.xhat.shape == one.var.shape == (b.t.size, 2) and one.stats.ess.shape == (b.t.size,)
    short = pf.simulate(b.t[:1], b.y[:, :1], b.u[:, :1])
    assert short.xhat.shape == (3, 1, 2)
    empty = pf.simulate(b.t, b.y[:0], b.u[:0])
    assert empty.xhat.shape == (0, b.t.size, 2) and empty.stats.ess.shape == (0, b.t.size)
    np.testing.assert_array_equal(pf(b.t, b.y, b.u), est.xhat)
    assert kklcasadi.estimators.ParticleFilter is ParticleFilter
    cells = evaluate(pf, s, Protocol(n_trials=2, T=6.0), kinds=["zero"])
    assert cells[0].smape.shape == (2,) and np.all(np.isfinite(cells[0].smape))


def test_priors():
    s = kc.systems.get("vdp")
    rng = np.random.default_rng(0)
    box = ParticleFilter(s, DT, n_particles=20000).prior(rng)
    assert box.shape == (20000, 2) and np.all((box >= -3) & (box <= 3))
    np.testing.assert_allclose(box.var(axis=0), 36 / 12, rtol=0.03)
    mean, cov = np.array([1.0, -2.0]), np.array([[0.5, 0.2], [0.2, 0.3]])
    gauss = ParticleFilter(s, DT, n_particles=20000, x0_mean=mean, x0_cov=cov).prior(rng)
    np.testing.assert_allclose(gauss.mean(axis=0), mean, atol=0.03)
    np.testing.assert_allclose(np.cov(gauss.T), cov, atol=0.02)
    degenerate = ParticleFilter(s, DT, n_particles=10, x0_mean=mean, x0_cov=np.diag([0.0, 1.0])).prior(rng)
    np.testing.assert_allclose(degenerate[:, 0], 1.0, atol=1e-12)


@pytest.mark.parametrize("resample", ["systematic", "stratified", "multinomial"])
def test_resampling_keeps_the_weights_in_expectation(resample):
    s = kc.systems.get("duffing")
    pf = ParticleFilter(s, DT, n_particles=50, resample=resample)
    weights = np.random.default_rng(3).dirichlet(np.full(50, 0.3))
    weights[[7, 30, 49]] = 0.0                                         # dead particles, the last among them
    weights /= weights.sum()
    rng = np.random.default_rng(4)
    picks = [pf.resample_indices(weights, rng) for _ in range(2000)]
    assert all(np.all(np.diff(p) >= 0) for p in picks)
    counts = np.array([np.bincount(p, minlength=50) for p in picks])
    assert np.all(counts.sum(axis=1) == 50) and not counts[:, [7, 30, 49]].any()
    np.testing.assert_allclose(counts.mean(axis=0), 50 * weights, atol=0.35)
    if resample == "systematic":                                       # floor or ceil of N w_i copies
        assert np.all(np.abs(counts - 50 * weights) < 1 + 1e-9)


def test_diverging_particles_are_dropped():
    """``xdot = -x^3``, one RK4 step per dt = 0.5: particles from |x| > 2.2 diverge to NaN within 6 steps.

    Without resampling every particle drawn there propagates to inf/NaN; they must get weight 0.
    """
    x, u = ca.SX.sym("x"), ca.SX.sym("u")
    wide = kc.System("cubic", x, u, [-x ** 3 + u], x, [[-3.0, 3.0]])
    plant = step_function(wide, 0.5, "rk", substeps=1)
    far = 2.2
    for _ in range(6):
        far = float(plant(far, [0.0, 0.0]))
    assert not np.isfinite(far)
    tr = kc.simulate(wide, [0.3], sig.make("zero"), T=20.0, dt=0.5, measurement_std=0.05, seed=0, method="rk")
    opts = dict(n_particles=500, process_std=0.01, measurement_std=0.05, ess_threshold=0.0)
    est = ParticleFilter(wide, 0.5, **opts).simulate(tr.t, tr.y, tr.u)
    assert np.all(np.isfinite(est.xhat)) and np.abs(est.xhat - tr.x).max() < 0.1
    outside = kc.System("cubic", x, u, [-x ** 3 + u], x, [[2.5, 3.0]])
    lost = ParticleFilter(outside, 0.5, **opts).simulate(tr.t, tr.y, tr.u)
    assert np.all(np.isfinite(lost.xhat[0])) and np.all(np.isnan(lost.xhat[-1]))


S = kc.systems.get("duffing")


@pytest.mark.parametrize("kwargs, kind, message", [
    (dict(system="duffing"), TypeError, "system: expected a kklcasadi.System, received str"),
    (dict(dt=0.0), ValueError, "dt: expected a finite number > 0"),
    (dict(n_particles=0), ValueError, "n_particles: expected a positive int, received 0"),
    (dict(n_particles=10.0), TypeError, "n_particles: expected a positive int"),
    (dict(process_std=-0.1), ValueError, "process_std: expected a finite number >= 0"),
    (dict(measurement_std=0.0), ValueError, "measurement_std: expected a finite number > 0, received 0.0. The "
                                            "likelihood"),
    (dict(substeps=0), ValueError, "substeps: expected a positive int"),
    (dict(seed=-1), ValueError, "seed: expected an int >= 0, received -1"),
    (dict(seed=None), TypeError, "seed: expected an int >= 0"),
    (dict(resample="residual"), ValueError, r"resample: expected one of \['systematic', 'stratified', "
                                            r"'multinomial'\], received 'residual'"),
    (dict(ess_threshold=1.5), ValueError, r"ess_threshold: expected a number in \[0, 1\], received 1.5"),
    (dict(ess_threshold=float("nan")), ValueError, "ess_threshold: expected a finite number"),
    (dict(roughening=-0.1), ValueError, "roughening: expected a finite number >= 0, received -0.1"),
    (dict(x0_mean=[0.0, 0.0]), ValueError, "x0_cov: expected an array together with x0_mean"),
    (dict(x0_cov=np.eye(2)), ValueError, "x0_mean: expected an array together with x0_cov"),
    (dict(x0_mean=[0.0], x0_cov=np.eye(2)), ValueError, r"x0_mean: expected shape \(2,\)"),
    (dict(x0_mean=[0.0, 0.0], x0_cov=np.eye(3)), ValueError, r"x0_cov: expected shape \(2, 2\)"),
    (dict(x0_mean=[0.0, 0.0], x0_cov=[[1.0, 2.0], [2.0, 1.0]]), ValueError,
     "x0_cov: expected a symmetric positive semi-definite matrix"),
    (dict(x0_mean=[0.0, 0.0], x0_cov=[[1.0, np.nan], [np.nan, 1.0]]), ValueError, "x0_cov: expected finite values"),
    (dict(jit="yes"), TypeError, "jit: expected a bool, received str"),
    (dict(compile="gcc"), TypeError, "compile: expected a callable casadi.Function -> casadi.Function or None"),
    (dict(n_threads=0), ValueError, "n_threads: expected a positive int, received 0"),
])
def test_bad_arguments_name_the_argument(kwargs, kind, message):
    args = {"system": S, "dt": DT, **kwargs}
    with pytest.raises(kind, match=message):
        ParticleFilter(args.pop("system"), args.pop("dt"), **args)


def test_bad_inputs_name_the_argument():
    pf = ParticleFilter(S, DT, n_particles=10)
    t = np.arange(10) * DT
    y, u = np.zeros((10, 1)), np.zeros((10, 1))
    with pytest.raises(ValueError, match=r"y: expected shape \(N, ny\) or \(M, N, ny\) with N = 10, ny = 1"):
        pf.simulate(t, np.zeros((10, 2)), u)
    with pytest.raises(ValueError, match=r"u: expected shape \(1, 10, 1\), received shape \(1, 9, 1\)"):
        pf.simulate(t, y, u[:9])
    with pytest.raises(ValueError, match="t: expected samples spaced by dt = 0.05"):
        pf.simulate(2 * t, y, u)
    with pytest.raises(ValueError, match=r"t: expected sample times of shape \(N,\)"):
        pf.simulate(t[:, None], y, u)
    bad = y.copy()
    bad[4] = np.nan
    with pytest.raises(ValueError, match="y: expected finite values, received NaN or inf at trial 0, sample 4"):
        pf.simulate(t, bad, u)
    with pytest.raises(ValueError, match="u: expected finite values, received NaN or inf at trial 0, sample 4"):
        pf.simulate(t, y, bad)


def test_the_benchmarks_roughening_is_the_validation_choice():
    """results/generalisation/all/pf_roughening_3030.json (``benchmarks/pf_roughening.py``, validation
    seed 3030): ROUGHENING is the lowest roughening within 0.5 % of the grid's lowest geometric mean of
    PF / EKF, which the plain filter (0) misses."""
    from pathlib import Path

    record = Path(__file__).resolve().parent.parent / "results" / "generalisation" / "all"
    data = json.loads((record / "pf_roughening_3030.json").read_text())
    assert data["seed"] != 2026 and data["particles"] == 1000
    ratios = np.array([row["ratios"] for row in data["rows"]])
    geo = np.exp(np.log(ratios).mean(axis=0))
    np.testing.assert_allclose(geo, data["geometric_mean"], rtol=1e-12)
    chosen = next(k for k, g in zip(data["grid"], geo) if g <= 1.005 * geo.min())
    assert chosen == data["chosen"] == ROUGHENING
    assert geo[data["grid"].index(0.0)] > 1.005 * geo.min()
    assert f"Chosen: {ROUGHENING:g}" in (record / "pf_roughening_3030.md").read_text()
