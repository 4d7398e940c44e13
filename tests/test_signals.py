import numpy as np
import pytest

from kklcasadi.plant import signals as sig


def test_square_matches_definition():
    u = sig.make("square", amplitude=0.5, omega=1.0, phase=0.3)
    t = np.linspace(0, 20, 401)
    np.testing.assert_array_equal(u(t)[:, 0], 0.5 * np.sign(np.sin(t + 0.3)))
    assert u(1.0).shape == (1,)
    assert u(t).shape == (401, 1)


@pytest.mark.parametrize("kind, params, t, expected", [
    ("zero", {}, 3.0, [0.0]),
    ("constant", {"value": [0.2, -0.1]}, 7.0, [0.2, -0.1]),
    ("sinusoid", {"amplitude": 2.0, "omega": 0.5, "phase": 0.1}, 3.0, [2.0 * np.sin(1.5 + 0.1)]),
    ("step", {"time": 2.0, "before": 0.0, "after": 1.5}, 1.999, [0.0]),
    ("step", {"time": 2.0, "before": 0.0, "after": 1.5}, 2.0, [1.5]),
    ("chirp", {"amplitude": 1.0, "omega0": 1.0, "omega1": 3.0, "duration": 10.0}, 4.0, [np.sin(4.0 + 0.1 * 16)]),
])
def test_signal_values(kind, params, t, expected):
    np.testing.assert_allclose(sig.make(kind, **params)(t), expected, rtol=1e-14)


def test_chirp_frequency_holds_after_duration():
    u = sig.make("chirp", amplitude=1.0, omega0=1.0, omega1=3.0, duration=10.0)
    phase_at_end = 10.0 + 0.1 * 100
    np.testing.assert_allclose(u(12.0), [np.sin(phase_at_end + 3.0 * 2.0)], rtol=1e-13)


def test_random_steps_are_seeded_and_piecewise_constant():
    a = sig.make("random", amplitude=0.8, hold=0.5, seed=3, horizon=10.0)
    b = sig.make("random", amplitude=0.8, hold=0.5, seed=3, horizon=10.0)
    t = np.linspace(0, 12, 1201)
    np.testing.assert_array_equal(a(t), b(t))
    assert np.all(np.abs(a(t)) <= 0.8)
    np.testing.assert_array_equal(a(np.array([1.0, 1.2, 1.49])), np.repeat(a(1.0)[None], 3, axis=0))
    assert not np.array_equal(a(t), sig.make("random", amplitude=0.8, hold=0.5, seed=4, horizon=10.0)(t))


def test_sampler_respects_protocol_ranges():
    rng = np.random.default_rng(0)
    for regime, amp_range, omega_range in [("id", (0.1, 1.0), (0.5, 2.0)), ("ood", (1.0, 2.0), (2.0, 4.0))]:
        for _ in range(50):
            s = sig.sample("square", rng, regime)
            assert amp_range[0] <= s.amplitude[0] <= amp_range[1]
            assert omega_range[0] <= s.omega <= omega_range[1]
            assert 0 <= s.phase <= 2 * np.pi
    c = [float(sig.sample("constant", rng, "ood").value[0]) for _ in range(200)]
    assert min(c) >= -2 and max(c) <= 2 and max(np.abs(c)) > 1
    assert isinstance(sig.sample("zero", rng), sig.Zero)
    assert sig.sample("sinusoid", rng, "train", nu=2).nu == 2


def test_sampler_is_seeded():
    a = [sig.sample("sinusoid", np.random.default_rng(5)) for _ in range(2)]
    assert a[0] == a[1]


