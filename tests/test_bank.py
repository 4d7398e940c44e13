"""The ``bank`` variant end to end: trained by train_observer on a few noisy runs, loaded as a
KKLObserver whose step, simulate and C code reproduce the reference estimator of filterbank."""

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

import casadi as ca  # noqa: E402
from conftest import c_program_estimates  # noqa: E402

import kklcasadi as kc  # noqa: E402
from kklcasadi.model.files import load_model  # noqa: E402
from kklcasadi.model.operational import MonitorConfig, nominal_runs  # noqa: E402
from kklcasadi.model.variants import bankdecoder as bd  # noqa: E402
from kklcasadi.model.variants import filterbank as fb  # noqa: E402
from kklcasadi.plant.runs import RolloutConfig  # noqa: E402
from kklcasadi.train import LoopConfig, default_config, train_observer  # noqa: E402
from kklcasadi.train.bank import design_copies  # noqa: E402
from kklcasadi.train.decoder import DecoderConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bank_dir(tmp_path_factory):
    config = replace(default_config("rossler", "bank"), y_poles=(0.5, 2.0), u_poles=(1.0,), members=1,
                     rollouts=RolloutConfig(n_traj=8, T=4.0),
                     decoder=DecoderConfig(hidden=(8, 8), asinh_scale=(0.0, 0.0, 0.01),
                                           loop=LoopConfig(epochs=2, batch_size=64, schedule="cosine")))
    return train_observer("rossler", "bank", tmp_path_factory.mktemp("bank") / "bank", config=config,
                          progress=False)


def test_bank_card_records_its_noise_level_design_and_domain(bank_dir):
    model = load_model(bank_dir)
    assert model.method == "bank" and model.base is None and model.spec.measurement_std == 0.1
    assert model.card["architecture"]["bank"] == {"y_poles": [0.5, 2.0], "u_poles": [1.0], "y_resonators": [],
                                                  "clock": 0.2, "time_scale": 1.0}
    training = model.card["training"]
    assert training["measurement_std"] == 0.1 and training["process_std"] == [0.1, 0.1, 0.1]
    assert training["threads"] == 1                     # kklcasadi.train.TRAIN_THREADS, torch's count while it trained
    assert training["runs"]["runs"] == 8 and training["runs"]["cut"] == 0 and training["runs"]["simulated_s"] == 32.0
    assert model.spec.nz == 2 + 1 + 1 and model.spec.domain is not None
    assert np.array_equal(model.arrays["decoder/asinh_scale"], [0.0, 0.0, 0.01])
    # the hook calibrates the decoder-input monitor on the fitting runs and records their input families
    assert model.spec.monitor.features == 4 + 1 + 1 and model.spec.monitor.calibration["fit_runs"] == 6
    # the default runs: every family, the hull of docs/protocol.md's id and ood ranges
    assert model.spec.fit_families["square"] == {"amplitude": (0.1, 2.0), "omega": (0.5, 4.0)}
    assert model.spec.fit_families["feedback"] == {"gain": (0.5, 3.0), "hold": (2.0, 10.0), "limit": (2.0, 2.0)}
    assert set(model.spec.fit_families) == {"zero", "constant", "sinusoid", "square", "multisine", "feedback"}


def test_bank_observer_equals_the_reference_estimator(bank_dir):
    obs = kc.load_observer(bank_dir)
    assert obs.encoder is None and obs.discretization == "exact" and obs.memory_shape == (2, 1)
    tr = kc.simulate(obs.system, [1.0, -2.0, 0.5], kc.signals.make("square", amplitude=0.5, omega=1.0), T=6.0,
                     dt=obs.dt, process_std=0.1, measurement_std=0.1, seed=3)
    model = load_model(bank_dir)
    arrays = {**model.arrays, "bank/A": model.A, "bank/By": model.B}
    expected = bd.estimate(model.spec.architecture.decoder_spec, arrays, tr.y, tr.u, obs.dt)
    est = obs.simulate(tr.t, tr.y, tr.u)
    np.testing.assert_allclose(est.xhat, expected, rtol=1e-10, atol=1e-10)
    live = obs.estimator()
    np.testing.assert_allclose([live.make_step(y, u) for y, u in zip(tr.y, tr.u)], est.xhat, rtol=0, atol=1e-13)
    rk4 = kc.load_observer(bank_dir, discretization="rk4", substeps=4).simulate(tr.t, tr.y, tr.u)
    assert np.abs(rk4.xhat - est.xhat).max() < 1e-3 * (1 + np.abs(est.xhat).max())   # RK4 vs exact


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")
@pytest.mark.parametrize("fixture, x0", [("bank_dir", [0.0, 1.0, 0.2]), ("ensemble_dir", [0.5, 1.0])])
def test_bank_compiles_to_c_that_reproduces_simulate(fixture, x0, request, tmp_path):
    """One decoder (Roessler) and a two-decoder ensemble with skip paths (Duffing): the C program's estimates are
    simulate's."""
    obs = kc.load_observer(request.getfixturevalue(fixture))
    tr = kc.simulate(obs.system, x0, kc.signals.make("sinusoid", amplitude=0.4, omega=1.5), T=3.0,
                     dt=obs.dt, measurement_std=0.1, seed=1)
    np.testing.assert_array_equal(c_program_estimates(obs, tmp_path, "bank", tr.t, tr.y, tr.u),
                                  obs.simulate(tr.t, tr.y, tr.u).xhat)


