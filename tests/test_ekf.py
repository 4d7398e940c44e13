import numpy as np
import pytest
from scipy.linalg import expm

import kklcasadi as kc
from kklcasadi.estimators.ekf import EKF
from kklcasadi.plant import signals as sig
from kklcasadi.plant.rk4 import RK4_STEP_LIMIT, rk4_step, stable_substeps, substeps_for


def test_rk4_step_is_the_fourth_order_taylor_polynomial_on_linear_systems():
    F = kc.systems.LINEAR_F
    h = 0.3
    x0 = np.array([1.0, -0.5])
    M = F * h
    taylor = np.eye(2) + M + M @ M / 2 + M @ M @ M / 6 + M @ M @ M @ M / 24
    np.testing.assert_allclose(rk4_step(lambda _s, x: F @ x, x0, h), taylor @ x0, rtol=1e-14)
    errs = [np.abs(rk4_step(lambda _s, x: F @ x, x0, 1.0, n) - expm(F) @ x0).max() for n in (4, 8, 16)]
    assert all(3.8 < np.log2(a / b) < 4.2 for a, b in zip(errs, errs[1:]))


def _stiff(lam, u_box=None):
    """``xdot = -lam x + u`` (one state, measured): its Jacobian's eigenvalue is ``-lam`` everywhere."""
    import casadi as ca

    x, u = ca.SX.sym("x"), ca.SX.sym("u")
    return kc.System("stiff", x, u, -lam * x + u, x, [[-1, 1]], u_box=u_box)


@pytest.mark.parametrize("lam,dt,expected", [(1.0, 0.05, 1), (40.0, 0.05, 1), (40.0, 0.06, 2), (100.0, 0.05, 3),
                                             (100.0, 0.2, 10)])
def test_stable_substeps_is_the_least_count_inside_the_rk4_limit(lam, dt, expected):
    n = stable_substeps(_stiff(lam), dt)
    assert n == expected
    assert dt / n * lam <= RK4_STEP_LIMIT < dt / max(n - 1, 1e-9) * lam or n == 1
    # the RK4 amplification factor R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24 of one interval: |R|^n < 1 with the
    # count (the decay is kept), and > 1 with a single step where h |lambda| is past the real-axis limit 2.785
    z = -lam * dt / n
    assert abs(1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24) < 1
    z1 = -lam * dt
    if z1 < -2.79:
        assert abs(1 + z1 + z1 ** 2 / 2 + z1 ** 3 / 6 + z1 ** 4 / 24) > 1


def test_stable_substeps_on_the_paper_plants_and_over_the_input_box():
    assert [stable_substeps(kc.systems.get(n), 0.05) for n in ("duffing", "vdp", "rossler", "fhn")] == [1, 1, 1, 5]
    import casadi as ca

    # the input enters the Jacobian: xdot = -u x with u in [0, 300] needs 8 steps at dt = 0.05 (300 * 0.05 / 2 = 7.5)
    x, u = ca.SX.sym("x"), ca.SX.sym("u")
    gain = kc.System("gain", x, u, -u * x, x, [[-1, 1]], u_box=[[0.0, 300.0]])
    assert stable_substeps(gain, 0.05) in (7, 8)             # drawn inputs reach 280-300 of the box's 300


def test_the_benchmarks_counts_for_the_paper_plants_and_the_stable_count_elsewhere():
    from kklcasadi.estimators.pf import SUBSTEPS
    from kklcasadi.evaluation.compare import MHE_SUBSTEPS

    assert [substeps_for(kc.systems.get(n), 0.05, SUBSTEPS) for n in ("duffing", "vdp", "rossler", "fhn")] == \
        [1, 1, 4, 4]                                           # the particle filter's, chosen on the benchmark
    assert [substeps_for(kc.systems.get(n), 0.05, MHE_SUBSTEPS) for n in ("duffing", "fhn")] == [1, 4]
    assert substeps_for(_stiff(100.0), 0.05, SUBSTEPS) == 3 == stable_substeps(_stiff(100.0), 0.05)
    with pytest.raises(ValueError, match=r"^dt: expected"):
        stable_substeps(_stiff(1.0), 0.0)
    with pytest.raises(ValueError, match=r"^samples: expected a positive int"):
        stable_substeps(_stiff(1.0), 0.05, samples=0)


