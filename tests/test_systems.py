import json
import re
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import kklcasadi as kc

PAPER = {  # docs/protocol.md table: (nx, nz, y index, box)
    "duffing": (2, 5, 0, [[-1, 1], [-1, 1]]),
    "vdp": (2, 5, 0, [[-3, 3], [-3, 3]]),
    "rossler": (3, 7, 1, [[-10, 10]] * 3),
    "fhn": (2, 5, 0, [[-2.5, 2.5], [-1.5, 1.5]]),
}


def reference_f(name, x, u):
    x1, x2 = x[0], x[1]
    if name == "duffing":
        return [x2, -x1 - x1 ** 3 + u]
    if name == "vdp":
        return [x2, (1 - x1 ** 2) * x2 - x1 + u]
    if name == "rossler":
        return [-(x[1] + x[2]), x[0] + 0.1 * x[1] + u, 0.1 + x[2] * (x[0] - 14)]
    if name == "fhn":
        return [10 * (x1 - x1 ** 3 - x2) + u, 1.5 * x1 - x2 + 0.8]
    if name == "lorenz":
        return [10 * (x[1] - x[0]), x[0] * (28 - x[2]) - x[1] + u, x[0] * x[1] - 8 / 3 * x[2]]
    raise KeyError(name)


@pytest.mark.parametrize("name", ["duffing", "vdp", "rossler", "fhn", "lorenz"])
def test_registry_matches_protocol_equations(name, rng):
    s = kc.systems.get(name)
    for _ in range(5):
        x = rng.uniform(-2, 2, s.nx)
        u = rng.uniform(-1, 1)
        np.testing.assert_allclose(np.asarray(s.f(x, u)).ravel(), reference_f(name, x, u), rtol=1e-14, atol=1e-14)
    if name in PAPER:
        nx, nz, iy, box = PAPER[name]
        assert (s.nx, s.nu, s.ny) == (nx, 1, 1)
        assert s.paper_design and kc.Design.paper(s).nz == nz
        np.testing.assert_array_equal(s.x0_box, box)
        x = rng.uniform(-2, 2, s.nx)
        assert float(s.h(x)) == x[iy]


@pytest.mark.parametrize("name", ["duffing", "vdp", "rossler", "fhn", "lorenz", "linear"])
def test_exact_jacobians_match_finite_differences(name, rng):
    s = kc.systems.get(name)
    x = rng.uniform(-1, 1, s.nx)
    u = rng.uniform(-1, 1, s.nu)
    dfdx, dfdu = (np.asarray(a) for a in s.f_jac(x, u))
    eps = 1e-6
    fd = np.column_stack([(np.asarray(s.f(x + eps * e, u)) - np.asarray(s.f(x - eps * e, u))).ravel() / (2 * eps)
                          for e in np.eye(s.nx)])
    np.testing.assert_allclose(dfdx, fd, rtol=1e-6, atol=1e-6)
    fdu = (np.asarray(s.f(x, u + eps)) - np.asarray(s.f(x, u - eps))).ravel() / (2 * eps)
    np.testing.assert_allclose(dfdu.ravel(), fdu, rtol=1e-6, atol=1e-6)
    assert np.asarray(s.h_jac(x)).shape == (s.ny, s.nx)


def test_user_plant_in_a_few_lines():
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u")
    pend = kc.System("pend", x, u, [x[1], -ca.sin(x[0]) - 0.1 * x[1] + u], x[0], x0_box=[[-1, 1], [-2, 2]])
    assert (pend.nx, pend.nu, pend.ny) == (2, 1, 1)
    np.testing.assert_allclose(np.asarray(pend.f([0.3, 0.1], 0.5)).ravel(), [0.1, -np.sin(0.3) - 0.01 + 0.5])
    kc.systems.register("pend_test", lambda: pend)
    assert "pend_test" in kc.systems.names()
    assert kc.systems.get("pend_test") is pend


def test_bad_plants_are_rejected():
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u")
    with pytest.raises(ValueError, match=r"x0_box: expected rows \[lo, hi\] with lo < hi \(rows \[0\]"):
        kc.System("p", x, u, [x[1], -x[0]], x[0], x0_box=[[1, -1], [0, 1]])
    with pytest.raises(ValueError, match=r"x0_box: expected rows \[lo, hi\] with lo < hi \(rows \[0\]"):
        kc.System("p", x, u, [x[1], -x[0]], x[0], x0_box=[[0, 0], [0, 1]])
    with pytest.raises(ValueError, match=r"x0_box: expected shape \(nx, 2\)"):
        kc.System("p", x, u, [x[1], -x[0]], x[0], x0_box=[[-1, 1]])
    with pytest.raises(ValueError, match=r"y: expected an output map h\(x\) that does not depend on the input u"):
        kc.System("p", x, u, [x[1], -x[0]], x[0] + u, x0_box=[[-1, 1], [-1, 1]])
    with pytest.raises(ValueError, match="xdot: expected 2 entries"):
        kc.System("p", x, u, [x[1]], x[0], x0_box=[[-1, 1], [-1, 1]])
    with pytest.raises(TypeError, match=r"x: expected a casadi\.SX symbol"):
        kc.System("p", np.zeros(2), u, [x[1], -x[0]], x[0], x0_box=[[-1, 1], [-1, 1]])
    with pytest.raises(ValueError, match=r"xdot, y: expected .*symbols of x and u only.*free symbols \['k'\]"):
        kc.System("p", x, u, [x[1], -ca.SX.sym("k") * x[0]], x[0], x0_box=[[-1, 1], [-1, 1]])
    with pytest.raises(ValueError, match=r"name: expected one of \['duffing'"):
        kc.systems.get("dufing")