def _arm() -> kc.System:
    """A damped pendulum on a cart-free arm: x = (phi, theta, omega), y = (theta, sin phi); phi and theta
    are angles, theta is measured, phi only through sin phi (a free angle state)."""
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 1)
    return kc.System("arm", x, u, [0.5 * x[2], x[2], -4.0 * ca.sin(x[1]) - 0.3 * x[2] + u],
                     [x[1], ca.sin(x[0])], [[-1.0, 1.0], [-1.5, 1.5], [-2.0, 2.0]], angle_states=(0, 1),
                     angle_outputs=(0,))


@pytest.fixture(scope="module")
def arm_dir(tmp_path_factory):
    config = replace(default_config("arm", "bank", epochs=2), measurement_std=0.01, process_std=(0.0, 0.0, 0.2),
                     rollouts=RolloutConfig(n_traj=8, T=3.0),
                     decoder=DecoderConfig(hidden=(8,), loop=LoopConfig(epochs=2, batch_size=64)))
    return train_observer(_arm(), "bank", tmp_path_factory.mktemp("arm") / "bank", config=config, dt=0.02,
                          progress=False)


def test_a_new_plant_gets_its_own_time_scale_and_its_angles(arm_dir):
    from kklcasadi.plant.design import time_scales

    model = load_model(arm_dir)
    bank = model.card["architecture"]["bank"]
    rate = time_scales(_arm())[0]
    assert bank["time_scale"] == pytest.approx(rate) and rate != 1.0
    np.testing.assert_allclose(bank["y_poles"], np.multiply(default_config("arm", "bank").y_poles, rate))
    assert bank["angles"] == {"outputs": [0], "measured": [[1, 0]], "free": [[0, 0.0]]}
    assert model.spec.nz == 2 * 8 + 5 + 1 and model.card["architecture"]["decoder"]["sizes"] == [22 + 2 + 1 + 1, 8, 4]
    assert model.card["training"]["process_std"] == [0.0, 0.0, 0.2]


def test_the_angle_observer_equals_the_reference_and_its_c_code(arm_dir, tmp_path):
    obs = kc.load_observer(arm_dir, system=_arm())
    tr = kc.simulate(obs.system, [0.3, 1.0, 0.0], kc.signals.make("sinusoid", amplitude=0.5, omega=2.0), T=3.0,
                     dt=obs.dt, measurement_std=0.01, seed=4)
    model = load_model(arm_dir)
    arrays = {**model.arrays, "bank/A": model.A, "bank/By": model.B}
    expected = bd.estimate(model.spec.architecture.decoder_spec, arrays, tr.y, tr.u, obs.dt)
    est = obs.simulate(tr.t, tr.y, tr.u)
    np.testing.assert_allclose(est.xhat, expected, rtol=1e-10, atol=1e-10)
    assert np.all(np.abs(est.xhat[:, 0]) <= np.pi)              # the free angle, about its box centre 0
    # theta measured on another branch: theta + 2 pi, up to the start of the filters from z(0) = 0
    moved = obs.simulate(tr.t, tr.y + [2 * np.pi, 0.0], tr.u).xhat
    np.testing.assert_allclose(moved[:, 1] - est.xhat[:, 1], 2 * np.pi, atol=1e-2)
    if shutil.which("gcc") is None:
        return
    np.testing.assert_allclose(c_program_estimates(obs, tmp_path, "arm", tr.t, tr.y, tr.u), est.xhat, rtol=0,
                               atol=1e-12)


