"""The augmented EKF as a block of the ``bank`` latent: its trajectory against AugmentedEKF.simulate, a bank with the
block end to end (trained, loaded, simulated against the reference, stepped live, compiled to C), the card's
refusals and the training configuration's."""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from conftest import c_program_estimates

import kklcasadi as kc
from kklcasadi.estimators.augmented import AugmentedEKF
from kklcasadi.model.variants.ekfblock import EKFBlock


def _runs(system, params, n_trials=3, T=6.0, seed=5):
    """Noisy runs of ``system`` at ``params`` under a square input: ``(t, y (M, N, ny), u (M, N, nu))``."""
    runs = [kc.simulate(system, x0, kc.signals.make("square", amplitude=0.8, omega=0.9), T=T, dt=0.05,
                        process_std=0.1, measurement_std=0.1, seed=seed + i, params=params)
            for i, x0 in enumerate(([0.4, -0.6], [-0.8, 0.3], [0.1, 0.9])[:n_trials])]
    return runs[0].t, np.stack([r.y for r in runs]), np.stack([r.u for r in runs])


@pytest.mark.parametrize("name, params, walk, scales", [("duffing", [1.3, 0.7], 0.003, (1.0, 1.0)),
                                                        ("vdp", [0.8, 1.2, 1.1], 0.01, (4.0, 2.0))])
