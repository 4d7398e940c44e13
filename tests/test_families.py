"""The input families of docs/protocol.md "Generalisation": samplers, the PD law, closed-loop simulation."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import kklcasadi as kc
from kklcasadi.plant import signals as sig
from kklcasadi.plant.simulate import simulate_batch


def test_sample_draws_what_it_drew_before():
    """The protocol's sampler goes through draw() now; its random stream is the one it always used."""
    for kind, regime in [("constant", "id"), ("sinusoid", "ood"), ("square", "train")]:
        a, b = np.random.default_rng(7), np.random.default_rng(7)
        got = [sig.sample(kind, a, regime, nu=2) for _ in range(5)]
        r = sig.RANGES[regime][kind]
        for s in got:
            if kind == "constant":
                np.testing.assert_array_equal(s.value, b.uniform(*r["value"], size=2))
            else:
                np.testing.assert_array_equal(s.amplitude, b.uniform(*r["amplitude"], size=2))
                assert s.omega == b.uniform(*r["omega"]) and s.phase == b.uniform(0.0, 2 * np.pi)


@pytest.mark.parametrize("kind", ["chirp", "random", "feedback"])
def test_held_out_families_respect_their_ranges(kind):
    ranges = sig.family_ranges(kind, "held_out")
    rng = np.random.default_rng(1)
    draws = [sig.draw(kind, rng, ranges, horizon=20.0, output_range=([-2.0], [4.0])) for _ in range(40)]
    t = np.arange(400) * 0.05
    for d in draws:
        if kind == "chirp":
            assert ranges["amplitude"][0] <= d.amplitude[0] <= ranges["amplitude"][1]
            assert ranges["omega0"][0] <= d.omega0 <= ranges["omega0"][1]
            assert ranges["omega1"][0] <= d.omega1 <= ranges["omega1"][1] and d.duration == 20.0
        elif kind == "random":
            assert np.all(np.abs(d(t)) <= d.amplitude) and ranges["hold"][0] <= d.hold <= ranges["hold"][1]
        else:
            r = d.reference(t)                   # set points within +-0.5 of the half-range about the centre 1
            assert np.all((r >= 1.0 - 1.5) & (r <= 1.0 + 1.5))
            for name in ("kp", "kd", "tau", "u_max"):
                assert ranges[name][0] <= getattr(d, name)[0] <= ranges[name][1]
    assert len({float(d(t).sum()) if kind != "feedback" else float(d.reference(t).sum()) for d in draws}) == 40


def test_family_errors():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match=r"^output_range: expected the \(low, high\) ends"):
        sig.draw("feedback", rng, sig.family_ranges("feedback", "held_out"))
    with pytest.raises(ValueError, match=r"^ranges: expected the parameters \['amplitude', 'hold'\]"):
        sig.draw("random", rng, {"amplitude": (0, 1)})
    with pytest.raises(ValueError, match=r"^ranges\['hold'\]: expected finite \(lo, hi\) with lo <= hi"):
        sig.draw("random", rng, {"amplitude": (0, 1), "hold": (3.0, 1.0)})
    with pytest.raises(ValueError, match=r"^regime: expected a regime that defines family 'chirp'"):
        sig.family_ranges("chirp", "train")
    with pytest.raises(ValueError, match=r"^kp: expected a scalar or 1 entries"):
        sig.PDFeedback(sig.Zero(1), kp=[1.0, 2.0])
    with pytest.raises(ValueError, match=r"^u_max: expected a finite number > 0"):
        sig.PDFeedback(sig.Zero(1), u_max=0.0)
    assert sig.family_ranges("zero", "ood") == {} and sig.family_ranges("square", "ood") == sig.RANGES["ood"]["square"]


def test_random_steps_offset():
    a = sig.RandomSteps(0.5, 1.0, seed=3, horizon=5.0)
    b = sig.RandomSteps(0.5, 1.0, seed=3, horizon=5.0, offset=2.0)
    np.testing.assert_array_equal(b.levels, a.levels + 2.0)


def pd_reference(y, r, kp, kd, tau, u_max, dt):
    """The PD law of the docs, written out sample by sample."""
    alpha = 1.0 - np.exp(-dt / tau)
    yf_prev, out = y[0], []
    for yk, rk in zip(y, r):
        yf = yf_prev + alpha * (yk - yf_prev)
        out.append(np.clip(kp * (rk - yk) - kd * (yf - yf_prev) / dt, -u_max, u_max))
        yf_prev = yf
    return np.array(out)