def test_a_single_process_std_acts_where_process_on_says():
    from kklcasadi.train.bank import BankConfig, process_stds

    arm = _arm()                                   # theta' = omega is kinematic, phi' = 0.5 omega is not
    assert default_config("arm", "bank").process_on == "forced"
    assert default_config("duffing", "bank").process_on == "all"
    np.testing.assert_array_equal(process_stds(arm, BankConfig(process_std=0.3, process_on="forced")), [0.3, 0, 0.3])
    np.testing.assert_array_equal(process_stds(arm, BankConfig(process_std=0.3)), [0.3, 0.3, 0.3])
    np.testing.assert_array_equal(process_stds(arm, BankConfig(process_std=(0.1, 0.2, 0.0))), [0.1, 0.2, 0.0])
    with pytest.raises(ValueError, match="process_std"):
        process_stds(arm, BankConfig(process_std=(0.1, 0.2)))
    with pytest.raises(ValueError, match="process_on"):
        BankConfig(process_on="some")


# ---------------------------------------------------------------------- decoder ensembles
@pytest.fixture(scope="module")
def ensemble_dir(tmp_path_factory):
    config = replace(default_config("duffing", "bank"), y_poles=(0.5, 2.0), u_poles=(1.0,), members=2, copies=(),
                     rollouts=RolloutConfig(n_traj=8, T=6.0),
                     monitor=MonitorConfig(spread_quantile=0.97, spread_runs=4),
                     decoder=DecoderConfig(hidden=(8, 8), skip=True, loop=LoopConfig(epochs=2, batch_size=64)))
    return train_observer("duffing", "bank", tmp_path_factory.mktemp("ensemble") / "bank", config=config,
                          seed=5, progress=False)


def _arrays(directory):
    model = load_model(directory)
    return model, {**model.arrays, "bank/A": model.A, "bank/By": model.B}, model.card["architecture"]["decoder"]


def test_an_ensemble_card_records_its_members_and_the_spread_test(ensemble_dir):
    model, arrays, arch = _arrays(ensemble_dir)
    assert model.card["architecture"]["bank"]["members"] == 2 and model.spec.architecture.members == 2
    assert {"decoder_1/W0", "decoder_1/b2", "decoder_1/out_std", "decoder_1/Wskip"} <= set(model.arrays)
    assert not np.array_equal(model.arrays["decoder/W0"], model.arrays["decoder_1/W0"])    # seeds 5 and 6
    assert arch["skip"] is True and model.spec.architecture.decoder.skip          # each member's linear path
    assert not np.array_equal(model.arrays["decoder/Wskip"], model.arrays["decoder_1/Wskip"])
    threshold, quantile = model.spec.monitor.spread
    assert threshold > 0 and quantile == 0.97
    # the threshold is that quantile of the spreads of 4 runs of the recipe at the nominal noise, after 5 s
    calibration = model.spec.monitor.calibration
    assert calibration["spread_source"].startswith("4 runs of the fitting recipe at the nominal noise")
    obs = kc.load_observer(ensemble_dir)
    rate = model.card["training"]["time_scale"]
    runs, _ = nominal_runs(obs.system, fb.bank_from_arrays(arrays), RolloutConfig(n_traj=8, T=6.0), 4, 5, dt=obs.dt,
                           measurement_std=0.1, process_std=np.full(2, 0.1), time_scale=rate)
    after = runs.t >= 5.0
    spreads = obs.spread_of(runs.z[after], np.concatenate([runs.y, runs.u], axis=1)[after][..., None])
    assert calibration["spread_samples"] == int(after.sum())
    assert threshold == pytest.approx(np.quantile(spreads, 0.97), rel=1e-9)
    assert len(model.card["training"]["member_fits"]) == 1
    history = (ensemble_dir / "history.json").read_text()
    assert '"decoder"' in history and '"decoder_1"' in history


