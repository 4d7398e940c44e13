import numpy as np
import pytest

import kklcasadi as kc


@pytest.mark.parametrize("name, nz", [("duffing", 5), ("rossler", 7), ("lorenz", 7)])
def test_default_design_is_the_papers(name, nz):
    d = kc.Design.default(kc.systems.get(name))
    np.testing.assert_array_equal(d.A, -np.diag(np.arange(1, nz + 1)))
    np.testing.assert_array_equal(d.B, np.ones((nz, 1)))
    assert d.nz == nz and d.ny == 1
    assert d.lam == pytest.approx(1.0)
    assert d.kappa == pytest.approx(1.0)


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
    d = kc.Design.default(kc.systems.get("duffing"))
    with pytest.raises(ValueError):
        d.A[0, 0] = 1.0
    with pytest.raises(AttributeError):
        d.A = np.eye(5)


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
