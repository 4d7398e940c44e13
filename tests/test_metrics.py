import numpy as np
import pytest

from kklcasadi import metrics


def test_smape_hand_computed():
    x = np.array([[1.0, 2.0], [-1.0, 0.0]])
    xh = np.array([[1.0, 1.0], [1.0, 0.0]])
    # terms: 0, 2*1/3, 2*2/2 = 2, 0 (both zero -> 0/1e-8 = 0)
    expected = 100.0 / 4 * (0 + 2 / 3 + 2 + 0)
    assert metrics.smape(x, xh) == pytest.approx(expected, rel=1e-8)  # the 1e-8 guard shifts it slightly


def test_smape_per_state_hand_computed_and_averages_to_the_total():
    x = np.array([[1.0, 2.0], [-1.0, 0.0]])
    xh = np.array([[1.0, 1.0], [1.0, 0.0]])
    # state 0: terms 0 and 2 -> 100 %; state 1: terms 2/3 and 0 -> 100/3 %
    np.testing.assert_allclose(metrics.smape(x, xh, per_state=True), [100.0, 100.0 / 3], rtol=1e-8)
    rng = np.random.default_rng(1)
    xb, xhb = rng.normal(size=(4, 30, 3)), rng.normal(size=(4, 30, 3))
    per = metrics.smape(xb, xhb, per_state=True)
    assert per.shape == (4, 3)
    np.testing.assert_allclose(per.mean(axis=-1), metrics.smape(xb, xhb), rtol=1e-13)


def test_smape_batched_and_bounds():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3, 50, 2))
    out = metrics.smape(x, x)
    np.testing.assert_array_equal(out, np.zeros(3))
    assert np.all(metrics.smape(x, -x) == pytest.approx(200.0))


def test_rmse_and_rmse_after():
    t = np.arange(10) * 1.0
    x = np.zeros((10, 1))
    xh = np.where(t[:, None] < 5, 10.0, 1.0)
    assert metrics.rmse(x, xh) == pytest.approx(np.sqrt((5 * 100 + 5) / 10))
    assert metrics.rmse_after(t, x, xh, 5.0) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="t_settle: expected a time at or before the last sample"):
        metrics.rmse_after(t, x, xh, 100.0)


def test_summary():
    s = metrics.summarize([1.0, 2.0, 3.0, 4.0, np.nan])
    assert (s.mean, s.median, s.n, s.n_failed) == (2.5, 2.5, 4, 1)
    assert s.iqr == pytest.approx(1.5)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match=r"xhat: expected the same shape as x_true \(5, 2\)"):
        metrics.smape(np.zeros((5, 2)), np.zeros((5, 3)))