def test_the_ensemble_decodes_the_mean_of_its_members(ensemble_dir):
    from kklcasadi.nets.numpy_mlp import mlp_numpy
    from kklcasadi.nets.specs import MLPSpec

    model, arrays, arch = _arrays(ensemble_dir)
    rng = np.random.default_rng(0)
    z, y, u = rng.normal(size=(50, model.spec.nz)), rng.normal(size=(50, 1)), rng.normal(size=(50, 1))
    spec, f = MLPSpec.from_card(arch), np.concatenate([z, y, u], axis=1)
    v = [mlp_numpy(spec, arrays, prefix, f) for prefix in ("decoder", "decoder_1")]
    pair, one = bd.DecoderSpec.from_card(arch, members=2), bd.DecoderSpec.from_card(arch)
    np.testing.assert_allclose(bd.decode(pair, arrays, z, y, u), (v[0] + v[1]) / 2, rtol=0, atol=1e-14)
    single = bd.decode(one, arrays, z, y, u)
    np.testing.assert_array_equal(single, v[0])
    assert np.abs(single - (v[0] + v[1]) / 2).max() > 1e-6
    # the spread: sqrt(mean_j sum_i ((v_ji - vbar_i) / s_i)^2), s the first member's output std
    s = arrays["decoder/out_std"]
    expected = np.sqrt((((v[0] - v[1]) / 2 / s) ** 2).sum(axis=1))
    np.testing.assert_allclose(bd.spread(pair, arrays, z, y, u), expected, rtol=1e-13)
    same = {**arrays, **{k.replace("decoder/", "decoder_1/"): a for k, a in arrays.items() if k.startswith("decoder/")}}
    np.testing.assert_array_equal(bd.spread(pair, same, z, y, u), 0.0)
    # the CasADi paths: decoder and spread at the same points
    zs, ys, us = ca.MX.sym("z", model.spec.nz), ca.MX.sym("y", 1), ca.MX.sym("u", 1)
    dec = bd.decoder_function(pair, arrays).map(50)
    np.testing.assert_allclose(np.asarray(dec(z.T, y.T, u.T)).T, (v[0] + v[1]) / 2, rtol=0, atol=1e-13)
    sp = ca.Function("s", [zs, ys, us], [bd.spread_expression(pair, arrays, fb.bank_from_arrays(arrays), zs, ys,
                                                              us)]).map(50)
    np.testing.assert_allclose(np.asarray(sp(z.T, y.T, u.T)).ravel(), expected, rtol=1e-12)


def test_growing_an_ensemble_keeps_its_members_arrays(ensemble_dir, monkeypatch):
    """benchmarks/ensemble_members.py grows a K0-decoder ensemble: each kept member, read back as a single
    decoder and joined again with ensemble_arrays, gives the model's own arrays."""
    import runpy

    from kklcasadi.train.bank import ensemble_arrays
    from kklcasadi.train.decoder import BankFit

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    script = runpy.run_path(str(ROOT / "benchmarks" / "ensemble_members.py"), run_name="ensemble_members")
    model, arrays, arch = _arrays(ensemble_dir)
    members = [script["member_arrays"](model.arrays, prefix) for prefix in bd.member_prefixes(2)]
    assert not any(name.startswith("decoder_1") for part in members for name in part)
    np.testing.assert_array_equal(members[1]["decoder/W0"], model.arrays["decoder_1/W0"])
    np.testing.assert_array_equal(members[1][bd.ASINH_SCALE], model.arrays[bd.ASINH_SCALE])
    one = bd.DecoderSpec.from_card(arch, angles=model.spec.architecture.angles)
    again = ensemble_arrays([BankFit(part, one, None, 0, 0.0, {}) for part in members])
    assert set(again) == set(model.arrays)
    for name, value in model.arrays.items():
        np.testing.assert_array_equal(again[name], value)


def test_the_ensemble_observer_equals_the_reference_and_monitors_the_spread(ensemble_dir):
    obs = kc.load_observer(ensemble_dir)
    model, arrays, arch = _arrays(ensemble_dir)
    tr = kc.simulate(obs.system, [1.0, -0.5], kc.signals.make("square", amplitude=0.5, omega=1.0), T=6.0,
                     dt=obs.dt, process_std=0.1, measurement_std=0.1, seed=3)
    est = obs.simulate(tr.t, tr.y, tr.u)
    pair = bd.DecoderSpec.from_card(arch, members=2)
    np.testing.assert_allclose(est.xhat, bd.estimate(pair, arrays, tr.y, tr.u, obs.dt), rtol=1e-10, atol=1e-10)
    z = fb.FilterBank(model.A, model.B, arrays["bank/Bu"], arrays["bank/c"]).run(tr.y, tr.u, obs.dt)
    w = np.concatenate([tr.y, tr.u], axis=1)[:, :, None]
    spread = obs.spread_of(z, w)
    np.testing.assert_allclose(spread, bd.spread(pair, arrays, z, tr.y, tr.u), rtol=1e-12)
    # the domain check is the prototype test and the spread test, in numpy and in CasADi alike
    threshold = obs.monitor.spec.spread[0]
    prototypes = obs.monitor.inside(np.concatenate([z, w[:, :, 0]], axis=1))
    inside = obs.in_domain(est.xhat, z, w)
    assert not inside[~prototypes | (spread > threshold)].any()
    check = np.asarray(obs.domain_check.map(len(z))(z.T, w[:, :, 0].T, est.xhat.T)).ravel() > 0.5
    np.testing.assert_array_equal(check, inside)


