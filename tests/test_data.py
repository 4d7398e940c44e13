import numpy as np
import pytest
from scipy.linalg import solve_sylvester

import kklcasadi as kc
from kklcasadi.plant import data
from kklcasadi.plant import signals as sig


def test_linear_labels_match_the_sylvester_solution():
    s = kc.systems.get("linear")
    d = kc.Design.default(s)
    # T F - A T = B H  <=>  (-A) T + T F = B H
    T = solve_sylvester(-d.A, kc.systems.LINEAR_F, d.B @ kc.systems.LINEAR_H)
    x, z, y = data.phase1(s, d, n_traj=12, seed=0, t_keep=2.0, domain_scale=1e3)
    assert x.shape == (12 * 40, 2) and z.shape == (12 * 40, 5) and y.shape == (12 * 40, 1)
    err = np.abs(z - x @ T.T).max() / np.abs(z).max()
    assert err < 1e-6, err


@pytest.mark.parametrize("name", ["duffing", "vdp"])
def test_phase1_labels_are_consistent_with_the_latent_ode(name):
    """Along a labelled trajectory, z(t) follows zdot = A z + B y (finite-difference check)."""
    s = kc.systems.get(name)
    d = kc.Design.paper(s)
    dt = 0.002
    x, z, y = data.phase1(s, d, n_traj=3, seed=1, t_keep=1.0, dt=dt)
    z = z.reshape(3, -1, d.nz)
    y = y.reshape(3, -1, 1)
    zdot_fd = (z[:, 2:] - z[:, :-2]) / (2 * dt)
    zdot = z[:, 1:-1] @ d.A.T + y[:, 1:-1] @ d.B.T
    np.testing.assert_allclose(zdot_fd, zdot, atol=1e-4 * np.abs(zdot).max())
    np.testing.assert_allclose(y.reshape(-1), x[:, 0])


def test_phase1_covers_the_box_and_is_seeded():
    s = kc.systems.get("duffing")
    d = kc.Design.paper(s)
    a = data.phase1(s, d, n_traj=8, seed=4, t_keep=1.0)
    b = data.phase1(s, d, n_traj=8, seed=4, t_keep=1.0)
    np.testing.assert_array_equal(a.z, b.z)
    first = a.x.reshape(8, 20, 2)[:, 0]
    # the backward-forward pass returns near the Latin-hypercube states
    np.testing.assert_allclose(first, s.sample_box(8, 4) + 0 * first, atol=0.2)


def test_pde_points_are_exact():
    s = kc.systems.get("vdp")
    p = data.pde_points(s, 50, seed=2)
    x1, x2 = p.x[:, 0], p.x[:, 1]
    np.testing.assert_allclose(p.f, np.column_stack([x2, (1 - x1 ** 2) * x2 - x1]), rtol=1e-14)
    np.testing.assert_array_equal(p.y[:, 0], x1)


def test_window_convention():
    u = np.arange(6.0)[:, None]
    w = data.input_windows(u, 3)
    assert w.shape == (6, 3, 1)
    np.testing.assert_array_equal(w[0, :, 0], [0, 0, 0])     # padded with u_0
    np.testing.assert_array_equal(w[1, :, 0], [0, 0, 1])
    np.testing.assert_array_equal(w[5, :, 0], [3, 4, 5])     # oldest first, ends at u_k
    batched = data.input_windows(np.stack([u, 2 * u]), 3)
    np.testing.assert_array_equal(batched[1, 4, :, 0], [4, 6, 8])
    with pytest.raises(ValueError, match="window: expected a positive int"):
        data.input_windows(u, 0)


def test_phase2_samples():
    s = kc.systems.get("duffing")
    signals = [sig.make("constant", value=0.5), sig.make("square", amplitude=1.0, omega=1.0)]
    p2 = data.phase2(s, n_traj=3, signals=signals, window=10, T=2.0, seed=0)
    assert p2.x.shape == (6, 40, 2) and p2.n_samples == 6 * 39 and not p2.dropped
    b = p2.batch(np.arange(p2.n_samples))
    np.testing.assert_allclose(b["xdot"][:, 0], b["x"][:, 1])
    np.testing.assert_allclose(b["xdot"][:, 1], -b["x"][:, 0] - b["x"][:, 0] ** 3 + b["u"][:, 0])
    np.testing.assert_array_equal(b["w"][:, -1], b["u"])                 # window ends at u_k
    np.testing.assert_array_equal(b["w_next"][:, :-1], b["w"][:, 1:])     # the next window shifts by one
    with pytest.raises(ValueError, match=r"index: expected flat sample indices in \[0, "):
        p2.batch(np.array([p2.n_samples]))


def test_phase2_drops_and_reports_blow_ups():
    import casadi as ca

    x = ca.SX.sym("x")
    u = ca.SX.sym("u")
    s = kc.System("escape", x, u, x ** 2 + u, x, [[-1.0, 1.0]])
    with pytest.warns(RuntimeWarning, match="dropped"):
        p2 = data.phase2(s, n_traj=4, signals=[sig.make("constant", value=-2.0), sig.make("constant", value=3.0)],
                         window=5, T=2.0, method="rk")
    assert len(p2.dropped) >= 4 and p2.x.shape[0] == 8 - len(p2.dropped)
    assert all(j == 1 for _, j in p2.dropped)


def test_label_modes():
    s = kc.systems.get("fhn")
    d = kc.Design.paper(s)
    cold = data.phase1(s, d, n_traj=4, seed=0, t_keep=1.0, labels="cold")
    z = cold.z.reshape(4, 20, d.nz)
    np.testing.assert_array_equal(z[:, 0], 0.0)                         # a cold-started observer
    np.testing.assert_allclose(cold.x.reshape(4, 20, 2)[:, 0], s.sample_box(4, 0))
    frozen = data.phase1(s, d, n_traj=4, seed=0, t_keep=1.0, labels="frozen")
    exact = data.phase1(s, d, n_traj=4, seed=0, t_keep=1.0, labels="exact")
    # frozen labels start at x0 (held exit state), exact ones have run on to the equilibrium
    assert np.abs(frozen.x.reshape(4, 20, 2)[:, 0] - s.sample_box(4, 0)).max() < 0.5
    assert np.ptp(exact.x, axis=0).max() < 1e-3
    with pytest.raises(ValueError, match=r"labels: expected one of \['auto', 'exact', 'frozen', 'forward', 'cold'\], "
                                         r"received 'warm'"):
        data.phase1(s, d, n_traj=2, labels="warm")
