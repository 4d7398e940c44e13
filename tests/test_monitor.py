"""The decoder-input domain monitor: calibration, the model file, the observer, C and the VM."""
import json
import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest
from conftest import bank_runs

import kklcasadi as kc
from kklcasadi.model import monitor as mon
from kklcasadi.model.files import CARD_FILE, load_model, save_model
from kklcasadi.observer.kkl import load_observer

GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc is not installed")


def curve(rng, n, noise=0.05):
    """Samples near the curve (s, s^2, sin 3s) with noise on the second coordinate only."""
    s = rng.uniform(-1, 1, n)
    return np.column_stack([s, s ** 2 + noise * rng.normal(size=n), np.sin(3.0 * s)])


def brute_distance(monitor, f):
    """The distance written out: min_j ||L f - P_j|| / r_j (independent of the monitor's algebra)."""
    g = f @ monitor.metric.T
    return np.array([np.min(np.linalg.norm(monitor.prototypes - gi, axis=1) / monitor.radii) for gi in g])


def test_calibration_flags_its_quantile_of_fresh_samples(rng):
    monitor = mon.calibrate(curve(rng, 20000), curve(rng, 20000), n_prototypes=400, quantile=0.95, seed=1)
    fresh = curve(np.random.default_rng(99), 20000)
    false_alarm = 1.0 - monitor.inside(fresh).mean()
    assert abs(false_alarm - 0.05) < 0.01                       # 5 % +- 4.6 binomial sigmas of 20 000 samples
    np.testing.assert_allclose(monitor.distance(fresh[:500]), brute_distance(monitor, fresh[:500]), rtol=1e-9,
                               atol=1e-9)
    assert monitor.spec.prototypes == 400 and monitor.spec.features == 3
    assert monitor.spec.calibration["fit_samples"] == 20000


def test_the_metric_weighs_directions_the_fitting_data_never_leave(rng):
    """A step of twice the noise off the curve along its noise-free third coordinate is flagged; a
    step of the noise's size along the noisy coordinate is not; the global whitening (no rounds of
    the metric) misses a good part of the first."""
    fit, validation = curve(rng, 20000), curve(rng, 20000)
    monitor = mon.calibrate(fit, validation, n_prototypes=2000, quantile=0.99, seed=1)
    plain = mon.calibrate(fit, validation, n_prototypes=2000, quantile=0.99, seed=1, iterations=0)
    base = curve(np.random.default_rng(5), 2000)
    along_noise, off_curve = base + [0.0, 0.05, 0.0], base + [0.0, 0.0, 0.1]
    assert monitor.inside(along_noise).mean() > 0.9 and monitor.inside(off_curve).mean() < 0.05
    assert plain.inside(off_curve).mean() > 0.2


def test_the_casadi_expression_is_the_numpy_test(rng):
    monitor = mon.calibrate(curve(rng, 5000), curve(rng, 5000), n_prototypes=200, seed=2)
    f = ca.MX.sym("f", 3)
    check = ca.Function("check", [f], [monitor.expression(f)])
    points = np.vstack([curve(rng, 300), rng.uniform(-1.5, 1.5, (300, 3))])
    distance = monitor.distance(points)
    clear = np.abs(distance - monitor.spec.threshold) > 1e-9 * monitor.spec.threshold   # no exact ties
    flags = np.array([float(check(p)) for p in points])
    np.testing.assert_array_equal(flags[clear] > 0.5, monitor.inside(points)[clear])
    assert 0.2 < flags.mean() < 0.9


def test_calibrate_runs_splits_by_run(rng):
    runs = np.stack([curve(rng, 200) for _ in range(10)])                 # (10 runs, 200 samples, 3)
    t = np.arange(200) * 0.05
    monitor = mon.calibrate_runs(runs, t, n_prototypes=100, validation_share=0.2, stride=2, settle_time=5.0)
    record = monitor.spec.calibration
    assert (record["fit_runs"], record["validation_runs"], record["stride"]) == (8, 2, 2)
    assert record["fit_samples"] == 8 * 100 and record["validation_samples"] == 2 * 50   # t >= 5 s: samples 100..199
    with pytest.raises(ValueError, match=r"^n_prototypes: expected fewer than the 800 fitting samples"):
        mon.calibrate_runs(runs, t, n_prototypes=800)