def test_an_ensemble_monitor_flags_what_its_members_disagree_on(ensemble_dir, tmp_path):
    from kklcasadi.model.files import save_model

    model = load_model(ensemble_dir)
    card = json.loads((ensemble_dir / "card.json").read_text())
    obs = kc.load_observer(ensemble_dir)
    tr = kc.simulate(obs.system, [1.0, -0.5], kc.signals.make("zero"), T=4.0, dt=obs.dt, measurement_std=0.1, seed=1)
    est = obs.simulate(tr.t, tr.y, tr.u)
    w = np.concatenate([tr.y, tr.u], axis=1)[:, :, None]
    spread = obs.spread_of(est.z, w)
    # a spread threshold below every sample's spread flags every sample
    card["monitor"]["spread"]["threshold"] = float(spread.min()) / 2
    tight = kc.load_observer(save_model(tmp_path / "tight", dict(model.arrays), card))
    assert not tight.in_domain(est.xhat, est.z, w).any()
    # the spread test without an ensemble is refused with the fix
    single = json.loads((ensemble_dir / "card.json").read_text())
    del single["architecture"]["bank"]["members"]
    arrays = {k: v for k, v in model.arrays.items() if not k.startswith("decoder_1/")}
    with pytest.raises(ValueError, match="monitor.spread.*decoder ensemble"):
        kc.load_observer(save_model(tmp_path / "single", arrays, single))
    bad = json.loads((ensemble_dir / "card.json").read_text())
    bad["monitor"]["spread"] = {"threshold": -1.0, "quantile": 0.99}
    with pytest.raises(ValueError, match="monitor.spread"):
        save_model(tmp_path / "bad", dict(model.arrays), bad)
    bad["monitor"]["spread"] = {"threshold": 1.0, "quantile": 0.99}
    bad["architecture"]["bank"]["members"] = 0
    with pytest.raises(ValueError, match="architecture.bank.members"):
        save_model(tmp_path / "zero", dict(model.arrays), bad)


def test_members_must_be_a_positive_integer():
    from kklcasadi.train.bank import SHIPPED_MEMBERS, BankConfig

    assert default_config("duffing", "bank").members == SHIPPED_MEMBERS == 2  # the shipped systems' ensembles
    assert default_config("vdp", "bank").members == 3
    assert default_config("arm", "bank").members == 1                         # a new plant's first observer

    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="members"):
            BankConfig(members=bad)
    with pytest.raises(ValueError, match="members"):
        bd.member_prefixes(0)
    assert bd.member_prefixes(3) == ("decoder", "decoder_1", "decoder_2")