def test_the_block_is_the_augmented_ekf_after_the_first_sample(name, params, walk, scales):
    family = kc.systems.get(name, param_spread=0.3)
    t, y, u = _runs(family, params)
    block = EKFBlock.design(family, 0.05, process_std=0.1, measurement_std=0.1, param_walk=walk, q_scale=scales[0],
                            r_scale=scales[1])
    ekf = AugmentedEKF(family, 0.05, process_std=0.1, measurement_std=0.1, param_walk=walk, q_scale=scales[0],
                       r_scale=scales[1])
    assert block.substeps == ekf.substeps and block.na == family.nx + family.n_params
    assert block.nz == block.na + block.na ** 2 + 1
    z = block.run(y, u)
    est = ekf.simulate(t, y, u)
    np.testing.assert_array_equal(z[:, 0], 0.0)                               # the latent's zero start
    np.testing.assert_allclose(z[:, 1:, :block.na], est.xhat[:, 1:], rtol=0, atol=1e-12)
    na = block.na
    P = z[:, 1:, na:block.ns].reshape(*z.shape[:2][:1], -1, na, na)         # column-major vec(P): P^T rows
    np.testing.assert_allclose(np.diagonal(P, axis1=2, axis2=3), est.var[:, 1:], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(z[:, 1:, -1], 1.0)                          # the start flag
    # the same filter one sample at a time
    live = ekf.estimator()
    steps = np.array([live.make_step(yk, uk) for yk, uk in zip(y[0], u[0])])
    np.testing.assert_allclose(z[0, 1:, :family.nx], steps[1:], rtol=0, atol=1e-12)


def test_the_block_runs_the_family_of_a_plant_fixed_from_it_and_refuses_a_plant_without_one():
    family = kc.systems.get("duffing", param_spread=0.3)
    nominal = family.at(family.param_nominal)
    block = EKFBlock.design(nominal, 0.05, process_std=0.1, measurement_std=0.1, param_walk=0.003)
    assert block.system is family
    with pytest.raises(ValueError, match=r"system: expected a plant with parameters .* received 'duffing', without "
                       "parameters"):
        EKFBlock.design(kc.systems.get("duffing"), 0.05, process_std=0.1, measurement_std=0.1, param_walk=0.003)
    with pytest.raises(ValueError, match="substeps: expected a positive integer"):
        EKFBlock(family, 0.05, (0.1, 0.1), 0.1, 0.003, substeps=0)
    with pytest.raises(ValueError, match="param_walk: expected"):
        EKFBlock(family, 0.05, (0.1, 0.1), 0.1, -1.0)


@pytest.mark.parametrize("field, value, match", [
    (None, {"process_std": [0.1, 0.1]}, r"architecture.bank.ekf': expected an object with the keys"),
    ("process_std", [0.1], r"architecture.bank.ekf.process_std': expected nx = 2 finite numbers >= 0"),
    ("measurement_std", 0.0, r"architecture.bank.ekf.measurement_std': expected a finite number > 0"),
    ("param_walk", -0.1, r"architecture.bank.ekf.param_walk': expected a finite number >= 0"),
    ("q_scale", "1", r"architecture.bank.ekf.q_scale': expected a finite number > 0"),
    ("substeps", 1.5, r"architecture.bank.ekf.substeps': expected a positive integer"),
])
def test_check_card_names_the_field(field, value, match):
    entry = {"process_std": [0.1, 0.1], "measurement_std": 0.1, "param_walk": 0.003, "q_scale": 1.0, "r_scale": 1.0,
             "substeps": 1}
    entry = value if field is None else {**entry, field: value}
    with pytest.raises(ValueError, match=match):
        EKFBlock.check_card(entry, "card.json", 2)


# ---------------------------------------------------------------------- a bank with the block end to end
@pytest.fixture(scope="module")
def block_dir(tmp_path_factory):
    pytest.importorskip("torch")
    from kklcasadi.plant.runs import RolloutConfig
    from kklcasadi.train import LoopConfig, default_config, train_observer
    from kklcasadi.train.decoder import DecoderConfig

    config = replace(default_config("duffing", "bank"), y_poles=(0.5, 2.0), u_poles=(1.0,), members=1,
                     copies=(1.0,), corner_copies=(100.0,), rollouts=RolloutConfig(n_traj=8, T=6.0), ekf_block=True,
                     decoder=DecoderConfig(hidden=(8, 8), skip=False, loop=LoopConfig(epochs=2, batch_size=64)))
    return train_observer(kc.systems.get("duffing", param_spread=0.3), "bank",
                          tmp_path_factory.mktemp("ekfblock") / "bank", config=config, seed=3, progress=False)


def test_the_card_records_the_block_and_its_design_rows(block_dir):
    from kklcasadi.model.files import load_model

    model = load_model(block_dir)
    entry = model.card["architecture"]["bank"]["ekf"]
    assert entry == {"process_std": [0.1, 0.1], "measurement_std": 0.1, "param_walk": 0.001, "q_scale": 1.0,
                     "r_scale": 1.0, "substeps": 1}
    spec = model.spec.architecture
    assert spec.n_ekf == 4 + 16 + 1 and spec.n_filters == 2 + 1 + 1 and spec.n_copy_latents == 5 * 2
    assert model.A.shape == (4 + 10 + 21,) * 2
    np.testing.assert_array_equal(model.A[14:, 14:], -np.eye(21) / 0.05)
    assert not np.any(model.B[14:]) and not np.any(model.A[:14, 14:]) and not np.any(model.A[14:, :14])
    assert model.card["architecture"]["decoder"]["sizes"][0] == 35 + 1 + 1
    assert model.card["architecture"]["decoder"]["skip"] is True         # the residual is folded into the skip path
    assert model.card["training"]["config"]["ekf_block"] is True


def test_the_decoder_corrects_the_blocks_estimate(block_dir):
    """With ekf_residual the decoder's skip path carries the block's estimate: the decoded state minus the
    block's estimate is what the network fitted (here, on 8 runs and 2 epochs, nearly nothing: the estimate stays
    within a small distance of the augmented EKF's)."""
    family = kc.systems.get("duffing", param_spread=0.3)
    obs = kc.load_observer(block_dir)
    t, y, u = _runs(family, [0.7, 1.3], n_trials=1, T=10.0)
    est = obs.simulate(t, y[0], u[0]).xhat
    aug = AugmentedEKF(family, 0.05, process_std=0.1, measurement_std=0.1, param_walk=0.001).simulate(t, y[0], u[0])
    gap = np.abs(est[40:] - aug.xhat[40:, :2]).mean(axis=0)
    assert np.all(gap < 0.5 * np.abs(aug.xhat[40:, :2]).mean(axis=0))


def test_the_observer_with_the_block_equals_the_reference_and_its_c_code(block_dir, tmp_path):
    from kklcasadi.model.files import load_model
    from kklcasadi.model.variants import bankdecoder as bd

    obs = kc.load_observer(block_dir)           # the family rebuilt from the card's box
    family = kc.systems.get("duffing", param_spread=0.3)
    assert obs.system.fingerprint == kc.systems.get("duffing").fingerprint and obs.system.family is not None
    t, y, u = _runs(family, [1.3, 0.7], n_trials=1, T=5.0)
    model = load_model(block_dir)
    spec = model.spec.architecture
    copies, ekf = spec.model_copies(model.arrays, family), spec.ekf_block(family)
    expected = bd.estimate(spec.decoder_spec, spec.filter_arrays(model.arrays), y[0], u[0], obs.dt, copies=copies,
                           ekf=ekf)
    est = obs.simulate(t, y[0], u[0])
    np.testing.assert_allclose(est.xhat, expected, rtol=1e-10, atol=1e-10)
    live = obs.estimator()
    np.testing.assert_allclose([live.make_step(yk, uk) for yk, uk in zip(y[0], u[0])], est.xhat, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(kc.load_observer(block_dir, system=family).simulate(t, y[0], u[0]).xhat, est.xhat)
    with pytest.raises(ValueError, match="discretization: expected 'exact'"):
        kc.load_observer(block_dir, discretization="rk4")
    with pytest.raises(ValueError, match="integrator: expected a model whose latent has a field"):
        obs.integrator()
    if shutil.which("gcc") is None:
        return
    np.testing.assert_array_equal(c_program_estimates(obs, tmp_path, "bank", t, y[0], u[0]), est.xhat)


@pytest.mark.parametrize("edit, match", [
    (lambda bank, design, arrays:
     bank["ekf"].update(param_walk=-1.0), r"architecture.bank.ekf.param_walk"),
    (lambda bank, design, arrays:
     bank["ekf"].pop("substeps"), r"architecture.bank.ekf': expected an object with the keys"),
    (lambda bank, design, arrays:
     design["A"][-2].__setitem__(-2, -10.0), r"design: expected the EKF block's last 21 rows"),
    (lambda bank, design, arrays:
     bank["ekf"].update(process_std=[0.1, 0.1, 0.1]), r"ekf.process_std': expected nx = 2"),
    (lambda bank, design, arrays:
     [bank.pop("copies")] + [arrays.pop(k) for k in list(arrays) if k.startswith("copies/")],
     r"design: expected the EKF block's last 21 rows .* received 31 rows"),   # the copies' latents left to the block
])
def test_a_card_with_a_bad_block_is_refused(block_dir, tmp_path, edit, match):
    from kklcasadi.model.files import load_model, save_model

    model = load_model(block_dir)
    card, arrays = json.loads(json.dumps(model.card)), dict(model.arrays)
    edit(card["architecture"]["bank"], card["design"], arrays)
    with pytest.raises(ValueError, match=match):
        save_model(tmp_path / "m", arrays, card, overwrite=True)
        kc.load_observer(tmp_path / "m")


@pytest.mark.parametrize("field, value, match", [
    ("ekf_block", 1, "ekf_block: expected True or False"),
    ("ekf_walk", -0.1, "ekf_walk: expected a finite number >= 0"),
    ("ekf_scales", (1.0,), r"ekf_scales: expected \(q_scale, r_scale\)"),
])
def test_bank_config_rejects_bad_block_settings(field, value, match):
    pytest.importorskip("torch")
    from kklcasadi.train.bank import BankConfig

    with pytest.raises((ValueError, TypeError), match=match):
        BankConfig(**{field: value})
    with pytest.raises(ValueError, match="teacher: expected None with the EKF block"):
        BankConfig(ekf_block=True, teacher="models/duffing/bank")


def test_kklcasadi_train_refuses_the_block_without_a_family_before_training(tmp_path, capsys):
    pytest.importorskip("torch")
    from kklcasadi.cli import main

    code = main(["train", "--system", "duffing", "--ekf-block", "--out", str(tmp_path / "m"), "--quiet"])
    assert code == 2 and not (tmp_path / "m").exists()
    assert "error: --ekf-block: expected a plant with parameters" in capsys.readouterr().err


def test_the_c_step_with_the_vector_kernels_is_within_their_tolerance(block_dir, capsys):
    import re

    from kklcasadi.evaluation.bench.observer_step import bench_observer_step
    from kklcasadi.observer.codegen import VECTOR_MATH_TOLERANCE

    if shutil.which("gcc") is None:
        pytest.skip("no gcc")
    bench_observer_step(block_dir, n_calls=2, repeat=1, callgrind=False)
    checks = dict(re.findall(r"^(.+?) +max \|difference\| from the CasADi VM: (\S+)$", capsys.readouterr().out, re.M))
    assert float(checks["C default (ca.external)"]) <= VECTOR_MATH_TOLERANCE


@pytest.mark.parametrize("name", ["duffing/bank", "vdp/bank"])
def test_a_card_without_the_block_steps_as_its_filters_and_copies_bit_for_bit(name):
    """Shipped observers with model copies and no block: the observer's latent step is the filter bank's exact step
    and the model copies' step, stacked, as before the block existed."""
    from kklcasadi.model.files import load_model

    obs = kc.load_observer(name)
    model = load_model(obs.model.path)
    spec = model.spec.architecture
    assert spec.n_ekf == 0 and not obs.exact_only
    bank, copies = spec.filter_bank(model.arrays), spec.model_copies(model.arrays, obs.system)
    assert copies is not None
    rng = np.random.default_rng(1)
    z, w = rng.normal(size=obs.nz) * 0.3, rng.normal(size=obs.memory_shape)
    y, y_next, u_next = rng.normal(size=obs.ny), rng.normal(size=obs.ny), rng.normal(size=obs.nu)
    z_next = np.asarray(obs.step(z, w, y, y_next, u_next)[0]).ravel()
    u = w.ravel()[obs.ny:]                                   # the memory [y_k; u_k]: the input held over the step
    n = bank.nz
    np.testing.assert_array_equal(z_next[:n], np.asarray(bank.step_function(obs.dt)(z[:n], y, y_next, u)).ravel())
    np.testing.assert_array_equal(z_next[n:], np.asarray(copies.step_function(obs.dt)(z[n:], y, y_next, u)).ravel())


def test_training_refuses_a_block_that_diverged_on_a_run(monkeypatch, tmp_path):
    """An augmented EKF that diverges on a training run (Van der Pol's, on one of 3000 runs with Student-t noise at
    twice the nominal level) is a one-line error naming the block, not a NaN in the decoder's normalisation."""
    pytest.importorskip("torch")
    from kklcasadi.plant.runs import RolloutConfig
    from kklcasadi.train import LoopConfig, bank, default_config, train_observer
    from kklcasadi.train.decoder import DecoderConfig

    real = bank.operational_data

    def diverged(*args, **kwargs):
        data = real(*args, **kwargs)
        data.z[data.run == 1, -1] = np.inf
        return data

    monkeypatch.setattr(bank, "operational_data", diverged)
    config = replace(default_config("duffing", "bank"), y_poles=(0.5,), u_poles=(1.0,), members=1,
                     rollouts=RolloutConfig(n_traj=3, T=3.0), ekf_block=True,
                     decoder=DecoderConfig(hidden=(4,), loop=LoopConfig(epochs=1, batch_size=64)))
    with pytest.raises(ValueError, match=r"^ekf_block: expected an augmented EKF that stays finite on every training "
                       r"run, received one that diverged on 1 of 3 runs \(the first, run 1\)"):
        train_observer(kc.systems.get("duffing", param_spread=0.3), "bank", tmp_path / "m", config=config, seed=3,
                       progress=False)
