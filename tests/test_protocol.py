import numpy as np

import kklcasadi as kc
from kklcasadi.protocol import Protocol, evaluate


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
    cache = {}
    truth = {kind: p.trials(s, kind) for kind in ("zero", "constant")}
    res = evaluate(lambda t, y, u: np.zeros(y.shape[:2] + (2,)), s, p, ("zero", "constant"), trials=cache)
    assert [r.kind for r in res] == ["zero", "constant"]
    np.testing.assert_allclose(res[0].smape, 200.0)
    assert set(cache) == {"zero", "constant"}
    np.testing.assert_array_equal(cache["zero"].x, truth["zero"].x)