@pytest.mark.parametrize("system", ["duffing", "vdp", "fhn", "rossler"])
def test_the_shipped_banks_are_decoder_ensembles_with_the_spread_test(system):
    """The shipped banks are ensembles of the default configuration's members (two; Van der Pol's three),
    trained as one (``training.config.members``) or grown by benchmarks/ensemble_members.py (the card
    says which), on the runs the system's default
    configuration makes (their count, families, ranges and noise range, and the input filters); the
    monitor holds the spread test, and on a protocol trial the ensemble is neither member."""
    from kklcasadi.evaluation.protocol import Protocol
    from kklcasadi.model.shipped import shipped_model
    path = shipped_model(system, "bank")
    model = load_model(path)
    config = default_config(system, "bank")          # `kklcasadi train --method bank` remakes the shipped recipe
    assert model.spec.architecture.members == config.members == (3 if system == "vdp" else 2)
    training = model.card["training"]
    assert (training.get("config", {}).get("members") == config.members
            or training["members_added_by"].startswith("benchmarks/ensemble_members.py"))
    assert len(training["member_fits"]) == config.members - 1
    runs = training["rollouts"]
    assert (runs["n_traj"], runs["kinds"], runs["regime"], tuple(runs["noise_range"])) == (
        config.rollouts.n_traj, list(config.rollouts.kinds), config.rollouts.regime, config.rollouts.noise_range)
    assert tuple(model.card["architecture"]["bank"]["u_poles"]) == config.u_poles
    assert model.spec.architecture.decoder.skip == config.decoder.skip == (system in ("duffing", "vdp"))  # skip
    copies = model.card["architecture"]["bank"].get("copies", {"weights": []})   # Duffing's and Van der Pol's
    assert tuple(copies["weights"]) == config.copies == ((1.0, 100.0, 1e4) if system in ("duffing", "vdp") else ())
    if config.copies:                                # Van der Pol's two RK4 substeps; Duffing's from their speed
        assert copies["substeps"] == design_copies(kc.systems.get(system), config, 0.05).substeps == (
            2 if system == "vdp" else 5)
        assert config.copy_substeps == (2 if system == "vdp" else None)
    decoder = training["decoder"]                    # the loss: Roessler's mse + 0.5 SMAPE, else mse
    assert decoder["loss"] == config.decoder.loss == ("mse+smape" if system == "rossler" else "mse")
    assert decoder["loss"] == "mse" or decoder["smape_weight"] == config.decoder.smape_weight == 0.5
    # the spread quantile chosen on validation trials (benchmarks/monitor_quantiles.py), on runs at the nominal
    # noise; where no quantile met the budget the card keeps the fitting runs' validation samples at 0.99
    choice = json.loads((ROOT / "results" / "generalisation" / system / f"{system}_3030_monitor.json").read_text())
    threshold, quantile = model.spec.monitor.spread
    assert threshold > 0 and quantile == (0.99 if choice["chosen"] is None else choice["chosen"])
    source = model.spec.monitor.calibration.get("spread_source", "")
    assert source.startswith("400 runs of the fitting recipe at the nominal noise") == (choice["chosen"] is not None)
    if choice["chosen"] is not None:
        row = next(r for r in choice["rows"] if r["quantile"] == quantile)
        assert row["in distribution"]["share_other"] <= choice["budget"]
        assert threshold == pytest.approx(row["threshold"], rel=1e-12)      # the same runs, the same quantile
    obs = kc.load_observer(path)
    batch = Protocol(n_trials=1, T=10.0).cell("square").simulate(obs.system)
    est = obs.simulate(batch.t, batch.y[0], batch.u[0])
    spec = model.spec.architecture
    arrays, arch = spec.filter_arrays(model.arrays), model.card["architecture"]["decoder"]
    angles, copies = spec.angles, spec.model_copies(model.arrays, obs.system)
    assert spec.decoder_spec == bd.DecoderSpec.from_card(arch, angles=angles, members=config.members)
    np.testing.assert_allclose(est.xhat, bd.estimate(spec.decoder_spec, arrays, batch.y[0], batch.u[0], obs.dt,
                                                     copies=copies), rtol=1e-9, atol=1e-9)
    for fewer in range(1, config.members):            # the ensemble is none of its leading sub-ensembles
        fewer_spec = bd.DecoderSpec.from_card(arch, angles=angles, members=fewer)
        part = bd.estimate(fewer_spec, arrays, batch.y[0], batch.u[0], obs.dt, copies=copies)
        assert np.abs(part - est.xhat).max() > 1e-6


@pytest.mark.parametrize("quantile, spread_quantile", [(0.98, 0.99), (0.9, 0.95)])
def test_bank_monitor_sets_both_thresholds_at_their_quantiles_of_the_validation_samples(quantile, spread_quantile):
    """bank_monitor: the prototype threshold and the spread threshold are the requested quantiles over the
    validation samples (the last fifth of the runs, after the settle time), and only those reach the spread."""
    from kklcasadi.model.operational import OperationalData, bank_monitor

    rng = np.random.default_rng(3)
    runs, per_run = 10, 40
    t = np.tile(np.arange(per_run) * 0.25, runs)                     # 0 .. 9.75 s per run
    run = np.repeat(np.arange(runs), per_run)
    z, y, u = rng.normal(size=(len(t), 3)), rng.normal(size=(len(t), 1)), rng.normal(size=(len(t), 1))
    data = OperationalData(z, y, u, np.zeros((len(t), 2)), t, run, {})
    seen = []

    def spread(zs, ys, us):
        seen.append(len(zs))
        return np.abs(zs[:, 0]) + 1e-3

    monitor = bank_monitor(data, 0, spread=spread, quantile=quantile, spread_quantile=spread_quantile)
    held = (run >= 8) & (t >= 5.0)
    assert seen == [int(held.sum())]
    assert monitor.spec.spread == (pytest.approx(np.quantile(np.abs(z[held, 0]) + 1e-3, spread_quantile)),
                                   spread_quantile)
    features = np.concatenate([z, y, u], axis=1)[held]
    assert monitor.spec.quantile == quantile
    assert np.mean(monitor.distance(features) <= monitor.spec.threshold) == pytest.approx(quantile, abs=0.03)