def test_bad_signals_give_clear_errors():
    with pytest.raises(ValueError, match=r"kind: expected one of \['zero', 'constant'"):
        sig.make("sawtooth")
    with pytest.raises(ValueError, match="value: expected finite values"):
        sig.make("constant", value=np.nan)
    with pytest.raises(ValueError, match=r"omega \(rad/s\): expected a finite number > 0"):
        sig.make("square", amplitude=1.0, omega=-1.0)
    with pytest.raises(TypeError, match=r"params: expected parameters of signal 'square' among"):
        sig.make("square", amp=1.0)
    with pytest.raises(ValueError, match=r"regime: expected one of \['train', 'id', 'ood'\]"):
        sig.sample("square", np.random.default_rng(0), "test")
    with pytest.raises(TypeError, match=r"rng: expected a numpy\.random\.Generator"):
        sig.sample("square", 0)
    with pytest.raises(ValueError, match="t: expected finite times"):
        sig.make("zero")(np.array([0.0, np.inf]))


U_BOX = [[280.0, 310.0], [-3.0, 1.0]]


def test_a_drawn_input_is_mapped_onto_the_plants_u_box():
    """``in_box``: the benchmark's +-UNIT_LEVEL goes to the box's edges, so id (|v| <= 1) spans its central half."""
    offset, scale = sig.box_map(U_BOX)
    np.testing.assert_allclose(offset, [295.0, -1.0], rtol=0, atol=0)
    np.testing.assert_allclose(scale, [7.5, 1.0], rtol=0, atol=0)
    t = np.linspace(0.0, 10.0, 201)
    edges = sig.in_box(sig.make("constant", value=[2.0, -2.0]), U_BOX)(t)
    np.testing.assert_array_equal(edges, np.tile([310.0, -3.0], (t.size, 1)))
    rng = np.random.default_rng(0)
    for kind in sig.BENCHMARK_KINDS:
        for _ in range(20):
            inner = sig.sample(kind, rng, "id", nu=2)
            u = sig.in_box(inner, U_BOX)(t)
            np.testing.assert_allclose(u, offset + scale * inner(t), rtol=0, atol=1e-12)
            assert np.all(u >= [287.5 - 1e-9, -2.0 - 1e-9]) and np.all(u <= [302.5 + 1e-9, 0.0 + 1e-9]), kind
    same = sig.make("sinusoid", amplitude=1.0, omega=1.0)
    assert sig.in_box(same, None) is same                        # a plant without a u_box: the benchmark's units


def test_a_feedback_law_in_a_plants_units_sends_offset_plus_scale_times_its_input():
    law = sig.PDFeedback(sig.make("constant", value=[0.5]), kp=2.0, kd=0.0, u_max=1.0)
    mapped = sig.in_box(law, [[280.0, 310.0]])
    assert isinstance(mapped, sig.PDFeedback)
    f = mapped.function(0.05)
    for y, expected in ((0.4, 0.2), (-3.0, 1.0), (3.0, -1.0)):                  # inside and at both saturations
        u, _ = f(np.array([y]), np.array([y]), np.array([0.5]), mapped.theta())
        assert float(u) == pytest.approx(295.0 + 7.5 * expected, abs=1e-12)
        u0, _ = law.function(0.05)(np.array([y]), np.array([y]), np.array([0.5]), law.theta())
        assert float(u0) == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize("u_box, message", [([[1.0, 1.0]], "u_box"), ([[0.0, np.inf]], "u_box"),
                                            ([1.0, 2.0], "u_box")])
def test_a_bad_u_box_is_named(u_box, message):
    with pytest.raises(ValueError, match=message):
        sig.in_box(sig.make("zero", size=1), u_box)


def test_a_mapped_signal_with_the_wrong_number_of_entries_is_named():
    with pytest.raises(ValueError, match=r"offset: expected a scalar or 2 entries \(one per input\), received size 3"):
        sig.Mapped(sig.make("constant", value=[0.0, 0.0]), offset=[1.0, 2.0, 3.0], scale=1.0)
    with pytest.raises(ValueError, match="scale"):
        sig.Mapped(sig.make("zero", size=1), offset=0.0, scale=-1.0)