# ----------------------------------------------------------------------------- in a model file

def test_a_monitor_round_trips_through_the_model_file(monitored_bank):
    path, monitor = monitored_bank
    model = load_model(path)
    assert model.spec.monitor == monitor.spec
    assert model.spec.fit_families == {"zero": {}, "constant": {"value": (-1.0, 1.0)}}
    np.testing.assert_array_equal(model.arrays[mon.PROTOTYPES], monitor.prototypes)
    np.testing.assert_array_equal(model.arrays[mon.RADII], monitor.radii)
    obs = load_observer(path)
    np.testing.assert_array_equal(obs.monitor.metric, monitor.metric)


def test_the_observer_flags_what_the_monitor_flags(monitored_bank):
    """Estimate.in_domain, obs.in_domain, the VM's domain_check per sample and the live estimator's
    stats agree with the monitor's own test of the decoder's features."""
    path, monitor = monitored_bank
    obs = load_observer(path)
    runs = bank_runs(n=4, T=5.0, seed=8)
    plant = obs.system
    runs_far = kc.simulate_batch(plant, plant.sample_box(2, 1), [kc.signals.make("square", amplitude=2.0, omega=4.0)]
                                 * 2, 5.0, 0.05, process_std=0.1, measurement_std=0.1, seed=1, method="rk")
    y, u = np.concatenate([runs.y, runs_far.y]), np.concatenate([runs.u, runs_far.u])
    est = obs.simulate(runs.t, y, u)
    w = np.concatenate([y, u], axis=-1)[..., None]                           # bank memory [y_k; u_k] (2, 1)
    features = np.concatenate([est.z, y, u], axis=-1)
    assert obs.domain is None                             # the factory's card has no box: the feature test alone
    np.testing.assert_array_equal(est.in_domain, monitor.inside(features))
    np.testing.assert_array_equal(est.in_domain, obs.in_domain(est.xhat, est.z, w))
    assert est.in_domain[:4].mean() > 0.7 and est.in_domain[4:].mean() < est.in_domain[:4].mean()
    vm = np.array([[float(obs.domain_check(est.z[i, k], w[i, k], est.xhat[i, k])) for k in range(0, 100, 7)]
                   for i in range(6)])
    np.testing.assert_array_equal(vm > 0.5, est.in_domain[:, ::7])
    live = obs.estimator()
    for k in range(runs.t.size):
        live.make_step(y[4, k], u[4, k])
        assert live.stats["in_domain"] == est.in_domain[4, k]
    assert live.stats["out_of_domain_steps"] == int((~est.in_domain[4]).sum())
    with pytest.raises(ValueError, match=r"^w: expected the observer's memory"):
        obs.in_domain(est.xhat, est.z)


@needs_gcc
def test_c_in_domain_equals_the_vm(monitored_bank, tmp_path):
    path, monitor = monitored_bank
    obs = load_observer(path)
    files = kc.generate_c(obs, tmp_path / "c", "mon", math="libm")
    header = files[1].read_text()
    assert "#define MON_HAS_FEATURE_MONITOR 1" in header and "arg[1] w (NW), arg[2] xhat (NX)" in header
    library = tmp_path / "libmon.so"
    subprocess.run([GCC, "-std=c99", "-O2", "-fPIC", "-shared", str(files[0]), "-o", str(library), "-lm"], check=True)
    check = ca.external("mon_in_domain", str(library))
    runs = bank_runs(n=4, T=5.0, seed=9)
    est = obs.simulate(runs.t, runs.y, runs.u)
    rng = np.random.default_rng(0)
    points = [(est.z[i, k], np.array([runs.y[i, k, 0], runs.u[i, k, 0]]), est.xhat[i, k])
              for i in range(4) for k in range(0, 100, 3)]
    points += [(z + rng.normal(0, 0.3, z.shape), w, x) for z, w, x in points[:60]]
    c_flags = [float(check(z, w, x)) for z, w, x in points]
    assert c_flags == [float(obs.domain_check(z, w, x)) for z, w, x in points]
    assert 0 < sum(c_flags) < len(points)