def test_the_ekf_takes_the_stable_count_by_default_and_follows_a_stiff_plant():
    plant = _stiff(100.0, u_box=[[-1.0, 1.0]])
    auto, one = EKF(plant, 0.05, R=1e-4), EKF(plant, 0.05, R=1e-4, substeps=1)
    assert (auto.substeps, one.substeps, EKF(plant, 0.05, substeps=4).substeps) == (3, 1, 4)
    # the truth settles at u / lam; the one-step filter's prediction amplifies (R(-5) = 13.7 per sample) and its
    # estimate is pulled by every measurement, the stable one's prediction decays as the plant does
    t = np.arange(200) * 0.05
    y = np.full((200, 1), 0.01) + np.random.default_rng(0).normal(0, 0.01, (200, 1))
    u = np.ones((200, 1))
    err = [np.abs(f.simulate(t, y, u).xhat[50:, 0] - 0.01).max() for f in (auto, one)]
    assert err[0] < 0.02 < err[1]
    with pytest.raises(ValueError, match=r'^substeps: expected a positive int or "auto", received \'often\''):
        EKF(plant, 0.05, substeps="often")
    with pytest.raises(ValueError, match=r"^substeps: expected a positive int"):
        EKF(plant, 0.05, substeps=0)


def kalman_reference(F, G, H, Q, R, x0, P0, dt, y, u):
    """Independent numpy Kalman filter on the RK4 discretisation of a linear plant."""
    M = F * dt
    Ad = np.eye(2) + M + M @ M / 2 + M @ M @ M / 6 + M @ M @ M @ M / 24
    Bd = (np.eye(2) + M / 2 + M @ M / 6 + M @ M @ M / 24) @ G * dt
    x, P = x0.copy(), P0.copy()
    out = []
    for k in range(len(y)):
        if k > 0:
            x = Ad @ x + Bd @ u[k - 1]
            P = Ad @ P @ Ad.T + Q
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        x = x + K @ (y[k] - H @ x)
        P = (np.eye(2) - K @ H) @ P
        out.append(x)
    return np.array(out)


def test_ekf_on_a_linear_plant_is_the_kalman_filter():
    s = kc.systems.get("linear")
    tr = kc.simulate(s, [0.7, -0.2], sig.make("square", amplitude=0.5, omega=2.0), T=10.0, dt=0.05,
                     process_std=0.1, measurement_std=0.1, seed=3)
    ekf = EKF(s, 0.05)
    est = ekf.simulate(tr.t, tr.y, tr.u)
    ref = kalman_reference(kc.systems.LINEAR_F, kc.systems.LINEAR_G, kc.systems.LINEAR_H, ekf.Q, ekf.R, ekf.x0,
                           ekf.P0, 0.05, tr.y, tr.u)
    np.testing.assert_allclose(est.xhat, ref, rtol=1e-10, atol=1e-12)


def test_ekf_batch_equals_single_and_converges():
    s = kc.systems.get("vdp")
    b = kc.simulate_batch(s, s.sample_box(3, 0), sig.make("zero"), T=20.0, measurement_std=0.01, seed=1,
                          method="rk")
    ekf = EKF(s, 0.05, R=1e-4)
    est = ekf.simulate(b.t, b.y, b.u)
    for i in range(3):
        np.testing.assert_array_equal(ekf.simulate(b.t, b.y[i], b.u[i]).xhat, est.xhat[i])
    assert np.abs(est.xhat[:, -100:] - b.x[:, -100:]).max() < 0.05
    assert np.all(est.var[:, -1] < est.var[:, 0])


def test_ekf_bad_input():
    s = kc.systems.get("duffing")
    ekf = EKF(s, 0.05)
    t = np.arange(10) * 0.05
    with pytest.raises(ValueError, match=r"y: expected shape \(N, ny\) or \(M, N, ny\)"):
        ekf.simulate(t, np.zeros((10, 2)), np.zeros((10, 1)))
    y = np.zeros((10, 1))
    y[4] = np.inf
    with pytest.raises(ValueError, match="y: expected finite values, received NaN or inf at trial 0, sample 4"):
        ekf.simulate(t, y, np.zeros((10, 1)))
    with pytest.raises(ValueError, match=r"Q: expected shape \(2, 2\)"):
        EKF(s, 0.05, Q=np.eye(3))
    with pytest.raises(ValueError, match="t: expected samples spaced by dt = 0.05"):
        ekf.simulate(t * 2, np.zeros((10, 1)), np.zeros((10, 1)))


def _tanh_plant():
    """A plant with exp and tanh in f (so the vector math rewrites apply) and two outputs."""
    import casadi as ca

    x, u = ca.SX.sym("x", 3), ca.SX.sym("u")
    xdot = [x[1], -x[0] - 0.2 * x[1] + ca.tanh(u + x[2]), -0.5 * x[2] + 0.1 * ca.exp(-x[0] ** 2)]
    return kc.System("tanh3", x, u, xdot, ca.vertcat(x[0], x[2]), [[-1, 1]] * 3)


