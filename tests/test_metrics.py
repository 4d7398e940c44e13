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


@pytest.mark.parametrize("a, expected", [
    (np.pi, np.pi), (-np.pi, np.pi), (3 * np.pi, np.pi), (0.0, 0.0), (2 * np.pi + 0.5, 0.5),
    (-2 * np.pi - 0.5, -0.5), (7.0, 7.0 - 2 * np.pi), (-7.0, -7.0 + 2 * np.pi),
])
def test_wrap_angle_hand_values(a, expected):
    assert metrics.wrap_angle(a) == pytest.approx(expected, abs=1e-14)


def test_wrap_angle_range_and_period():
    rng = np.random.default_rng(3)
    a = rng.uniform(-50, 50, (20, 30))
    w = metrics.wrap_angle(a)
    assert w.shape == a.shape and np.all(w > -np.pi) and np.all(w <= np.pi)
    k = np.round((a - w) / (2 * np.pi))
    np.testing.assert_allclose(a - w, 2 * np.pi * k, atol=1e-12)
    assert np.isnan(metrics.wrap_angle([np.nan, np.inf])).all()


def test_defaults_are_bitwise_the_unwrapped_metrics():
    rng = np.random.default_rng(4)
    x, xh = rng.normal(size=(3, 40, 2)) * 5, rng.normal(size=(3, 40, 2)) * 5
    t = np.arange(40) * 0.5
    # the formulas of docs/protocol.md written out, compared bit for bit
    terms = 2.0 * np.abs(x - xh) / (np.abs(x) + np.abs(xh) + 1e-8)
    np.testing.assert_array_equal(metrics.smape(x, xh), 100.0 * terms.mean(axis=(-2, -1)))
    np.testing.assert_array_equal(metrics.smape(x, xh, angles=()), metrics.smape(x, xh))
    np.testing.assert_array_equal(metrics.rmse(x, xh), np.sqrt(np.mean((x - xh) ** 2, axis=(-2, -1))))
    np.testing.assert_array_equal(metrics.rmse_after(t, x, xh, 5.0, angles=()), metrics.rmse_after(t, x, xh, 5.0))


def test_angle_errors_are_wrapped_and_other_states_untouched():
    rng = np.random.default_rng(5)
    x = rng.normal(size=(50, 3))
    err = rng.uniform(-0.5, 0.5, (50, 3))
    xh = x + err
    shifted = xh.copy()
    shifted[:, 1] += 2 * np.pi * rng.integers(-3, 4, 50)          # the same angles on other branches
    assert metrics.rmse(x, shifted, angles=(1,)) == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-12)
    assert metrics.rmse(x, shifted) > 1.0
    assert metrics.smape(x, shifted, angles=[1]) == pytest.approx(metrics.smape(x, xh, angles=[1]), rel=1e-12)
    per = metrics.smape(x, shifted, angles=(1,), per_state=True)
    np.testing.assert_array_equal(per[[0, 2]], metrics.smape(x, xh, per_state=True)[[0, 2]])
    t = np.linspace(0, 10, 50)
    assert metrics.rmse_after(t, x, shifted, 5.0, angles=(1,)) == pytest.approx(
        metrics.rmse_after(t, x, xh, 5.0), rel=1e-12)
    # an error of pi - 0.1 one way is 2 pi - (pi - 0.1) the other: wrapping keeps the shorter
    a = np.zeros((1, 1))
    assert metrics.rmse(a, a + np.pi + 0.1, angles=(0,)) == pytest.approx(np.pi - 0.1, rel=1e-12)


@pytest.mark.parametrize("angles, kind", [((2,), ValueError), ((0, 0), ValueError), (1, TypeError)])
def test_bad_angle_indices_name_the_argument(angles, kind):
    x = np.zeros((4, 2))
    with pytest.raises(kind, match=r"^angles: expected a sequence of distinct indices in \[0, 2\)"):
        metrics.rmse(x, x, angles=angles)
