"""Proposition 1 certificate: exact on the linear plant, holds under perturbation, all method paths."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

import kklcasadi as kc
from kklcasadi.evaluation.certificate import Certificate, certificate, decoder_lipschitz_upper
from kklcasadi.model.files import save_model
from kklcasadi.plant.systems import LINEAR_F, LINEAR_H

SMALL = {"n_points": 600, "n_labels": 4, "n_trials": 3, "T": 12.0, "t_settle": 8.0}


def _linear_model(directory: Path, perturbation: float = 0.0, seed: int = 0) -> Path:
    """The exact KKL map of the linear plant (Sylvester ``T F - A T = B H``) as identity MLPs.

    The decoder is the pseudo-inverse of ``T``; ``perturbation`` adds Gaussian noise of that
    standard deviation to both weight matrices.
    """
    plant = kc.systems.get("linear")
    design = kc.Design.paper(plant)
    T = scipy.linalg.solve_sylvester(-design.A, LINEAR_F, design.B @ LINEAR_H)
    rng = np.random.default_rng(seed)
    maps = {"encoder": T, "decoder": np.linalg.pinv(T)}
    arrays, arch = {}, {}
    for prefix, W in maps.items():
        W = W + perturbation * rng.normal(size=W.shape)
        d_out, d_in = W.shape
        arrays.update({f"{prefix}/W0": W, f"{prefix}/b0": np.zeros(d_out),
                       f"{prefix}/in_mean": np.zeros(d_in), f"{prefix}/in_std": np.ones(d_in),
                       f"{prefix}/out_mean": np.zeros(d_out), f"{prefix}/out_std": np.ones(d_out)})
        arch[prefix] = {"sizes": [d_in, d_out], "activation": "identity"}
    card = {"method": "autonomous", "system": {"name": "linear", "nx": 2, "nu": 1, "ny": 1},
            "design": {"A": design.A.tolist(), "B": design.B.tolist()}, "dt": 0.05, "window": 1,
            "architecture": arch, "base": None, "noise": {"measurement_std": 0.0},
            "training": {"note": f"exact Sylvester map, perturbation {perturbation}"}}
    return save_model(directory, arrays, card)


def test_exact_linear_map_has_zero_residual_and_its_bound_holds(tmp_path):
    obs = kc.load_observer(_linear_model(tmp_path / "exact"))
    cert = certificate(obs, kinds=("zero",), **SMALL)
    assert isinstance(cert, Certificate)
    assert (cert.kappa, cert.lam, cert.ell_inj, cert.lam_eff) == pytest.approx((1.0, 1.0, 0.0, 1.0))
    assert cert.eps_pde < 1e-12
    assert cert.eps_enc < 1e-6 and cert.eps_dec < 1e-6
    pinv_norm = np.linalg.norm(obs.model.arrays["decoder/W0"], 2)
    assert cert.ell_dec == pytest.approx(pinv_norm, rel=1e-10)
    assert cert.ell_dec_upper == pytest.approx(pinv_norm, rel=1e-10)
    assert cert.bound < 1e-5 and not cert.vacuous
    # the sampled observer's own error is its O(dt^2) discretisation error, which the sampled-data
    # bound covers and the continuous-time one does not
    assert cert.observed < 1e-3
    assert cert.holds_sampled and not cert.vacuous_sampled
    assert cert.observed <= cert.bound_sampled + cert.transient_sampled
    assert "holds on the runs" in str(cert)


@pytest.mark.parametrize("perturbation", [0.02, 0.1])
def test_perturbed_map_has_a_residual_and_the_bound_still_holds(tmp_path, perturbation):
    obs = kc.load_observer(_linear_model(tmp_path / "perturbed", perturbation, seed=3))
    cert = certificate(obs, kinds=("zero",), **SMALL)
    assert cert.eps_pde > 1e-3 and cert.eps_enc > 1e-4 and cert.eps_dec > 1e-4
    assert cert.observed > 1e-4
    assert cert.holds and cert.holds_sampled
    assert cert.observed <= cert.bound + cert.transient


def test_vacuous_bound_is_said_plainly(tmp_path):
    cert = certificate(kc.load_observer(_linear_model(tmp_path / "exact")), kinds=("zero",),
                       **SMALL)
    worse = dataclasses.replace(cert, bound=2 * cert.diameter)
    assert worse.vacuous
    assert "VACUOUS" in str(worse) and "says nothing" in str(worse)
    assert dataclasses.replace(cert, bound=np.inf).vacuous


def test_decoder_lipschitz_upper_folds_the_normalisation(model_dir_factory):
    obs = kc.load_observer(model_dir_factory("autonomous", "duffing", seed=2))
    a = obs.model.arrays
    expected = (np.linalg.norm(a["decoder/out_std"][:, None] * a["decoder/W2"], 2)
                * np.linalg.norm(a["decoder/W1"], 2)
                * np.linalg.norm(a["decoder/W0"] / a["decoder/in_std"][None, :], 2))
    assert decoder_lipschitz_upper(obs) == pytest.approx(expected, rel=1e-12)


def test_decoder_lipschitz_upper_adds_the_skip_path_and_bounds_the_slopes(model_dir_factory):
    obs = kc.load_observer(model_dir_factory("autonomous", "duffing", seed=2, skip=True))
    a = obs.model.arrays
    layers = (np.linalg.norm(a["decoder/out_std"][:, None] * a["decoder/W2"], 2)
              * np.linalg.norm(a["decoder/W1"], 2)
              * np.linalg.norm(a["decoder/W0"] / a["decoder/in_std"][None, :], 2))
    skip = np.linalg.norm(a["decoder/out_std"][:, None] * a["decoder/Wskip"] / a["decoder/in_std"][None, :], 2)
    bound = decoder_lipschitz_upper(obs)
    assert skip > 0 and bound == pytest.approx(layers + skip, rel=1e-12)
    rng = np.random.default_rng(0)
    decode = lambda z: np.asarray(obs.decode(z, np.zeros((obs.window, obs.nu)))).ravel()  # noqa: E731
    for _ in range(50):
        z1, z2 = rng.normal(size=(2, obs.nz)) * 3
        assert np.linalg.norm(decode(z1) - decode(z2)) <= bound * np.linalg.norm(z1 - z2) * (1 + 1e-12)


def test_dyn_collapses_to_its_base_at_zero_input_and_differs_under_input(model_dir_factory):
    dyn_dir = model_dir_factory("dyn", "duffing", seed=7, base=True)
    dyn = kc.load_observer(dyn_dir)
    base = kc.load_observer(dyn_dir.parent / "autonomous")
    small = {**SMALL, "n_points": 200, "n_trials": 1, "T": 3.0, "t_settle": 1.0, "n_labels": 2}
    c_dyn, c_base = (certificate(o, kinds=("zero",), **small) for o in (dyn, base))
    for name in ("eps_pde", "eps_enc", "eps_dec", "ell_dec", "eps_step", "observed"):
        assert getattr(c_dyn, name) == pytest.approx(getattr(c_base, name), rel=1e-9, abs=1e-12)
    d_dyn, d_base = (certificate(o, kinds=("square",), **small) for o in (dyn, base))
    assert d_dyn.eps_pde != pytest.approx(d_base.eps_pde, rel=1e-6)


@pytest.mark.parametrize("method", ["inject", "obs"])
def test_nonlinear_latent_dynamics_shrink_the_decay_rate(model_dir_factory, method):
    obs = kc.load_observer(model_dir_factory(method, "duffing", seed=8, base=method == "obs"))
    small = {**SMALL, "n_points": 200, "n_trials": 1, "T": 3.0, "t_settle": 1.0, "n_labels": 2}
    cert = certificate(obs, kinds=("constant",), **small)
    assert cert.ell_inj > 0
    assert cert.lam_eff == pytest.approx(cert.lam - cert.kappa * cert.ell_inj)
    assert np.isfinite(cert.eps_pde) and np.isfinite(cert.eps_step) and cert.rho_step > 0
    if cert.lam_eff <= 0:
        assert cert.vacuous and cert.bound == np.inf


@pytest.mark.parametrize("kwargs, error, fragment", [
    ({"kinds": ()}, ValueError, "kinds"),
    ({"kinds": ("ramp",)}, ValueError, "kinds"),
    ({"n_points": 0}, ValueError, "n_points"),
    ({"t_settle": 50.0}, ValueError, "t_settle"),
])
def test_bad_arguments_are_named(tmp_path, kwargs, error, fragment):
    obs = kc.load_observer(_linear_model(tmp_path / "exact"))
    with pytest.raises(error, match=fragment):
        certificate(obs, **kwargs)


def test_observer_type_is_checked():
    with pytest.raises(TypeError, match="observer"):
        certificate("models/duffing/inject")


def test_certificate_command_prints_and_saves(tmp_path, capsys):
    import json

    from kklcasadi.cli import main

    model = _linear_model(tmp_path / "exact")
    out = tmp_path / "cert.json"
    assert main(["certificate", str(model), "--kinds", "zero", "--points", "300", "--labels", "2", "--trials", "2",
                 "--T", "6", "--settle", "4", "--out", str(out)]) == 0
    assert "Proposition 1 certificate: linear / autonomous" in capsys.readouterr().out
    from kklcasadi import provenance

    data = json.loads(out.read_text())
    assert data["provenance"]["command"].startswith("kklcasadi certificate ") and data["provenance"]["seeds"] == {
        "seed": 0}
    record = provenance.json_payload(data)[0]
    assert record["model"] == str(model) and record["holds_sampled"] is True
    assert record["eps_pde"] < 1e-12 and len(record["domain"]) == 2
    before = out.read_bytes()
    assert main(["certificate", str(model), "--out", str(out)]) == 2         # refused before any certificate
    assert capsys.readouterr() == ("", f"error: --out: {out} exists and this command does not overwrite; move it "
                                       "away, or choose another --out.\n")
    assert out.read_bytes() == before


@pytest.mark.parametrize("method", ["obs_stream", "bank"])
def test_certificate_refuses_what_proposition_1_does_not_cover(model_dir_factory, method):
    obs = kc.load_observer(model_dir_factory(method))
    with pytest.raises(ValueError, match=f"received method '{method}'"):
        certificate(obs)