def test_pd_law_matches_its_definition():
    law = sig.PDFeedback(sig.RandomSteps(0.8, 2.0, seed=1, horizon=10.0), kp=1.7, kd=0.6, tau=0.25, u_max=0.4)
    rng = np.random.default_rng(2)
    y, t = rng.normal(size=200), np.arange(200) * 0.05
    r = law.reference(t)[:, 0]
    f, c, u = law.function(0.05), law.state0(y[:1]), []
    for k in range(200):
        uk, c = f(c, y[k], r[k], law.theta())
        u.append(float(uk))
    expected = pd_reference(y, r, 1.7, 0.6, 0.25, 0.4, 0.05)
    np.testing.assert_allclose(u, expected, rtol=1e-13, atol=1e-15)
    assert np.mean(np.abs(expected) == 0.4) > 0.2                       # the saturation is exercised


@pytest.mark.parametrize("method", ["cvodes", "rk"])
def test_closed_loop_applies_the_law_to_the_measured_output(method):
    """u_k is the law of the recorded noisy y_k, and replaying those inputs open loop gives the same run."""
    plant = kc.systems.get("duffing")
    rng = np.random.default_rng(4)
    laws = [sig.draw("feedback", rng, sig.family_ranges("feedback", "held_out"), horizon=10.0,
                     output_range=([-1.0], [1.0])) for _ in range(3)]
    x0 = plant.sample_box(3, 0)
    seeds = np.random.SeedSequence(9).spawn(3)
    batch = simulate_batch(plant, x0, laws, 10.0, 0.05, process_std=0.1, measurement_std=0.1, seed=seeds,
                           method=method)
    assert batch.ok.all()
    for i, law in enumerate(laws):
        expected = pd_reference(batch.y[i, :, 0], law.reference(batch.t)[:, 0], law.kp[0], law.kd[0], law.tau[0],
                                law.u_max[0], 0.05)
        np.testing.assert_allclose(batch.u[i, :, 0], expected, rtol=1e-12, atol=1e-14)
        replay = simulate_batch(plant, x0[i:i + 1], batch.u[i], 10.0, 0.05, process_std=0.1, measurement_std=0.1,
                                seed=[seeds[i]], method=method)
        np.testing.assert_array_equal(replay.x[0], batch.x[i])
        np.testing.assert_array_equal(replay.y[0], batch.y[i])


def test_closed_loop_tracks_the_set_point_noise_free():
    """Noise-free, a constant set point, unsaturated: Duffing settles where x1 + x1^3 = kp (r - x1),
    as solve_ivp of the continuous PD loop (with the derivative on x2) says, to the sampling error."""
    plant = kc.systems.get("duffing")
    law = sig.PDFeedback(sig.Constant(0.3), kp=2.0, kd=1.0, tau=0.05, u_max=10.0)
    tr = kc.simulate(plant, [0.0, 0.0], law, T=30.0, dt=0.01)
    sol = solve_ivp(lambda _t, x: [x[1], -x[0] - x[0] ** 3 + 2.0 * (0.3 - x[0]) - 1.0 * x[1]], (0, 30.0),
                    [0.0, 0.0], rtol=1e-10, atol=1e-12)
    settle = np.roots([1.0, 0.0, 3.0, -0.6]).real[np.abs(np.roots([1.0, 0.0, 3.0, -0.6]).imag) < 1e-12][0]
    np.testing.assert_allclose(tr.x[-1, 0], settle, atol=1e-3)
    np.testing.assert_allclose(sol.y[0, -1], settle, atol=1e-6)


def test_closed_loop_refuses_mixed_inputs_and_wrong_sizes():
    plant = kc.systems.get("duffing")
    law = sig.PDFeedback(sig.Zero(1))
    with pytest.raises(TypeError, match=r"^u: expected signals or arrays for every trial, or output-feedback laws"):
        simulate_batch(plant, np.zeros((2, 2)), [law, sig.Zero(1)], 1.0, 0.05)
    with pytest.raises(ValueError, match=r"^u\[0\]: expected an output-feedback law of one input per output"):
        simulate_batch(plant, np.zeros((1, 2)), [sig.PDFeedback(sig.Zero(2))], 1.0, 0.05)
