import shutil

import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.evaluation.protocol import Profile, Protocol, evaluate, evaluate_cells
from kklcasadi.evaluation.report import score
from kklcasadi.evaluation.trialcache import TrialCache


def test_trials_are_shared_and_noise_free_variant_reuses_them():
    s = kc.systems.get("duffing")
    p = Protocol(n_trials=3, T=2.0, method="rk")
    a, b = p.trials(s, "square"), p.trials(s, "square")
    np.testing.assert_array_equal(a.y, b.y)
    clean = p.noise_free().trials(s, "square")
    np.testing.assert_array_equal(clean.x[:, 0], a.x[:, 0])
    np.testing.assert_array_equal(clean.u, a.u)
    assert not np.array_equal(clean.y, a.y)
    amps = [float(sig.amplitude[0]) for sig in p.signals(s, "square")]
    assert all(0.1 <= a_ <= 1.0 for a_ in amps)
    assert not np.array_equal(p.trials(s, "sinusoid").u, a.u)


def test_evaluate_scores_a_zero_estimator_at_200_percent():
    s = kc.systems.get("vdp")
    p = Protocol(n_trials=2, T=6.0, method="rk").noise_free()
    cache = TrialCache(None)
    truth = {kind: p.trials(s, kind) for kind in ("zero", "constant")}
    res = evaluate(lambda t, y, u: np.zeros(y.shape[:2] + (2,)), s, p, ("zero", "constant"), trials=cache)
    assert [r.kind for r in res] == ["zero", "constant"]
    np.testing.assert_allclose(res[0].smape, 200.0)
    kept = cache.trials(s, p.cell("zero"))                       # from memory: the very batch evaluate scored
    assert kept is cache.trials(s, p.cell("zero"))
    np.testing.assert_array_equal(kept.x, truth["zero"].x)


def test_evaluate_with_a_trial_cache_scores_exactly_as_without(tmp_path):
    s = kc.systems.get("vdp")
    p = Protocol(n_trials=2, T=6.0, method="rk")
    kinds = ("zero", "sinusoid")

    def first_state_is_y(t, y, u):
        return np.concatenate([y, np.zeros_like(y)], axis=2)

    plain = evaluate(first_state_is_y, s, p, kinds)
    cache = TrialCache(tmp_path)
    filled = evaluate(first_state_is_y, s, p, kinds, trials=cache)
    assert sorted(f.name for f in tmp_path.iterdir()) == sorted(cache.path(s, p.cell(k)).name for k in kinds)
    read = evaluate(first_state_is_y, s, p, kinds, trials=TrialCache(tmp_path), progress="vdp test")
    for a, b, c in zip(plain, filled, read):
        np.testing.assert_array_equal(a.smape, b.smape)
        np.testing.assert_array_equal(a.smape, c.smape)
        np.testing.assert_array_equal(a.rmse_after, c.rmse_after)


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")
def test_the_fast_estimators_score_exactly_as_the_reference_path(model_dir_factory, tmp_path):
    from kklcasadi.estimators.ekf import EKF
    from kklcasadi.evaluation.compiled import Compiler, ekf_estimator, observer_estimator
    from kklcasadi.evaluation.report import score
    from kklcasadi.observer.kkl import load_observer

    obs = load_observer(model_dir_factory("inject", base=True))
    p = Protocol(n_trials=3, T=6.0, method="rk")
    kinds = ("constant", "square")
    fast = score("inject", observer_estimator(obs, compiler=Compiler(cache_dir=tmp_path)), obs.system, p, kinds=kinds)
    slow = score("inject", lambda t, y, u: obs.simulate(t, y, u).xhat, obs.system, p, kinds=kinds)
    ekf = EKF(obs.system, p.dt)
    fast_ekf = score("EKF", ekf_estimator(ekf, compiler=Compiler(cache_dir=tmp_path)), obs.system, p, kinds=kinds)
    slow_ekf = score("EKF", lambda t, y, u: ekf.simulate(t, y, u).xhat, obs.system, p, kinds=kinds)
    for a, b in ((fast, slow), (fast_ekf, slow_ekf)):
        assert list(a.results) == list(b.results) == [(n, k) for n in (False, True) for k in kinds]
        for cell in a.results:
            np.testing.assert_array_equal(a.results[cell].smape, b.results[cell].smape)


