import casadi as ca
import numpy as np
import pytest
from scipy.linalg import solve_sylvester, svdvals

import kklcasadi as kc
from kklcasadi.plant import data
from kklcasadi.plant.design import MAX_SPREAD, MIN_MARGIN, MIN_SPREAD


def duffing_chain(nx, ny, *, c=0.1, coupling=0.5, speed=1.0):
    """``nx / 2`` damped Duffing oscillators in a chain (free ends), u on the first; y = x1, x_nx, sum(x)."""
    n = nx // 2
    x, u = ca.SX.sym("x", nx), ca.SX.sym("u")
    q, v = x[:n], x[n:]
    acc = []
    for i in range(n):
        left, right = (q[i - 1] if i > 0 else q[i]), (q[i + 1] if i < n - 1 else q[i])
        acc.append(-q[i] - q[i] ** 3 - c * v[i] + coupling * (left - 2 * q[i] + right) + (u if i == 0 else 0))
    xdot = [speed * e for e in [*[v[i] for i in range(n)], *acc]]
    return kc.System("chain", x, u, xdot, [x[0], x[nx - 1], ca.sum1(x)][:ny], [[-1, 1]] * nx)


def linear_chain(n, ny, *, c=0.1, coupling=0.3):
    """``n`` damped linear oscillators (stiffness 1 + i/4) in a chain; y = positions 1, n, n/2 + 1."""
    K = np.diag(1 + 0.25 * np.arange(n)) + coupling * (2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1))
    K[0, 0] -= coupling
    K[-1, -1] -= coupling
    F = np.block([[np.zeros((n, n)), np.eye(n)], [-K, -c * np.eye(n)]])
    H = np.zeros((ny, 2 * n))
    H[np.arange(ny), [0, n - 1, n // 2][:ny]] = 1.0
    G = np.zeros((2 * n, 1))
    G[n] = 1.0
    x, u = ca.SX.sym("x", 2 * n), ca.SX.sym("u")
    xdot = ca.mtimes(ca.DM(F), x) + ca.mtimes(ca.DM(G), u)
    return kc.System("linear_chain", x, u, xdot, ca.mtimes(ca.DM(H), x), [[-1, 1]] * (2 * n)), F, H


def pbh_margin(A, B):
    """Independent PBH: smallest singular value of [A - lam I, B] over all eigenvalues, relative to |[A, B]|."""
    values = [svdvals(np.hstack([A - lam * np.eye(len(A)), B]))[-1] for lam in np.linalg.eigvals(A)]
    return min(values) / np.linalg.norm(np.hstack([A, B]), 2)


@pytest.mark.parametrize("name, nz", [("duffing", 5), ("rossler", 7), ("lorenz", 7)])
def test_paper_design_is_the_papers(name, nz):
    d = kc.Design.paper(kc.systems.get(name))
    np.testing.assert_array_equal(d.A, -np.diag(np.arange(1, nz + 1)))
    np.testing.assert_array_equal(d.B, np.ones((nz, 1)))
    assert d.nz == nz and d.ny == 1
    assert d.lam == pytest.approx(1.0)
    assert d.kappa == pytest.approx(1.0)


@pytest.mark.parametrize("name", ["duffing", "vdp", "rossler", "fhn", "lorenz", "linear"])
def test_the_paper_plants_carry_the_paper_design_flag(name):
    assert kc.systems.get(name).paper_design == (name in ("duffing", "vdp", "rossler", "fhn"))


def test_kappa_and_lam_of_a_non_normal_design():
    A = np.array([[-1.0, 10.0], [0.0, -2.0]])
    d = kc.Design(A, [1.0, 1.0])
    _, vecs = np.linalg.eig(A)
    assert d.kappa == pytest.approx(np.linalg.cond(vecs))
    assert d.kappa > 10
    assert d.lam == pytest.approx(1.0)
    t = d.forgetting_time(3.0, 1e-6)
    assert d.kappa * np.exp(-d.lam * t) * 3.0 == pytest.approx(1e-6)


def test_design_is_immutable():
    d = kc.Design.paper(kc.systems.get("duffing"))
    with pytest.raises(ValueError):
        d.A[0, 0] = 1.0
    with pytest.raises(AttributeError):
        d.A = np.eye(5)
    with pytest.raises(AttributeError):
        d.controllability_margin = 1.0


def test_bad_designs_are_rejected():
    with pytest.raises(ValueError, match="A: expected a Hurwitz matrix"):
        kc.Design(np.diag([-1.0, 0.5]), np.ones((2, 1)))
    with pytest.raises(ValueError, match=r"\(A, B\): expected a controllable pair"):
        kc.Design(-np.eye(2), np.ones((2, 1)))
    with pytest.raises(ValueError, match="A: expected a non-empty square matrix"):
        kc.Design(np.ones((2, 3)), np.ones((2, 1)))
    with pytest.raises(ValueError, match=r"B: expected shape \(nz, ny\) = \(2, ny\)"):
        kc.Design(-np.diag([1.0, 2.0]), np.ones((3, 1)))
    with pytest.raises(TypeError, match=r"system: expected a kklcasadi\.System"):
        kc.Design.default("duffing")
    with pytest.raises(TypeError, match=r"system: expected a kklcasadi\.System"):
        kc.Design.paper("duffing")


@pytest.mark.parametrize("A, B, message", [
    # a decoupled mode that B misses (a zero row of B)
    (-np.diag([1.0, 2.0, 3.0]), [[1.0], [0.0], [1.0]], r"received 0 \|\[A, B\]\| at lam = -2\. B does not reach the "
                                                        r"mode of lam: its left eigenvector w lies on latents \[1\]"),
    # a repeated eigenvalue with one input
    (-np.eye(2), np.ones((2, 1)), r"at lam = -1\. lam has 2 independent eigenvectors and B 1 column"),
    (-np.diag([1.0, 3.0, 3.0, 2.0]), np.ones((4, 1)), r"at lam = -3\. lam has 2 independent eigenvectors"),
    # three independent eigenvectors of one eigenvalue need three inputs, not two
    (-np.diag([1.0, 1.0, 1.0, 2.0]), [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.5]],
     r"at lam = -1\. lam has 3 independent eigenvectors and B 2 column"),
    # two outputs whose blocks miss a latent
    (-np.diag([1.0, 2.0, 3.0, 4.0]), [[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [0.0, 0.0]], r"at lam = -4\..*latents \[3\]"),
])
def test_uncontrollable_pairs_are_refused_naming_the_eigenvalue(A, B, message):
    with pytest.raises(ValueError, match=r"\(A, B\): expected a controllable pair \(PBH: s_min\(\[A - lam I, B\]\) "
                                         r">= 1e-07 \|\[A, B\]\| at every eigenvalue lam of A\).*" + message):
        kc.Design(A, B)


def test_repeated_eigenvalues_with_enough_inputs_and_a_defective_chain_are_controllable():
    d = kc.Design(-np.diag([1.0, 1.0, 2.0]), [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    assert d.controllability_margin == pytest.approx(pbh_margin(d.A, d.B), rel=1e-12)
    # a Jordan chain of -1 (size 3) plus -2, in rotated coordinates: reached only through the chain's end
    Q, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(4, 4)))
    A = Q @ (np.diag([-1.0, -1.0, -1.0, -2.0]) + np.diag([1.0, 1.0, 0.0], 1)) @ Q.T
    assert kc.Design(A, Q @ [[0.0], [0.0], [1.0], [1.0]]).controllability_margin > 0.1
    # the defective eigenvalue is found to rounding: -1, -0.9999..., -1.0000..., possibly with a tiny imaginary part
    lam = r"-(1|0\.9999\d*|1\.0000\d*)([+-][\d.e-]+j)?"
    with pytest.raises(ValueError, match=rf"at lam = {lam}\. B does not reach the mode of lam"):
        kc.Design(A, Q @ [[1.0], [0.0], [0.0], [1.0]])       # the chain's start: its end is unreachable


@pytest.mark.parametrize("eps", [1e-2, 1e-5])
def test_margin_of_a_weakly_reached_mode_is_analytic(eps):
    """A = diag(-1, -2), B = (1, eps): at lam = -2, [A - lam I, B] [.]^T = [[2, eps], [eps, eps^2]]."""
    A, B = np.diag([-1.0, -2.0]), np.array([[1.0], [eps]])
    trace, det = 2 + eps ** 2, eps ** 2
    s_min = np.sqrt(det / ((trace + np.sqrt(trace ** 2 - 4 * det)) / 2))       # ~ eps / sqrt(2)
    d = kc.Design(A, B)
    assert d.controllability_margin == pytest.approx(s_min / np.linalg.norm(np.hstack([A, B]), 2), rel=1e-10)
    assert kc.Design(7.0 * A, 7.0 * B).controllability_margin == pytest.approx(d.controllability_margin, rel=1e-12)


def test_the_margin_is_the_size_of_a_perturbation_that_makes_the_pair_uncontrollable():
    d = kc.Design.default(duffing_chain(4, 2))
    M = np.hstack([d.A, d.B])
    lam = min(np.linalg.eigvals(d.A), key=lambda lam: svdvals(np.hstack([d.A - lam * np.eye(d.nz), d.B]))[-1])
    u, s, vh = np.linalg.svd(np.hstack([d.A - lam.real * np.eye(d.nz), d.B]))
    E = -s[-1] * np.outer(u[:, -1], vh[d.nz - 1])                   # the rank-one step to rank nz - 1
    assert np.linalg.norm(E, 2) == pytest.approx(d.controllability_margin * np.linalg.norm(M, 2), rel=1e-10)
    with pytest.raises(ValueError, match=r"\(A, B\): expected a controllable pair"):
        kc.Design(d.A + E[:, :d.nz], d.B + E[:, d.nz:])


@pytest.mark.parametrize("nz", [17, 65, 129])
def test_the_papers_pair_is_controllable_at_sizes_the_controllability_matrix_could_not_tell(nz):
    d = kc.Design(-np.diag(np.arange(1.0, nz + 1)), np.ones((nz, 1)))
    assert d.controllability_margin == pytest.approx(pbh_margin(d.A, d.B), rel=1e-12)
    assert d.controllability_margin > 0.4 / nz


@pytest.mark.parametrize("ny", [1, 2, 3])
@pytest.mark.parametrize("nx", [2, 4, 8, 16, 32, 64])
def test_default_design_scales(nx, ny):
    d = kc.Design.default(duffing_chain(nx, ny))
    nz = ny * (2 * nx + 1)
    rates = -np.diag(d.A)
    assert d.nz == nz and d.ny == ny
    np.testing.assert_array_equal(d.A, np.diag(-rates))
    # per-output blocks of unit-gain filters: latent i is driven by its block's output only, with gain rate_i
    blocks = np.repeat(np.arange(ny), [nz // ny + (j < nz % ny) for j in range(ny)])
    expected_B = np.zeros((nz, ny))
    expected_B[np.arange(nz), blocks] = rates
    np.testing.assert_array_equal(d.B, expected_B)
    np.testing.assert_allclose(d.latent_equilibrium(np.arange(1.0, ny + 1)[None]), (blocks + 1.0)[None], rtol=1e-14)
    # distinct real poles of bounded stiffness, on the chain's time scale (unit stiffness, coupling 0.5)
    assert np.min(np.diff(np.sort(rates))) > 1e-3 * rates.min()
    assert rates.max() / rates.min() < MAX_SPREAD
    assert 0.5 < rates.min() and rates.max() < 6.0
    assert d.controllability_margin > 1e-5 and d.kappa == 1.0


def test_default_poles_follow_the_plants_time_scale():
    slow, fast = kc.Design.default(duffing_chain(4, 1)), kc.Design.default(duffing_chain(4, 1, speed=10.0))
    np.testing.assert_allclose(fast.A, 10.0 * slow.A, rtol=1e-12)
    np.testing.assert_allclose(fast.B, 10.0 * slow.B, rtol=1e-12)


@pytest.mark.parametrize("omega, nz", [(3.0, 5), (0.5, 4)])
def test_default_poles_of_an_oscillator_are_log_spaced_about_its_frequency(omega, nz):
    """|eig| = omega everywhere: no spread, so s = MIN_SPREAD and rate_i = omega s^((i - nz//2 + 1/2) / nz)."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    s = kc.System("osc", x, u, [omega * x[1], -omega * x[0] + u], x[0], [[-1, 1], [-1, 1]])
    d = kc.Design.default(s, nz=nz)
    expected = omega * MIN_SPREAD ** ((np.arange(nz) - nz // 2 + 0.5) / nz)
    np.testing.assert_allclose(-np.diag(d.A), expected, rtol=1e-12)
    assert not np.any(np.isclose(expected, omega))             # the plant's own rate is never a pole


def test_default_poles_of_a_plant_without_a_time_scale_lie_about_one():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    double_integrator = kc.System("di", x, u, [x[1], u], x[0], [[-1, 1], [-1, 1]])       # df/dx nilpotent
    rates = -np.diag(kc.Design.default(double_integrator).A)
    np.testing.assert_allclose(rates, MIN_SPREAD ** ((np.arange(5) - 2 + 0.5) / 5), rtol=1e-12)


def test_default_design_takes_poles_and_nz():
    plant = duffing_chain(2, 2)
    per_latent = kc.Design.default(plant, poles=[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], nz=6)
    np.testing.assert_array_equal(np.diag(per_latent.A), [-1.0, -2.0, -3.0, -4.0, -5.0, -6.0])
    np.testing.assert_array_equal(per_latent.B, [[1, 0], [2, 0], [3, 0], [0, 4], [0, 5], [0, 6]])
    per_block = kc.Design.default(plant, poles=[1.0, 2.0, 4.0, 8.0, 16.0])           # nz = 10, same in both blocks
    np.testing.assert_array_equal(np.diag(per_block.A), -np.tile([1.0, 2.0, 4.0, 8.0, 16.0], 2))
    np.testing.assert_array_equal(kc.Design.from_poles([1.0, 2.0, 3.0], 2).B, [[1, 0], [2, 0], [0, 3]])
    assert kc.Design.default(plant, nz=7).nz == 7
    with pytest.raises(ValueError, match=r"poles: expected 10 rates \(one per latent\) or 5 .*received shape \(3,\)"):
        kc.Design.default(plant, poles=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match=r"poles: expected positive rates"):
        kc.Design.from_poles([1.0, -2.0], 1)
    with pytest.raises(ValueError, match=r"nz: expected at least ny = 2"):
        kc.Design.default(plant, nz=1)
    with pytest.raises(ValueError, match=r"at lam = -2\. lam has 2 independent eigenvectors and B 1 column"):
        kc.Design.from_poles([1.0, 2.0, 2.0], 1)


@pytest.mark.parametrize("n, ny, which", [(8, 1, "default"), (2, 1, "default"), (2, 2, "default"), (2, 3, "default"),
                                          (2, 2, "paper"), (2, 3, "paper")])
def test_linear_labels_match_the_sylvester_solution(n, ny, which):
    """Phase-1 labels of a linear chain (nx = 2n) equal T x with T F - A T = B H, for one to three outputs."""
    plant, F, H = linear_chain(n, ny)
    d = getattr(kc.Design, which)(plant)
    T = solve_sylvester(-d.A, F, d.B @ H)
    x, z, y = data.phase1(plant, d, n_traj=12, seed=0, t_keep=2.0, domain_scale=1e3)
    assert z.shape == (12 * 40, ny * (4 * n + 1)) and y.shape == (12 * 40, ny)
    err = np.abs(z - x @ T.T).max() / np.abs(z).max()
    assert err < 1e-6, err


def test_min_margin_is_far_below_the_default_designs_and_far_above_rounding():
    assert 1e3 * np.finfo(float).eps < MIN_MARGIN < 1e-5


@pytest.mark.parametrize("seed", range(40))
def test_the_filter_bank_margin_is_the_svd_margin(seed):
    """Diagonal A, one output per latent (Design.from_poles, .default): the secular-equation path
    gives the general path's margin, eigenvalue and least reachable direction, also with a repeated
    pole, an undriven latent or a barely driven one."""
    from kklcasadi.plant import design as dz

    rng = np.random.default_rng(seed)
    nz, ny = int(rng.integers(1, 25)), int(rng.integers(1, 4))
    rates = rng.uniform(0.1, 10.0, nz)
    if seed % 4 == 1 and nz > 2:
        rates[1] = rates[0]
    B = np.zeros((nz, ny))
    B[np.arange(nz), rng.integers(0, ny, nz)] = rates * rng.uniform(0.5, 2.0, nz)
    if seed % 5 == 2:
        B[rng.integers(nz)] = 0.0
    if seed % 7 == 3:
        B[0][B[0] != 0] = 1e-9
    A = -np.diag(rates)
    assert dz._filter_bank(A, B)
    margin, lam, multiplicity, w = dz._pbh_filters(A, B)
    scale = np.linalg.norm(np.hstack([A, B]), 2)
    svd = [np.linalg.svd(np.hstack([A - a * np.eye(nz), B]), compute_uv=False)[-1] / scale for a in np.diag(A)]
    assert margin == pytest.approx(min(svd), rel=1e-9, abs=1e-15)
    assert svd[int(np.argmin(np.abs(np.diag(A) - lam.real)))] == pytest.approx(min(svd), rel=1e-9, abs=1e-15)
    reached = np.linalg.norm(w @ np.hstack([A - lam.real * np.eye(nz), B])) / scale
    assert np.linalg.norm(w) == pytest.approx(1.0) and reached == pytest.approx(margin, rel=1e-7, abs=1e-14)
    assert multiplicity == np.sum(np.abs(np.diag(A) - lam.real) <= 1e-4 * np.abs(A).max())
