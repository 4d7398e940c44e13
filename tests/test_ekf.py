import numpy as np
import pytest
from scipy.linalg import expm

import kklcasadi as kc
from kklcasadi.estimators.ekf import EKF
from kklcasadi.plant import signals as sig
from kklcasadi.plant.rk4 import rk4_step


def test_rk4_step_is_the_fourth_order_taylor_polynomial_on_linear_systems():
    F = kc.systems.LINEAR_F
    h = 0.3
    x0 = np.array([1.0, -0.5])
    M = F * h
    taylor = np.eye(2) + M + M @ M / 2 + M @ M @ M / 6 + M @ M @ M @ M / 24
    np.testing.assert_allclose(rk4_step(lambda _s, x: F @ x, x0, h), taylor @ x0, rtol=1e-14)
    errs = [np.abs(rk4_step(lambda _s, x: F @ x, x0, 1.0, n) - expm(F) @ x0).max() for n in (4, 8, 16)]
    assert all(3.8 < np.log2(a / b) < 4.2 for a, b in zip(errs, errs[1:]))


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
