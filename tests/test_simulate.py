import numpy as np
import pytest
from scipy.integrate import solve_ivp

import kklcasadi as kc
from kklcasadi.plant import signals as sig


def reference(system, x0, u, T, dt):
    """scipy solve_ivp, interval by interval with the input held (independent implementation)."""
    t = np.arange(int(round(T / dt))) * dt
    us = u(t)
    xs = [np.asarray(x0, float)]
    for k in range(len(t) - 1):
        def rhs(_t, x, u=us[k]):
            return np.asarray(system.f(x, u)).ravel()

        sol = solve_ivp(rhs, (0.0, dt), xs[-1], method="DOP853", rtol=1e-11, atol=1e-12)
        xs.append(sol.y[:, -1])
    return t, np.array(xs)


@pytest.mark.parametrize("name, x0", [("duffing", [0.5, -0.3]), ("vdp", [1.0, 2.0]), ("fhn", [1.0, -0.5])])
def test_cvodes_matches_solve_ivp(name, x0):
    s = kc.systems.get(name)
    u = sig.make("square", amplitude=0.7, omega=1.5, phase=0.2)
    tr = kc.simulate(s, x0, u, T=5.0, dt=0.05)
    t, x = reference(s, x0, u, 5.0, 0.05)
    np.testing.assert_array_equal(tr.t, t)
    np.testing.assert_allclose(tr.x, x, rtol=1e-5, atol=1e-5)  # CVODES at the protocol's rtol 1e-8
    np.testing.assert_array_equal(tr.u[:, 0], u(t)[:, 0])
    np.testing.assert_allclose(tr.y[:, 0], x[:, 0], rtol=1e-5, atol=1e-5)


def test_rk_converges_at_fourth_order():
    s = kc.systems.get("duffing")
    u = sig.make("sinusoid", amplitude=0.5, omega=1.0)
    ref = kc.simulate(s, [0.8, 0.0], u, T=6.0, dt=0.3, rtol=1e-13, atol=1e-14).x
    errs = [np.abs(kc.simulate(s, [0.8, 0.0], u, T=6.0, dt=0.3, method="rk", substeps=n).x - ref).max()
            for n in (1, 2, 4)]
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(orders > 3.7), (errs, orders)


def test_linear_plant_matches_matrix_exponential():
    from scipy.linalg import expm

    s = kc.systems.get("linear")
    F, G = kc.systems.LINEAR_F, kc.systems.LINEAR_G
    dt = 0.1
    tr = kc.simulate(s, [1.0, 0.0], sig.make("constant", value=0.4), T=3.0, dt=dt, rtol=1e-12, atol=1e-14)
    # exact ZOH discretisation: x+ = Ad x + Bd u
    M = expm(np.block([[F, G], [np.zeros((1, 3))]]) * dt)
    Ad, Bd = M[:2, :2], M[:2, 2:]
    x = np.array([1.0, 0.0])
    for k in range(1, len(tr.t)):
        x = Ad @ x + Bd[:, 0] * 0.4
        np.testing.assert_allclose(tr.x[k], x, rtol=1e-9, atol=1e-11)


def test_noise_is_seeded_and_has_the_right_size():
    s = kc.systems.get("duffing")
    u = sig.make("zero")
    a = kc.simulate(s, [0.5, 0.0], u, T=50.0, process_std=0.1, measurement_std=0.1, seed=7, method="rk")
    b = kc.simulate(s, [0.5, 0.0], u, T=50.0, process_std=0.1, measurement_std=0.1, seed=7, method="rk")
    c = kc.simulate(s, [0.5, 0.0], u, T=50.0, process_std=0.1, measurement_std=0.1, seed=8, method="rk")
    np.testing.assert_array_equal(a.y, b.y)
    assert not np.array_equal(a.y, c.y)
    v = a.y[:, 0] - a.x[:, 0]
    assert 0.08 < v.std() < 0.12
    clean = kc.simulate(s, [0.5, 0.0], u, T=50.0, method="rk")
    assert np.abs(clean.x - a.x).max() > 0.01  # process noise moved the state


def test_batch_equals_single_runs():
    s = kc.systems.get("vdp")
    x0 = s.sample_box(4, 0)
    us = [sig.make("sinusoid", amplitude=0.3 * (i + 1), omega=1.0) for i in range(4)]
    seeds = [11, 12, 13, 14]
    batch = kc.simulate_batch(s, x0, us, T=5.0, process_std=0.1, measurement_std=0.1, seed=seeds)
    assert batch.x.shape == (4, 100, 2) and batch.ok.all() and len(batch) == 4
    for i in range(4):
        one = kc.simulate(s, x0[i], us[i], T=5.0, process_std=0.1, measurement_std=0.1, seed=seeds[i])
        np.testing.assert_allclose(batch[i].x, one.x, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(batch[i].y - batch[i].x[:, :1], one.y - one.x[:, :1])


def test_blow_up_is_reported_not_kept():
    import casadi as ca

    x = ca.SX.sym("x")
    u = ca.SX.sym("u")
    unstable = kc.System("escape", x, u, x ** 2 + u, x, [[0.0, 2.0]])
    batch = kc.simulate_batch(unstable, [[-0.5], [2.0]], sig.make("zero"), T=2.0, dt=0.05, method="rk")
    assert batch.ok.tolist() == [True, False]
    assert np.isnan(batch.x[1, -1]).all()
    with pytest.raises(RuntimeError, match="blew up"):
        kc.simulate(unstable, [2.0], sig.make("zero"), T=2.0, dt=0.05, method="rk")


def test_bad_arguments_are_named():
    s = kc.systems.get("duffing")
    u = sig.make("zero")
    with pytest.raises(ValueError, match=r"x0: expected shape \(2,\)"):
        kc.simulate(s, [0.0, 0.0, 0.0], u, T=1.0)
    with pytest.raises(ValueError, match="dt: expected a finite number > 0"):
        kc.simulate(s, [0.0, 0.0], u, T=1.0, dt=0.0)
    with pytest.raises(ValueError, match="T: expected a whole number of sample periods"):
        kc.simulate(s, [0.0, 0.0], u, T=1.01, dt=0.05)
    with pytest.raises(ValueError, match=r"u\[0\]: expected samples of shape \(N, nu\) = \(20, 1\)"):
        kc.simulate(s, [0.0, 0.0], np.zeros((19, 1)), T=1.0)
    bad = np.zeros((20, 1))
    bad[7] = np.nan
    with pytest.raises(ValueError, match=r"u\[0\]: expected finite samples, received \[nan\] at sample 7"):
        kc.simulate(s, [0.0, 0.0], bad, T=1.0)
    with pytest.raises(ValueError, match=r"method: expected one of \['cvodes', 'rk'\]"):
        kc.simulate(s, [0.0, 0.0], u, T=1.0, method="euler")
    with pytest.raises(ValueError, match="process_std: expected a finite number >= 0"):
        kc.simulate(s, [0.0, 0.0], u, T=1.0, process_std=-1.0)