@pytest.mark.parametrize("settle_time", [5.0, 20.0])
def test_bank_monitor_takes_the_spread_threshold_from_the_runs_it_is_given(settle_time):
    """bank_monitor with spread_data: the spread threshold is the quantile over those runs' samples after the
    settle time (all of them where the runs end before it), the prototype threshold still from the validation
    samples; the card's calibration record names the source."""
    from kklcasadi.model.operational import OperationalData, bank_monitor

    rng = np.random.default_rng(4)

    def runs(n, per_run, width):
        t = np.tile(np.arange(per_run) * 0.25, n)
        z = rng.normal(size=(len(t), 3)) * width
        return OperationalData(z, rng.normal(size=(len(t), 1)), rng.normal(size=(len(t), 1)), np.zeros((len(t), 2)),
                               t, np.repeat(np.arange(n), per_run), {})

    data, nominal = runs(10, 40, 2.0), runs(6, 40, 1.0)
    seen = []

    def spread(zs, ys, us):
        seen.append(len(zs))
        return np.abs(zs[:, 0]) + 1e-3

    monitor = bank_monitor(data, 0, spread=spread, spread_data=nominal, spread_source="six runs", spread_quantile=0.9,
                           settle_time=settle_time)
    after = nominal.t >= (settle_time if settle_time < 10.0 else 0.0)
    assert seen == [int(after.sum())]
    assert monitor.spec.spread == (pytest.approx(np.quantile(np.abs(nominal.z[after, 0]) + 1e-3, 0.9)), 0.9)
    assert monitor.spec.calibration["spread_source"] == "six runs"
    assert monitor.spec.calibration["spread_samples"] == int(after.sum())
    plain = bank_monitor(data, 0, spread=spread, spread_quantile=0.9, settle_time=settle_time)
    assert plain.spec.threshold == monitor.spec.threshold and plain.spec.spread[0] > monitor.spec.spread[0]
    with pytest.raises(ValueError, match="spread_data"):
        bank_monitor(data, 0, spread=spread, spread_data=OperationalData(*(a[:0] for a in (
            nominal.z, nominal.y, nominal.u, nominal.x, nominal.t, nominal.run)), {}))


@pytest.mark.parametrize("field, value", [("quantile", 1.0), ("spread_quantile", 0.0), ("spread_runs", -1),
                                          ("spread_runs", 2.5)])
def test_monitor_config_rejects_bad_settings(field, value):
    from kklcasadi.model.operational import MonitorConfig
    from kklcasadi.train.bank import BankConfig

    with pytest.raises((ValueError, TypeError), match=field):
        MonitorConfig(**{field: value})
    with pytest.raises(TypeError, match="monitor"):
        BankConfig(monitor={"quantile": 0.9})


#: The benchmark scripts that need no torch (the bank's runs, its samples and its monitor are torch-free).
TORCH_FREE_SCRIPTS = ("calibrate_monitors.py", "monitor_quantiles.py", "bitwise_estimates.py")


def test_the_monitor_is_calibrated_again_without_torch(ensemble_dir, tmp_path, no_torch_env):
    """benchmarks/calibrate_monitors.py in an interpreter that cannot import torch: it re-simulates the decoder's
    fitting runs (checked against the card's domain bit for bit) and calibrates the same monitor training gave
    the model (the same runs and quantiles: the same thresholds and arrays, bitwise); the other torch-free
    scripts start there too."""
    copy = tmp_path / "bank"
    shutil.copytree(ensemble_dir, copy)
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "calibrate_monitors.py"), str(copy),
                             "--spread-quantile", "0.97", "--spread-runs", "4"], capture_output=True, text=True,
                            env=no_torch_env, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    before, after = load_model(ensemble_dir), load_model(copy)
    assert after.card["monitor"]["calibration"]["source"].endswith("re-simulated by benchmarks/calibrate_monitors.py")
    drop = ("calibration",)
    assert ({k: v for k, v in after.card["monitor"].items() if k not in drop}
            == {k: v for k, v in before.card["monitor"].items() if k not in drop})
    assert set(after.arrays) == set(before.arrays)
    for name, value in before.arrays.items():
        np.testing.assert_array_equal(after.arrays[name], value)
    for script in TORCH_FREE_SCRIPTS:
        run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), "--help"], capture_output=True,
                             text=True, env=no_torch_env, cwd=ROOT / "benchmarks")
        assert run.returncode == 0 and "usage" in run.stdout, (script, run.stderr)


