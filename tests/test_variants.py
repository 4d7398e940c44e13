"""The variant table: every method reads its spec, arrays, CasADi parts and hooks from one place;
a new variant is one class plus a registration; the torch and CasADi model-based injections agree."""

from dataclasses import dataclass
from typing import Optional

import casadi as ca
import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.cli import build_parser
from kklcasadi.model import variants
from kklcasadi.model.card import make_card
from kklcasadi.model.files import load_model, save_model
from kklcasadi.model.variants.base import MapsSpec, Networks, Variant, plain_maps


def test_registry_lists_every_method_and_names_unknown_ones():
    assert variants.names() == ("autonomous", "curriculum", "obs", "dyn", "inject", "obs_stream", "dyn_stream",
                                "bank")
    assert set(variants.trainable()) == set(variants.names())
    with pytest.raises(ValueError, match=r"method: expected one of \['autonomous'.*received 'lstm'"):
        variants.get("lstm")
    parser = build_parser()
    for method in variants.trainable():                        # the CLI's choices are the table's
        assert parser.parse_args(["train", "--system", "vdp", "--method", method, "--out", "m"]).method == method
    with pytest.raises(SystemExit):
        parser.parse_args(["train", "--system", "vdp", "--method", "lstm", "--out", "m"])


@pytest.mark.parametrize("method", variants.names())
def test_spec_round_trips_through_the_card(model_dir_factory, method):
    model = load_model(model_dir_factory(method, base=method != "autonomous"))
    spec, variant = model.spec, model.spec.variant
    assert variant is variants.get(method)
    assert spec.architecture.to_card() == model.card["architecture"]
    assert {k: model.card[k] for k in variant.card_fields} == variant.card_entries(spec.architecture)
    assert {k: v.shape for k, v in model.arrays.items()} == spec.array_shapes()
    obs = kc.load_observer(model.path)
    assert obs.variant is variant and obs.linear is variant.linear


@pytest.mark.parametrize("method", ["inject", "obs"])
def test_torch_model_based_injection_equals_the_casadi_one(model_dir_factory, method, rng):
    torch = pytest.importorskip("torch")
    from kklcasadi.train.nets import MLP
    from kklcasadi.train.phase2 import model_based_injection

    extra = {"model_based_injection": True} if method == "obs" else None
    obs = kc.load_observer(model_dir_factory(method, card_extra=extra))
    arch = obs.model.spec.architecture
    encoder = MLP.from_arrays(obs.model.arrays, "encoder", arch.encoder, dtype=torch.float64)
    decoder = MLP.from_arrays(obs.model.arrays, "decoder", arch.decoder, dtype=torch.float64)
    z, u = rng.normal(size=(50, obs.nz)) * 2, rng.normal(size=(50, obs.nu))
    expected = np.hstack([np.asarray(obs.model_injection(zi, ui)) for zi, ui in zip(z, u)]).T
    got = model_based_injection(obs.system, encoder, decoder, z, u)
    assert np.abs(expected).max() > 1e-2
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-10)


# ----------------------------------------------------------------------------- a new variant

@dataclass(frozen=True)
class GainSpec(MapsSpec):
    """The maps plus a constant input gain ``K`` (nz, nu), stored as the array ``gain/K``."""

    nu: int = 1

    def array_shapes(self):
        return {**super().array_shapes(), "gain/K": (self.encoder.n_out, self.nu)}


class ConstantGain(Variant):
    """zdot = A z + B y + K u: the smallest variant with its own arrays and input term."""

    name = "constant_gain"
    summary = "test variant: zdot = A z + B y + K u"
    linear = False

    def parse(self, card, sizes, where):
        maps = MapsSpec.parse_maps(card["architecture"], sizes, where)
        return GainSpec(maps.encoder, maps.decoder, sizes.nu)

    def networks(self, spec, arrays, system, window):
        encoder, decoder = plain_maps(spec, arrays, window, system.nu)
        gain = ca.DM(np.asarray(arrays["gain/K"]))

        def input_term(z: ca.MX, u: ca.MX, context: Optional[ca.MX]) -> ca.MX:
            return ca.mtimes(gain, u)

        return Networks(encoder, decoder, None, input_term)


def test_a_new_variant_is_one_class_and_one_registration(model_dir_factory, monkeypatch, tmp_path, rng):
    monkeypatch.setitem(variants.VARIANTS, "constant_gain", ConstantGain())
    base = load_model(model_dir_factory("autonomous"))
    plant = kc.systems.get("duffing")
    spec = GainSpec(base.spec.architecture.encoder, base.spec.architecture.decoder, 1)
    K = rng.normal(size=(base.spec.nz, 1))
    card = make_card(plant, kc.Design(base.A, base.B), "constant_gain", spec, dt=base.dt)
    obs = kc.load_observer(save_model(tmp_path / "gain", {**base.arrays, "gain/K": K}, card))
    z, y, u = rng.normal(size=obs.nz), rng.normal(size=1), rng.normal(size=1)
    expected = base.A @ z + base.B @ y + K @ u
    np.testing.assert_allclose(np.asarray(obs.rhs(z, y, u, np.zeros((1, 1)))).ravel(), expected,
                               rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match="gain/K.*missing"):
        save_model(tmp_path / "bad", dict(base.arrays), card)


@pytest.mark.parametrize("method", variants.names())
def test_input_free_variants_are_those_whose_step_never_reads_u(model_dir_factory, method):
    """``Variant.input_free`` (the benchmark's hand-written dense C step is written for them) holds
    exactly where the observer's latent and estimate do not depend on the input, structurally:
    neither on ``u`` nor on the memory it keeps of the inputs."""
    obs = kc.load_observer(model_dir_factory(method, base=method == "inject"))
    z, w = ca.MX.sym("z", obs.nz), ca.MX.sym("w", *obs.memory_shape)
    y, y_next, u = ca.MX.sym("y", obs.ny), ca.MX.sym("y1", obs.ny), ca.MX.sym("u", obs.nu)
    z_next, _, xhat_next = obs.step(z, w, y, y_next, u)
    outputs = ca.vertcat(z_next, xhat_next, obs.decode(z, w))
    reads_u = ca.jacobian(outputs, ca.vertcat(u, ca.vec(w))).nnz() > 0
    assert obs.variant.input_free == (not reads_u)


def test_the_training_side_registers_every_trained_variant():
    """The model layer says whether a variant trains and nothing more; the training side registers each hook."""
    pytest.importorskip("torch")
    from kklcasadi.train.registry import TRAINERS, register, trainer

    assert set(TRAINERS) == {v.name for v in variants.VARIANTS.values() if v.trains}
    assert {v.name for v in variants.VARIANTS.values() if not v.trains} == {"inject"}
    assert trainer("bank").config.__name__ == "BankConfig" and callable(trainer("bank").hook)
    with pytest.raises(ValueError, match=r"^method: expected a method not registered yet, received 'bank'"):
        register("bank", trainer("bank").hook, trainer("bank").config)
    with pytest.raises(ValueError, match=r"^method: expected a variant whose trains is True, received 'inject'"):
        register("inject", trainer("bank").hook, trainer("bank").config)
    with pytest.raises(ValueError, match=r"^method: expected one of \['autonomous'.*\(a trained method\), received "
                                         r"'inject'"):
        trainer("inject")