def test_check_state_names_the_argument():
    s = kc.systems.get("duffing")
    with pytest.raises(ValueError, match=r"x0: expected shape \(2,\)"):
        s.check_state([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="x0: expected finite values"):
        s.check_state([np.nan, 0.0])


def test_sample_box_is_seeded_and_inside():
    s = kc.systems.get("fhn")
    a = s.sample_box(64, 3)
    np.testing.assert_array_equal(a, s.sample_box(64, 3))
    assert np.all(a >= s.x0_box[:, 0]) and np.all(a <= s.x0_box[:, 1])
    # Latin hypercube: one sample per stratum in every coordinate
    strata = np.floor((a - s.x0_box[:, 0]) / (s.x0_box[:, 1] - s.x0_box[:, 0]) * 64).astype(int)
    for i in range(s.nx):
        assert sorted(strata[:, i]) == list(range(64))


def _pendulum(**angles):
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    return kc.System("pend", x, u, [x[1], -ca.sin(x[0]) + u], ca.vertcat(x[0], x[1]), [[-3, 3], [-2, 2]], **angles)


def test_angle_indices_are_stored_sorted_and_enter_the_fingerprint_only_when_given():
    plain = _pendulum()
    assert plain.angle_states == () and plain.angle_outputs == ()
    marked = _pendulum(angle_states=[0], angle_outputs=np.array([0]))
    assert marked.angle_states == (0,) and marked.angle_outputs == (0,)
    assert _pendulum(angle_states=(), angle_outputs=()).fingerprint == plain.fingerprint
    prints = {plain.fingerprint, marked.fingerprint, _pendulum(angle_states=(0,)).fingerprint,
              _pendulum(angle_outputs=(0,)).fingerprint, _pendulum(angle_states=(0, 1)).fingerprint}
    assert len(prints) == 5
    assert _pendulum(angle_states=(1, 0)).angle_states == (0, 1)
    assert _pendulum(angle_states=(1, 0)).fingerprint == _pendulum(angle_states=(0, 1)).fingerprint


def test_u_box_is_stored_read_only_and_enters_the_fingerprint_only_when_given():
    plain = _pendulum()
    boxed = _pendulum(u_box=[[-4.5, 6.0]])
    assert plain.u_box is None
    np.testing.assert_array_equal(boxed.u_box, [[-4.5, 6.0]])
    assert not boxed.u_box.flags.writeable
    # the dynamics are the same; what the plant declares about its rig is not
    prints = {plain.fingerprint, boxed.fingerprint, _pendulum(u_box=[[-4.5, 6.5]]).fingerprint}
    assert len(prints) == 3
    assert _pendulum(u_box=np.array([[-4.5, 6.0]])).fingerprint == boxed.fingerprint
    assert boxed.definition_digest != plain.definition_digest


@pytest.mark.parametrize("u_box, words", [
    ([[-1, 1], [-1, 1]], r"u_box: expected shape \(nu, 2\) = \(1, 2\)"),
    ([[1, -1]], r"u_box: expected rows \[lo, hi\] with lo < hi \(rows \[0\]"),
    ([[0, np.inf]], "u_box: expected finite bounds"),
])
def test_bad_u_box_is_rejected_naming_it(u_box, words):
    with pytest.raises(ValueError, match=words):
        _pendulum(u_box=u_box)


@pytest.mark.parametrize("angles, kind, words", [
    ({"angle_states": (2,)}, ValueError, "angle_states: expected a sequence of distinct indices in [0, 2)"),
    ({"angle_states": (0, 0)}, ValueError, "repeated"),
    ({"angle_outputs": (-1,)}, ValueError, "angle_outputs: expected"),
    ({"angle_states": 0}, TypeError, "received int"),
    ({"angle_states": "0"}, TypeError, "received str"),
    ({"angle_outputs": (True,)}, TypeError, "of type bool"),
    ({"angle_states": (0.0,)}, TypeError, "of type float"),
])
def test_bad_angle_indices_are_rejected(angles, kind, words):
    with pytest.raises(kind, match=re.escape(words)):
        _pendulum(**angles)


def _shipped_fingerprints():
    root = Path(__file__).resolve().parents[1] / "models"
    found = {}
    for card in sorted(root.glob("*/*/card.json")):
        system = json.loads(card.read_text())["system"]
        found.setdefault(system["name"], set()).add(system["fingerprint"])
    return found


@pytest.mark.parametrize("name", sorted(_shipped_fingerprints()))
def test_registry_fingerprints_equal_the_shipped_cards(name):
    assert {kc.systems.get(name).fingerprint} == _shipped_fingerprints()[name]