@pytest.mark.parametrize("edit, message", [
    (lambda c, a: c["monitor"].update(kind="gaussian"), r"'monitor\.kind': expected 'nearest_prototype'"),
    (lambda c, a: c["monitor"].update(threshold=-1.0), r"'monitor\.threshold': expected a number > 0"),
    (lambda c, a: c["monitor"].update(quantile=1.0), r"'monitor\.quantile': expected a number in \(0, 1\)"),
    (lambda c, a: c["monitor"].pop("calibration"), r"'monitor': expected an object with exactly the keys"),
    (lambda c, a: c["monitor"].update(prototypes=299), r"monitor/prototypes"),
    (lambda c, a: a.pop(mon.METRIC), r"monitor/metric"),
    (lambda c, a: a.update({mon.RADII: np.zeros(300)}), r"'monitor/radii': expected radii > 0"),
    (lambda c, a: c.update(fit_families={"constant": {"value": [1.0, -1.0]}}),
     r"'fit_families\.constant\.value': expected a range \[lo, hi\]"),
    (lambda c, a: c.update(fit_families=[]), r"'fit_families': expected a non-empty object"),
])
def test_a_bad_monitor_names_the_field(monitored_bank, tmp_path, edit, message):
    path, _ = monitored_bank
    model = load_model(path)
    card, arrays = json.loads(json.dumps(model.card)), dict(model.arrays)
    edit(card, arrays)
    with pytest.raises(ValueError, match=message):
        save_model(tmp_path / "bad", arrays, card)


def test_a_monitor_of_another_feature_size_is_refused(monitored_bank, rng):
    path, _ = monitored_bank
    model = load_model(path)
    other = mon.calibrate(rng.normal(size=(2000, 5)), rng.normal(size=(500, 5)), n_prototypes=50)
    card = {**model.card, "monitor": other.spec.to_card()}
    arrays = {k: v for k, v in model.arrays.items() if not k.startswith("monitor/")}
    save_model(path, {**arrays, **other.arrays()}, card, overwrite=True)
    with pytest.raises(ValueError, match=r"card\.json: 'monitor\.features': expected the decoder's input size nz \+ "
                                         r"memory = 7, received 5"):
        load_observer(path)
    assert json.loads((path / CARD_FILE).read_text())["monitor"]["features"] == 5


def test_with_a_box_too_the_monitor_is_both_tests(monitored_bank):
    path, monitor = monitored_bank
    runs = bank_runs(n=4, T=5.0, seed=8)
    xhat = load_observer(path).simulate(runs.t, runs.y, runs.u).xhat
    x_lo, x_hi = np.quantile(xhat.reshape(-1, 2), [0.1, 0.9], axis=0)   # a box the estimates leave now and then
    model = load_model(path)
    card = {**model.card, "domain": {"x_lo": x_lo.tolist(), "x_hi": x_hi.tolist(), "z_lo": [-5.0] * 5,
                                     "z_hi": [5.0] * 5}}
    save_model(path, dict(model.arrays), card, overwrite=True)
    est = load_observer(path).simulate(runs.t, runs.y, runs.u)
    margin = 0.1 * (x_hi - x_lo)                                           # DOMAIN_MARGIN of the range
    box = np.all((est.xhat >= x_lo - margin) & (est.xhat <= x_hi + margin), axis=-1) & \
        np.all(np.abs(est.z) <= 6.0, axis=-1)
    feature = monitor.inside(np.concatenate([est.z, runs.y, runs.u], axis=-1))
    np.testing.assert_array_equal(est.in_domain, box & feature)
    assert (box & ~feature).any() and (feature & ~box).any()