def _first_state_is_y(t, y, u):
    return np.concatenate([y, np.zeros_like(y)], axis=2)


class _SharingEstimator:
    """Says it shares the work of trials with the same inputs; records the trials of each call."""

    shares_inputs = True

    def __init__(self):
        self.calls = []

    def __call__(self, t, y, u):
        self.calls.append(y.shape[0])
        return _first_state_is_y(t, y, u)


def test_the_noise_columns_of_a_regime_go_in_one_call_and_score_as_cell_by_cell(tmp_path):
    s = kc.systems.get("vdp")
    p = Protocol(n_trials=3, T=6.0, method="rk")
    kinds = ("zero", "square")
    sharing = _SharingEstimator()
    profile = Profile()
    together = score("y", sharing, s, p, kinds=kinds, trials=TrialCache(tmp_path), profile=profile)
    apart = score("y", _first_state_is_y, s, p, kinds=kinds)
    assert sharing.calls == [6, 6]                                     # clean and noisy cells of a regime at once
    assert list(together.results) == list(apart.results) == [(n, k) for n in (False, True) for k in kinds]
    for cell in apart.results:
        np.testing.assert_array_equal(together.results[cell].smape, apart.results[cell].smape)
        np.testing.assert_array_equal(together.results[cell].rmse_after, apart.results[cell].rmse_after)
    assert {"simulate", "estimate", "score"} <= set(profile.wall)
    again = Profile()
    evaluate_cells(_first_state_is_y, s, [p.cell("zero")], trials=TrialCache(tmp_path), profile=again)
    assert "read" in again.wall and "simulate" not in again.wall
    with pytest.raises(ValueError, match="cells: expected the same sample times"):
        evaluate_cells(_first_state_is_y, s, [p.cell("zero"), Protocol(n_trials=3, T=4.0, method="rk").cell("zero")])


def _boxed_plant() -> kc.System:
    """A stable first-order plant whose input lives in [10, 20] (its rest point at u = 15 is x = 0)."""
    import casadi as ca
    x, u = ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    return kc.System("boxed", x, u, -x + 0.1 * (u - 15.0), x, [[-1.0, 1.0]], u_box=[[10.0, 20.0]])


@pytest.mark.parametrize("kind", ["zero", "constant", "sinusoid", "square"])
def test_a_plant_with_a_u_box_is_scored_on_inputs_in_its_box(kind):
    """The protocol's id families span the u_box's central half (not the benchmark's |u| <= 1 around 0); the ood
    ones the whole box; the held-out families (a PD loop included) the same way."""
    from kklcasadi.evaluation.generalisation import Case, Settings
    plant = _boxed_plant()
    batch = Protocol(n_trials=4, T=3.0, method="rk").trials(plant, kind)
    assert np.all(batch.u >= 12.5 - 1e-12) and np.all(batch.u <= 17.5 + 1e-12)
    if kind == "zero":
        np.testing.assert_array_equal(batch.u, 15.0)
    ood = Protocol(n_trials=8, T=3.0, method="rk", regime="ood").trials(plant, kind)
    assert np.all(ood.u >= 10.0 - 1e-12) and np.all(ood.u <= 20.0 + 1e-12)
    if kind != "zero":
        assert np.abs(ood.u - 15.0).max() > 2.5                   # beyond the central half
    settings = Settings(n_trials=4, T=3.0, method="rk")
    for family in ("chirp", "random", "feedback"):
        held = Case(family, "held_out", 0.1).cell(settings).simulate(plant)
        assert np.all(held.u >= 12.5 - 1e-12) and np.all(held.u <= 17.5 + 1e-12), family
        assert held.u.std() > 0, family
