"""The covariance head in the observer: the card holds it, the CasADi step and ``Estimate.cov``/``var`` give the
covariance of every estimate (equal to the numpy reference of :mod:`kklcasadi.model.variants.covariance`, the
estimates bitwise those of the step without it), the stateful estimator the same, and the generated C's
``name_step`` gains the covariance output (bitwise the CasADi VM with the C library's math, within 1e-12 with the
vector kernels)."""

import json
import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest
from conftest import write_signed_card

from kklcasadi.model.files import load_model, save_model
from kklcasadi.model.variants.bankdecoder import decoder_features
from kklcasadi.model.variants.covariance import COVARIANCE, SCALE, array_shapes, covariance_numpy
from kklcasadi.nets.specs import MLPSpec
from kklcasadi.observer.codegen import generate_c
from kklcasadi.observer.kkl import load_observer

GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc is not installed")


def with_head(path, hidden=(6,), seed=0, scale=(0.7, 1.3), asinh=None):
    """Give the bank model at ``path`` a random covariance head (in place; a test's own directory), and
    optionally the decoder's output map ``asinh`` scales."""
    model = load_model(path)
    nx = model.spec.system.nx
    n_in = model.card["architecture"]["decoder"]["sizes"][0]
    spec = MLPSpec((n_in, *hidden, nx * (nx + 1) // 2))
    rng = np.random.default_rng(seed)
    arrays = {}
    for name, shape in array_shapes(spec, nx).items():
        arrays[name] = (rng.normal(size=shape) / np.sqrt(shape[-1]) if len(shape) == 2
                        else 0.3 * rng.normal(size=shape))
    for name in arrays:
        if name.endswith("_std"):
            arrays[name] = rng.uniform(0.5, 2.0, arrays[name].shape)
    arrays[SCALE] = np.asarray(scale, dtype=float)
    if asinh is not None:
        arrays["decoder/asinh_scale"] = np.asarray(asinh, dtype=float)
    card = json.loads(json.dumps(model.card))
    card["architecture"][COVARIANCE] = spec.to_card()
    return save_model(path, {**model.arrays, **arrays}, card, overwrite=True), spec, arrays


def runs(obs, m=3, n=30, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * obs.dt
    y = np.sin(1.3 * t)[None, :, None] + 0.2 * rng.normal(size=(m, n, obs.ny))
    u = 0.8 * np.sign(np.sin(2.0 * t + rng.uniform(0, 3, (m, 1))))[..., None]
    return t, y, u


@pytest.fixture
def headed(model_dir_factory):
    path, spec, arrays = with_head(model_dir_factory("bank", hidden=(9, 7)))
    return load_observer(path), spec, arrays


def test_the_card_holds_the_head_and_the_observer_gives_the_reference_covariance(model_dir_factory):
    path, spec, arrays = with_head(model_dir_factory("bank", hidden=(9, 7)), asinh=[0.0, 0.4])
    obs = load_observer(path)
    assert obs.model.card["architecture"][COVARIANCE] == spec.to_card()
    t, y, u = runs(obs)
    est = obs.simulate(t, y, u)
    assert est.cov.shape == (3, t.size, 2, 2) and est.var.shape == (3, t.size, 2)
    model = obs.model
    f = decoder_features(est.z, y, u)
    expected = covariance_numpy(spec, arrays, f, est.xhat, model.arrays["decoder/out_std"],
                                model.arrays["decoder/asinh_scale"])
    np.testing.assert_allclose(est.cov, expected, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(est.var, np.diagonal(est.cov, axis1=-2, axis2=-1))
    assert np.all(np.linalg.eigvalsh(est.cov) > 0)
    one = obs.simulate(t, y[1], u[1])                                  # one trial: (N, nx, nx)
    np.testing.assert_array_equal(one.cov, est.cov[1])


def test_the_estimates_are_bitwise_those_of_the_step_without_the_head(headed, model_dir_factory):
    obs, _, _ = headed
    plain = load_observer(model_dir_factory("bank", hidden=(9, 7)))             # same seed: same decoder
    assert plain.covariance is None and plain.step_covariance is None
    t, y, u = runs(obs)
    a, b = obs.simulate(t, y, u), plain.simulate(t, y, u)
    np.testing.assert_array_equal(a.xhat, b.xhat)
    np.testing.assert_array_equal(a.z, b.z)
    assert b.cov is None and b.var is None
    rng = np.random.default_rng(2)
    args = [rng.normal(size=obs.step.size_in(k)) for k in range(5)]
    for x, y_ in zip(obs.step_covariance(*args)[:3], obs.step(*args)):
        np.testing.assert_array_equal(np.array(x), np.array(y_))
    P = np.array(obs.step_covariance(*args)[3])
    z_next, w_next, xhat_next = obs.step(*args)
    np.testing.assert_array_equal(P, np.array(obs.covariance(z_next, w_next, xhat_next)))


def test_the_estimator_gives_the_covariance_of_simulate(headed):
    obs, _, _ = headed
    t, y, u = runs(obs, m=1)
    est = obs.simulate(t, y[0], u[0])
    stepper = obs.estimator()
    assert stepper.cov is None
    for k in range(t.size):
        stepper.make_step(y[0, k], u[0, k])
        np.testing.assert_allclose(stepper.cov, est.cov[k], rtol=1e-13, atol=0)


def test_a_head_with_wrong_sizes_is_refused(model_dir_factory):
    path = model_dir_factory("bank")
    model = load_model(path)
    card = json.loads(json.dumps(model.card))
    card["architecture"][COVARIANCE] = {"sizes": [card["architecture"]["decoder"]["sizes"][0], 4, 2],
                                        "activation": "tanh"}
    write_signed_card(path, card)                  # signed: the digest passes, the field's own check refuses it
    with pytest.raises(ValueError, match=r"architecture\.covariance\.sizes.*nx \(nx \+ 1\) / 2 = 3"):
        load_model(path)
    card["architecture"]["covariances"] = card["architecture"].pop(COVARIANCE)
    write_signed_card(path, card)
    with pytest.raises(ValueError, match=r"'architecture'.*optionally \['covariance', 'inflation'\]"):
        load_model(path)


@needs_gcc
@pytest.mark.parametrize("math, tol, asinh", [("libm", 0.0, None), ("vector", 1e-12, None), ("libm", 0.0, [0.0, 0.4]),
                                              ("vector", 1e-12, [0.0, 0.4])])
def test_the_c_step_gains_the_covariance_output(model_dir_factory, tmp_path, math, tol, asinh):
    """C equals the CasADi VM, with a state decoded through ``s sinh(v)`` (its interval gain) or without."""
    obs = load_observer(with_head(model_dir_factory("bank", hidden=(9, 7)), asinh=asinh)[0])
    files = generate_c(obs, tmp_path, "cov", math=math)
    header = files[1].read_text()
    assert "#define COV_HAS_COVARIANCE 1" in header and "res[3] P_next" in header
    library = tmp_path / "libcov.so"
    subprocess.run([GCC, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-fPIC", "-shared", str(files[0]),
                    "-o", str(library), "-lm"], check=True)
    step = ca.external("cov_step", str(library))
    covariance = ca.external("cov_covariance", str(library))
    assert step.n_out() == 4
    rng = np.random.default_rng(5)
    for scale in (0.5, 3.0, 40.0, 0.5, 3.0):
        args = [scale * rng.normal(size=obs.step.size_in(k)) for k in range(5)]
        pairs = list(zip(step(*args), obs.step_covariance(*args)))
        xhat = scale * rng.normal(size=obs.nx)
        pairs.append((covariance(args[0], args[1], xhat), obs.covariance(args[0], args[1], xhat)))
        for c_out, vm_out in pairs:
            c_out, vm_out = np.array(c_out), np.array(vm_out)
            if tol == 0:
                assert np.array_equal(c_out, vm_out), np.max(np.abs(c_out - vm_out))
            else:
                np.testing.assert_allclose(c_out, vm_out, rtol=tol, atol=tol * np.max(np.abs(vm_out)))


@needs_gcc
def test_the_main_example_still_reproduces_simulate(headed, tmp_path):
    from conftest import c_program_estimates

    obs, _, _ = headed
    t, y, u = runs(obs, m=1)
    np.testing.assert_array_equal(c_program_estimates(obs, tmp_path, "cov", t, y[0], u[0]),
                                  obs.simulate(t, y[0], u[0]).xhat)


# ----------------------------------------------------------------------------- a linear-Gaussian plant

def _linear_gaussian(tmp_path, q=0.1, r=0.1, dt=0.05):
    """A damped oscillator ``x' = F x + w`` (``w`` held over each interval, std ``q``), ``y = x_1 + v`` (std ``r``),
    and a bank observer whose latent is the continuous-time Kalman filter of its sampled noise (``A = F - K H``,
    ``By = K``, the Riccati gain for ``Qc = q^2 dt I``, ``Rc = r^2 dt``) and whose decoder reads ``xhat = z`` (a
    linear skip path): ``(system, observer, Phi, Psi, H)``."""
    import scipy.linalg

    import kklcasadi
    from kklcasadi.model.card import make_card
    from kklcasadi.model.variants import BankSpec

    F, H = np.array([[0.0, 1.0], [-1.0, -0.5]]), np.array([[1.0, 0.0]])
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    system = kklcasadi.System("oscillator", x, u, ca.mtimes(ca.DM(F), x) + ca.vertcat(0, u), [x[0]], [[-1, 1], [-1, 1]])
    P = scipy.linalg.solve_continuous_are(F.T, H.T, q ** 2 * dt * np.eye(2), np.array([[r ** 2 * dt]]))
    K = P @ H.T / (r ** 2 * dt)
    A, By = F - K @ H, K
    decoder = MLPSpec((4, 3, 2), skip=True)
    spec = BankSpec(decoder, A, By, dt, 1, {"y_poles": [1.0], "u_poles": [], "y_resonators": [], "clock": None})
    card = make_card(system, type("D", (), {"A": A, "B": By})(), "bank", spec, dt=dt, window=1)
    arrays = {name: np.zeros(shape) for name, shape in spec.array_shapes().items()}
    arrays.update({"bank/Bu": np.array([[0.0], [1.0]]), "decoder/in_std": np.ones(4), "decoder/out_std": np.ones(2),
                   "decoder/Wskip": np.eye(2, 4)})
    path = save_model(tmp_path / "oscillator", arrays, card)
    M = scipy.linalg.expm(np.block([[F, np.eye(2)], [np.zeros((2, 4))]]) * dt)
    return system, load_observer(path, system=system), M[:2, :2], M[:2, 2:], H


def test_the_learned_covariance_of_a_linear_gaussian_observer_is_the_exact_one(tmp_path):
    """On a linear-Gaussian plant the error of a linear observer is Gaussian with a covariance computed exactly
    (the augmented system's discrete Lyapunov equation, in steady state); the head fit on runs of it and
    calibrated on others recovers its stds within 6 % and its correlation within 0.1 at every sample. That
    observer is the continuous-time Kalman filter of the sampled noise: its covariance is within 10 % (std) of
    the sampled-data Kalman filter's, the best any estimator of y_0..y_k does."""
    import scipy.linalg

    from kklcasadi.train.covariance import CovarianceConfig, calibrate, fit_covariance, output_errors

    q, r, dt = 0.1, 0.1, 0.05
    system, obs, Phi, Psi, H = _linear_gaussian(tmp_path, q, r, dt)
    # the observer's exact step, read off its (linear) step function: z' = Ad z + Gy y + Gn y_next (u = 0)
    cols = lambda k, n: [np.array(obs.step(*[np.eye(n)[j] if i == k else np.zeros(obs.step.size_in(i))  # noqa: E731
                                           for i in range(5)])[0]).ravel() for j in range(n)]
    Ad, Gy, Gn = (np.column_stack(cols(k, n)) for k, n in ((0, 2), (2, 1), (3, 1)))
    # s = [x; z; v]: x' = Phi x + Psi w, z' = Ad z + Gy (H x + v) + Gn (H x' + v'), v' new
    T = np.zeros((5, 5))
    T[:2, :2] = Phi
    T[2:4, :2], T[2:4, 2:4], T[2:4, 4:] = Gy @ H + Gn @ H @ Phi, Ad, Gy
    N = np.zeros((5, 3))                                       # driven by [w (2); v' (1)]
    N[:2, :2], N[2:4, :2], N[2:4, 2:], N[4:, 2:] = Psi, Gn @ H @ Psi, Gn, np.eye(1)
    S = scipy.linalg.solve_discrete_lyapunov(T, N @ np.diag([q ** 2, q ** 2, r ** 2]) @ N.T)
    D = np.hstack([np.eye(2), -np.eye(2), np.zeros((2, 1))])
    exact = D @ S @ D.T
    Qd = Psi @ Psi.T * q ** 2
    prior = scipy.linalg.solve_discrete_are(Phi.T, H.T, Qd, np.array([[r ** 2]]))
    kalman = prior - prior @ H.T @ np.linalg.solve(H @ prior @ H.T + r ** 2, H @ prior)
    ratio = np.sqrt(np.diag(exact) / np.diag(kalman))
    assert np.all(ratio >= 1 - 1e-9) and np.all(ratio < 1.1), ratio

    def runs(m, seed, n=600, settle=200):
        """Stationary runs of the plant (u = 0) and the observer's estimates after ``settle`` samples."""
        rng = np.random.default_rng(seed)
        stationary = scipy.linalg.solve_discrete_lyapunov(Phi, Qd)
        x = np.empty((m, n, 2))
        x[:, 0] = rng.multivariate_normal(np.zeros(2), stationary, m)
        for k in range(n - 1):
            x[:, k + 1] = x[:, k] @ Phi.T + (q * rng.normal(size=(m, 2))) @ Psi.T
        y = x[..., :1] + r * rng.normal(size=(m, n, 1))
        u = np.zeros((m, n, 1))
        est = obs.simulate(np.arange(n) * dt, y, u)
        keep = slice(settle, None, 2)
        return x[:, keep], est.xhat[:, keep], decoder_features(est.z, y, u)[:, keep], est

    x, xhat, f, _ = runs(60, 1)
    e = x - xhat
    np.testing.assert_allclose(np.cov(e.reshape(-1, 2).T), exact, rtol=0, atol=0.05 * np.max(exact))  # the sample's
    fit = fit_covariance(f.reshape(-1, 4), output_errors(x, xhat, np.ones(2), np.zeros(2)).reshape(-1, 2),
                         CovarianceConfig(hidden=(4,)), seed=0)
    xv, xhv, fv, _ = runs(60, 2)
    scale = calibrate(fit.arrays, fit.arch, fv.reshape(-1, 4), xhv.reshape(-1, 2), (xv - xhv).reshape(-1, 2),
                      np.ones(2), np.zeros(2))
    P = covariance_numpy(MLPSpec.from_card(fit.arch, "architecture", COVARIANCE), {**fit.arrays, SCALE: scale},
                         fv, xhv, np.ones(2), np.zeros(2))
    std = np.sqrt(np.diagonal(P, axis1=-2, axis2=-1))
    corr = P[..., 0, 1] / (std[..., 0] * std[..., 1])
    np.testing.assert_allclose(std, np.broadcast_to(np.sqrt(np.diag(exact)), std.shape), rtol=0.06)
    np.testing.assert_allclose(corr, exact[0, 1] / np.sqrt(exact[0, 0] * exact[1, 1]), atol=0.1)


# ----------------------------------------------------------------------------- consistency beside the SMAPE

def test_the_covariances_are_scored_on_the_protocols_trials(headed):
    """score_uncertainty's rows are kklcasadi.consistency of the observer's variances (compiled: bitwise its
    simulate) and of the EKF's own, on the cells' trials."""
    from kklcasadi.consistency import consistency
    from kklcasadi.estimators.ekf import EKF
    from kklcasadi.evaluation.compiled import Compiler
    from kklcasadi.evaluation.protocol import Protocol
    from kklcasadi.evaluation.uncertainty import (
        filter_uncertainty,
        observer_uncertainty,
        score_uncertainty,
        uncertainty_table,
    )

    obs, _, _ = headed
    ekf = EKF(obs.system, obs.dt)
    protocol = Protocol(n_trials=3, method="rk")
    cells = [protocol.cell("zero"), protocol.cell("square")]
    estimators = [("kkl", observer_uncertainty(obs, compiler=Compiler())), ("EKF", filter_uncertainty(ekf))]
    rows = score_uncertainty(estimators, obs.system, cells)
    assert [(r.label, r.cell) for r in rows] == [("kkl", "zero-noisy"), ("kkl", "square-noisy"), ("EKF", "zero-noisy"),
                                                 ("EKF", "square-noisy")]
    batch = cells[1].simulate(obs.system)
    est, filt = obs.simulate(batch.t, batch.y, batch.u), ekf.simulate(batch.t, batch.y, batch.u)
    assert rows[1].consistency == consistency(batch.x, est.xhat, est.var, t=batch.t)
    assert rows[3].consistency == consistency(batch.x, filt.xhat, filt.var, t=batch.t)
    table = uncertainty_table(rows)
    assert table.count("\n") == 5 and "| duffing | square-noisy | EKF |" in table


def test_evaluate_writes_the_consistency_table(headed, tmp_path, capsys, model_dir_factory):
    import kklcasadi.provenance as provenance
    from kklcasadi.cli import main

    obs, _, _ = headed
    out = tmp_path / "eval"
    args = ["evaluate", str(obs.model.path), "--trials", "2", "--kinds", "zero", "--noise", "on", "--ekf",
            "--consistency", "--out", str(out)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "mean NEES (95 % band)" in printed and "| duffing | zero-noisy | EKF |" in printed
    records = provenance.json_payload(json.loads((out / "duffing_consistency.json").read_text()))
    assert [r["label"] for r in records] == [obs.model.path.name, "EKF"]
    scores = provenance.json_payload(json.loads((out / "duffing_scores.json").read_text()))
    smape = {r["method"]: np.mean(r["smape"]) for r in scores}                # the SMAPE of the same run
    assert [smape[r["label"]] for r in records] == pytest.approx([r["smape"] for r in records], rel=1e-12)
    assert provenance.read(out / "duffing_consistency.md").command == "kklcasadi " + " ".join(args)
    assert main(["evaluate", str(obs.model.path), "--noise", "off", "--consistency"]) == 2
    assert "--consistency: the covariances are scored on the noisy cells" in capsys.readouterr().err
    assert main(["evaluate", str(model_dir_factory("bank")), "--consistency"]) == 2
    assert "--consistency: expected a model with a covariance head" in capsys.readouterr().err


def test_generalise_scores_the_covariances_on_every_case(headed, tmp_path, capsys, model_dir_factory):
    """``kklcasadi generalise --consistency``: the head and the EKF tuned to the case's noise, case by case; the
    EKF's row is kklcasadi.consistency of case_ekf's own variances on the case's trials."""
    import kklcasadi.provenance as provenance
    from kklcasadi.cli import main
    from kklcasadi.consistency import consistency
    from kklcasadi.evaluation import generalisation as gen

    obs, _, _ = headed
    out = tmp_path / "gen"
    assert main(["generalise", str(obs.model.path), "--families", "constant", "--regimes", "ood", "--noise-levels",
                 "0.2", "--trials", "2", "--consistency", "--out", str(out)]) == 0
    assert "| duffing | constant ood 0.2 | EKF |" in capsys.readouterr().out
    records = provenance.json_payload(json.loads((out / "duffing_generalisation_consistency.json").read_text()))
    assert [(r["label"], r["cell"]) for r in records] == [(obs.model.path.name, "constant ood 0.2"),
                                                           ("EKF", "constant ood 0.2")]
    case = gen.Case("constant", "ood", 0.2)
    batch = case.cell(gen.Settings(n_trials=2)).simulate(obs.system)
    filt = gen.case_ekf(obs.system, 0.2, obs.dt).simulate(batch.t, batch.y, batch.u)
    expected = consistency(batch.x, filt.xhat, filt.var, t=batch.t).to_json()
    assert {k: records[1][k] for k in expected} == expected
    assert main(["generalise", str(model_dir_factory("bank")), "--consistency"]) == 2
    assert "--consistency: expected a model with a covariance head" in capsys.readouterr().err


# ----------------------------------------------------------------------------- the shipped heads

def test_robustness_scores_every_covariance_on_the_cases_trials(headed, tmp_path, capsys):
    """``kklcasadi robustness --consistency``, the smallest case end to end: the head's, the EKF's, the tuned EKF's,
    the augmented EKF's (its plant states) and the particle filter's (on its trials) covariances, each row
    kklcasadi.consistency of that estimator's own variances on the case's trials, beside the SMAPE of the table."""
    import kklcasadi as kc
    import kklcasadi.provenance as provenance
    from kklcasadi.cli import main
    from kklcasadi.consistency import consistency
    from kklcasadi.estimators import AugmentedEKF, ParameterPF, TunedEKF
    from kklcasadi.estimators.pf import ROUGHENING
    from kklcasadi.evaluation import generalisation as gen
    from kklcasadi.evaluation import robustness as rb

    obs, _, _ = headed
    out = tmp_path / "rob"
    assert main(["robustness", str(obs.model.path), "--kinds", "exact", "--trials", "2", "--tuning-trials", "2",
                 "--pf", "20", "--pf-trials", "1", "--vm", "--no-cache", "--consistency", "--labels", "kkl",
                 "--out", str(out)]) == 0
    assert "| duffing | exact | augmented EKF |" in capsys.readouterr().out
    assert "mean NEES (95 % band)" in (out / "duffing_robustness.md").read_text()
    data = provenance.json_payload(json.loads((out / "duffing_robustness.json").read_text()))
    records = {r["label"]: r for r in data["consistency"]}
    assert list(records) == ["kkl", "EKF", "tuned EKF", "augmented EKF", "PF (x, p)"]
    assert {r["cell"] for r in records.values()} == {"exact"}
    family, nominal = kc.systems.get("duffing", param_spread=0.3), kc.systems.get("duffing")
    settings = rb.Settings(n_trials=2, n_tuning=2)
    case = rb.RobustCase("exact", "exact")
    batch = rb.RobustCell(case, settings).simulate(family)
    tuning = rb.RobustCell(case, settings, tuning=True).simulate(family)
    t, x, y, u = batch.t, batch.x, batch.y, batch.u
    chosen = data["cases"][0]["tuning"]["augmented"]
    aekf = AugmentedEKF(family, 0.05, q_scale=chosen["q_scale"], r_scale=chosen["r_scale"],
                        param_walk=chosen["param_walk"], input_disturbance=chosen["input_disturbance"])
    pf = ParameterPF(family, 0.05, n_particles=20, roughening=ROUGHENING, seed=2026, jit=False)
    a, p = aekf.simulate(t, y, u), pf.simulate(t, y[:1], u[:1])
    head = obs.simulate(t, y, u)
    estimates = {"kkl": (x, head.xhat, head.var),
                 "EKF": (x, *(lambda e: (e.xhat, e.var))(gen.case_ekf(nominal, 0.1, 0.05).simulate(t, y, u))),
                 "tuned EKF": (x, *(lambda e: (e.xhat, e.var))(TunedEKF.fit(
                     nominal, 0.05, tuning, process_std=0.1, measurement_std=0.1).simulate(t, y, u))),
                 "augmented EKF": (x, aekf.split(a.xhat)[0], aekf.split(a.var)[0]),
                 "PF (x, p)": (x[:1], pf.split(p.xhat)[0], pf.split(p.var)[0])}
    smape = {"kkl": data["cases"][0]["models"]["kkl"]["smape_mean"],
             **{rb.TITLES[b]: data["cases"][0]["baselines"][b]["smape_mean"] for b in rb.BASELINES}}
    for label, (truth, xhat, var) in estimates.items():
        expected = consistency(truth, xhat, var, t=t).to_json()
        got = {k: records[label][k] for k in expected}
        assert got["trials"] == expected["trials"] and got["samples"] == expected["samples"]
        assert got["nees"] == pytest.approx(expected["nees"], rel=1e-9), label
        assert got["log_likelihood"] == pytest.approx(expected["log_likelihood"], rel=1e-9), label
        assert got["coverage"] == expected["coverage"] and got["nees_band"] == expected["nees_band"], label
        assert records[label]["smape"] == smape[label] == pytest.approx(np.mean(kc.metrics.smape(truth, xhat)),
                                                                        rel=1e-9)


def test_a_sample_the_domain_monitor_flags_has_a_large_variance():
    """The shipped duffing/bank on ood square-wave trials (10 of 25 s, seed 5): where the domain monitor flags a
    sample (after 5 s; 12 % of them), the velocity's variance is at least twice its median where it does not
    (measured: 3.5x; the velocity's mean squared error 5.1x); the measured position's stays within 30 %
    (measured: 0.97x; its squared error 1.25x)."""
    from kklcasadi.evaluation.compiled import CompiledRecord
    from kklcasadi.evaluation.protocol import Protocol

    obs = load_observer("duffing/bank")
    batch = Protocol(n_trials=10, T=25.0, seed=5, regime="ood", method="rk").trials(obs.system, "square")
    xhat, z, cov = CompiledRecord(obs).record(batch.t, batch.y, batch.u)
    inside = obs.in_domain(xhat, z, np.concatenate([batch.y, batch.u], axis=-1)[..., None])
    late = batch.t >= 5.0
    var = np.diagonal(cov, axis1=-2, axis2=-1)[:, late]
    flagged = ~inside[:, late]
    assert 0.02 < flagged.mean() < 0.5
    ratio = np.median(var[flagged], axis=0) / np.median(var[~flagged], axis=0)
    assert ratio[1] > 2 and abs(ratio[0] - 1) < 0.3, ratio
