"""Training over a family of plants and with noise as it is (issue 46.2, 46.3): the operational runs draw each
run's parameters from the plant's box and its measurement noise from the recipe's noise models; the card
records both."""

from dataclasses import replace

import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.plant.noise import noise_model
from kklcasadi.plant.runs import RolloutConfig, rollouts

CFG = RolloutConfig(n_traj=8, T=4.0, kinds=("sinusoid", "feedback", "pd", "square"), regime="train",
                    noise_range=(1.0, 1.0), method="rk", substeps=2)
NOISE = {"process_std": 0.1, "measurement_std": 0.1}


def test_each_run_draws_its_parameters_from_the_box():
    family = kc.systems.get("vdp", param_spread=0.3)
    batch = rollouts(family, CFG, seed=3, **NOISE)
    theta = family.sample_params(8, np.random.default_rng([3, 7]))
    assert np.all((theta >= 0.7) & (theta <= 1.3)) and len(np.unique(theta[:, 0])) == 8
    # every run, open or closed loop, is the run of the plant at its values (the same draws otherwise)
    for i in range(8):
        fixed = rollouts(family.at(theta[i]), CFG, seed=3, **NOISE)
        np.testing.assert_allclose(batch.x[i], fixed.x[i], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(batch.u[i], fixed.u[i], rtol=1e-10, atol=1e-10)
    nominal = rollouts(kc.systems.get("vdp"), CFG, seed=3, **NOISE)
    assert not np.allclose(batch.x, nominal.x)
    np.testing.assert_array_equal(nominal.x, rollouts(family.at(family.param_nominal), CFG, seed=3, **NOISE).x)


def test_each_run_draws_its_noise_model():
    plant = kc.systems.get("duffing")
    gauss = rollouts(plant, CFG, seed=4, **NOISE)
    np.testing.assert_array_equal(rollouts(plant, replace(CFG, noise_models=("gauss",)), seed=4, **NOISE).y, gauss.y)
    quantised = rollouts(plant, replace(CFG, noise_models=("quantised:0.2",)), seed=4, **NOISE)
    np.testing.assert_allclose(quantised.y / 0.2, np.round(quantised.y / 0.2), atol=1e-9)    # open and closed loop
    open_loop = [0, 3, 4, 7]                                          # sinusoid, square: the same plant runs
    np.testing.assert_array_equal(quantised.x[open_loop], gauss.x[open_loop])
    np.testing.assert_array_equal(quantised.y[open_loop], 0.2 * np.floor(gauss.y[open_loop] / 0.2 + 0.5))
    mixed = rollouts(plant, replace(CFG, n_traj=40, kinds=("zero",), noise_models=("gauss", "student-t:1")), seed=5,
                     **NOISE)
    residual = mixed.y[..., 0] - mixed.x[..., 0]
    kurtosis = np.array([np.mean(r ** 4) / np.mean(r ** 2) ** 2 for r in residual])
    assert np.sum(kurtosis < 4) >= 10 and np.sum(kurtosis > 10) >= 10      # Gaussian runs (3) and Cauchy ones
    with pytest.raises(ValueError, match=r"noise_model: expected parts among"):
        RolloutConfig(noise_models=("laplace",))
    assert RolloutConfig(noise_models=("outliers:0.05,10",)).noise_models == (str(noise_model("outliers:0.05,10")),)


def test_training_over_a_family_records_the_box_and_the_draw(tmp_path):
    pytest.importorskip("torch")
    from kklcasadi.model.files import load_model
    from kklcasadi.train import LoopConfig, default_config, train_observer
    from kklcasadi.train.decoder import DecoderConfig

    family = kc.systems.get("duffing", param_spread=0.3)
    config = replace(default_config("duffing", "bank"), members=1, copies=(),
                     rollouts=replace(CFG, noise_models=("gauss", "student-t:2")),
                     decoder=DecoderConfig(hidden=(8,), loop=LoopConfig(epochs=1, batch_size=64)))
    path = train_observer(family, "bank", tmp_path / "robust", config=config, progress=False)
    card = load_model(path).card
    assert card["system"]["fingerprint"] == kc.systems.get("duffing").fingerprint     # the nominal plant
    runs = card["training"]["runs"]
    assert runs["params"]["names"] == ["alpha", "beta"] and runs["params"]["box"] == [[0.7, 1.3], [0.7, 1.3]]
    assert "default_rng([0, 7])" in runs["params"]["draw"] and sum(runs["noise_models"].values()) == 8
    assert card["training"]["rollouts"]["noise_models"] == ["gauss", "student-t:2"]
    assert kc.load_observer(path, system=family).system.fingerprint == kc.systems.get("duffing").fingerprint
    with pytest.raises(ValueError, match=r"^system: expected a plant without parameters for method 'autonomous'"):
        train_observer(family, "autonomous", tmp_path / "auto", progress=False)


def test_the_training_flags(capsys, tmp_path):
    from kklcasadi.cli import build_parser, main
    from kklcasadi.cli.train import training_config

    args = build_parser().parse_args(["train", "--system", "duffing", "--param-spread", "0.3", "--runs", "40",
                                      "--noise-model", "gauss", "student-t:3", "--out", str(tmp_path / "m")])
    config = training_config(kc.systems.get("duffing"), "bank", args)
    assert config.rollouts.n_traj == 40 and config.rollouts.noise_models == ("gauss", "student-t:3")
    for given, scale in ((["1.5"], 1.5), (["1", "1.5"], (1.0, 1.5))):
        args = build_parser().parse_args(["train", "--system", "vdp", "--teacher", "vdp/bank", "--input-scale", *given,
                                          "--out", str(tmp_path / "s")])
        assert training_config(kc.systems.get("vdp"), "bank", args).rollouts.input_scale == scale
    assert main(["train", "--system", "vdp", "--input-scale", "2", "1", "--out", str(tmp_path / "s")]) == 2
    assert "error: --input-scale: expected a factor > 0 or a range 0 < lo <= hi, received (2.0, 1.0)" in \
        capsys.readouterr().err
    assert main(["train", "--system", "rossler", "--param-spread", "0.3", "--out", str(tmp_path / "r")]) == 2
    assert "error: --param-spread: expected None for 'rossler', which has no parameterised form" in \
        capsys.readouterr().err
    assert main(["train", "--plant", "examples/damped3_plant.py:make_plant", "--param-spread", "0.3",
                 "--out", str(tmp_path / "p")]) == 2
    assert "error: --param-spread: makes the family of a shipped --system" in capsys.readouterr().err
    assert main(["train", "--system", "duffing", "--method", "autonomous", "--noise-model", "student-t:3",
                 "--out", str(tmp_path / "a")]) == 2
    assert "error: --noise-model: only --method bank takes it" in capsys.readouterr().err