@pytest.mark.skipif(__import__("shutil").which("gcc") is None, reason="gcc is not installed")
@pytest.mark.parametrize("plant,math,form", [("duffing", "libm", "sx"), ("duffing", "vector", "dense"),
                                             ("tanh3", "libm", "sx"), ("tanh3", "vector", "sx"),
                                             ("tanh3", "libm", "dense"), ("tanh3", "vector", "dense")])
def test_ekf_c_step_is_the_vm_step(tmp_path, plant, math, form):
    import subprocess

    import casadi as ca

    from kklcasadi.observer.codegen import C_FLAGS, VECTOR_MATH_TOLERANCE

    s = kc.systems.get(plant) if plant == "duffing" else _tanh_plant()
    ekf = EKF(s, 0.05)
    files = ekf.generate_c(tmp_path, "filt", math=math, form=form)
    source = files[0].read_text()
    assert [f.name for f in files] == ["filt.c", "filt.h"] and f"#define FILT_NS {s.nx + s.nx ** 2}\n" in \
        files[1].read_text()
    assert ("kklc_tanh(" in source) == (plant == "tanh3" and math == "vector")      # the rewrites ran
    assert ("kklc_mv_" in source) == (form == "dense")                              # the axpy kernels
    library = tmp_path / "libfilt.so"
    build = subprocess.run(["gcc", *C_FLAGS, "-Wall", "-Wextra", "-Werror", "-fPIC", "-shared", str(files[0]), "-o",
                            str(library), "-lm"], capture_output=True, text=True)
    assert build.returncode == 0, build.stderr
    step, start = ca.external("filt_step", str(library)), ca.external("filt_start", str(library))
    vm = ekf.step_of(form)
    tr = kc.simulate(s, [0.5, -0.3] + [0.2] * (s.nx - 2), sig.make("sinusoid", amplitude=0.8, omega=1.3), T=5.0,
                     dt=0.05, process_std=0.1, measurement_std=0.1, seed=2)
    reference = ekf.simulate(tr.t, tr.y, tr.u).xhat
    state = np.array(start(tr.y[0])).ravel()
    xhat = [state[:s.nx]]
    tol = 0.0 if math == "libm" or plant == "duffing" else VECTOR_MATH_TOLERANCE
    for k in range(len(tr.t) - 1):
        uy = np.concatenate([tr.u[k], tr.y[k + 1]])
        c_next = np.array(step(state, uy)).ravel()
        vm_next = np.array(vm(state, uy)).ravel()                       # one step of the VM from the same state
        assert np.all(np.abs(c_next - vm_next) <= tol * (1 + np.abs(vm_next)))
        state = c_next
        xhat.append(state[:s.nx])
    if tol == 0.0 and form == "sx":                                        # bitwise the whole run of simulate
        np.testing.assert_array_equal(np.array(xhat), reference)
    else:                                                                  # the dense form: rounding apart
        np.testing.assert_allclose(np.array(xhat), reference, rtol=1e-10, atol=1e-10)
    with pytest.raises(FileExistsError):
        ekf.generate_c(tmp_path, "filt")
    with pytest.raises(ValueError, match="form: expected one of"):
        ekf.step_of("sparse")


@pytest.mark.parametrize("value, definite, message", [
    ([[1.0, 0.5], [0.0, 1.0]], False, "Q: expected a symmetric positive semi-definite matrix"),
    ([[1.0, 0.0], [0.0, -1e-3]], False, "Q: expected a symmetric positive semi-definite matrix"),
    ([[1.0, 0.0], [0.0, 0.0]], True, "Q: expected a symmetric positive definite matrix"),
    ([[1.0, 0.0], [0.0, np.nan]], False, "Q: expected finite values"),
    (np.eye(3), False, r"Q: expected shape \(2, 2\), received shape \(3, 3\)"),
])
def test_the_one_covariance_check_names_the_argument(value, definite, message):
    from kklcasadi.validation import covariance

    with pytest.raises(ValueError, match=message):
        covariance(value, 2, "Q", definite=definite)
    assert np.array_equal(covariance([[1.0, 0.0], [0.0, 0.0]], 2, "Q"), np.diag([1.0, 0.0]))   # semi-definite
    with pytest.raises(ValueError, match="P0: expected a symmetric positive definite matrix"):
        kc.MHE(kc.systems.get("duffing"), 0.05, P0=np.zeros((2, 2)))