def test_monitor_quantiles_writes_its_table_and_record_as_one_and_never_over_them(ensemble_dir, tmp_path,
                                                                                   monkeypatch, capsys):
    """benchmarks/monitor_quantiles.py on six cases of one trial: the table and the record are written together,
    a second run of the seed is refused before any work (one line naming --seed), a run that fails after the
    table is printed writes neither file."""
    import runpy

    from kklcasadi import provenance
    from kklcasadi.evaluation import generalisation as gen

    script = ROOT / "benchmarks" / "monitor_quantiles.py"
    monkeypatch.syspath_prepend(str(script.parent))                # its sibling calibrate_monitors.py
    monkeypatch.chdir(tmp_path)                                   # it writes under ./results/generalisation
    few = [case for case in gen.cases() if case.label.startswith(("zero id", "chirp"))]     # every group, 6 cases
    monkeypatch.setattr(gen, "cases", lambda: few)

    def run(*flags):
        monkeypatch.setattr(sys, "argv", [str(script), str(ensemble_dir), "--trials", "1", "--spread-runs", "4",
                                          *flags])
        runpy.run_path(str(script), run_name="__main__")

    run()
    folder = tmp_path / "results" / "generalisation" / "duffing"
    names = ["duffing_3030_monitor.json", "duffing_3030_monitor.md"]
    assert sorted(p.name for p in folder.iterdir()) == names
    assert provenance.read(folder / names[0]) == provenance.read(folder / names[1])
    assert "| 0.97 |" in (folder / names[1]).read_text()
    first = [(folder / name).read_bytes() for name in names]
    assert "bank / EKF" in capsys.readouterr().out
    with pytest.raises(FileExistsError, match="^--seed: .*duffing_3030_monitor.md exists and this command does not"):
        run()
    assert "bank / EKF" not in capsys.readouterr().out                   # refused before any case was run

    def failing(*args, **kwargs):
        raise OSError("disk")

    monkeypatch.setattr(provenance, "json_record", failing)
    with pytest.raises(OSError, match="disk"):
        run("--seed", "3031")
    assert "| 0.97 |" in capsys.readouterr().out                        # failed after the table was made
    assert sorted(p.name for p in folder.iterdir()) == names and [(folder / n).read_bytes() for n in names] == first
    assert [p for p in tmp_path.rglob(".*")] == []


def test_growing_an_ensemble_writes_a_new_model_and_never_over_one(ensemble_dir, tmp_path, monkeypatch, capsys):
    """benchmarks/ensemble_members.py end to end on the small ensemble: a third member fitted and cached (its
    summary, then its arrays), the model written to --out with its monitor; a second run to the same --out is
    refused before any fit, in one line naming --out, and the model it read is left alone."""
    import runpy

    script = ROOT / "benchmarks" / "ensemble_members.py"
    monkeypatch.syspath_prepend(str(script.parent))
    source = {p.name: p.read_bytes() for p in ensemble_dir.iterdir() if p.is_file()}

    def grow(out):
        monkeypatch.setattr(sys, "argv", [str(script), str(ensemble_dir), "--members", "3", "--out", str(out),
                                          "--cache", str(tmp_path / "cache")])
        runpy.run_path(str(script), run_name="__main__")

    grow(tmp_path / "grown")
    grown = load_model(tmp_path / "grown")
    assert grown.spec.architecture.members == 3 and "decoder_2/W0" in grown.arrays
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["duffing_m7.json", "duffing_m7.npz"]
    capsys.readouterr()
    for out in (tmp_path / "grown", ensemble_dir):
        with pytest.raises(FileExistsError, match=f"^--out: {out}/.* exists and this command does not overwrite"):
            grow(out)
    assert capsys.readouterr().out == ""
    assert {p.name: p.read_bytes() for p in ensemble_dir.iterdir() if p.is_file()} == source
