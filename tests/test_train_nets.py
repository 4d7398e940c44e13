"""The torch networks: the specified forward passes, exact collapses, per-sample LoRA deltas,
jvp/vmap, and bitwise array round trips."""

import numpy as np
import pytest
import torch

from kklcasadi.nets.specs import ACTIVATIONS, HyperSpec, MLPSpec, ObsSpec, lora_target_shapes
from kklcasadi.train.nets import MLP, GRUContext, LoRAHyperNet, ObsInjection, mlp_forward_lora


@pytest.fixture(autouse=True)
def float64():
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    torch.manual_seed(0)
    yield
    torch.set_default_dtype(previous)


def numpy_mlp(arrays, prefix, spec, x):
    act = {"tanh": np.tanh, "relu": lambda v: np.maximum(v, 0),
           "softplus": lambda v: np.log1p(np.exp(v)), "identity": lambda v: v}[spec.activation]
    v = (x - arrays[f"{prefix}/in_mean"]) / arrays[f"{prefix}/in_std"]
    n_layers = len(spec.layer_shapes)
    for i in range(n_layers):
        v = arrays[f"{prefix}/W{i}"] @ v + arrays[f"{prefix}/b{i}"]
        v = v if i == n_layers - 1 else act(v)
    if spec.skip:
        v = v + arrays[f"{prefix}/Wskip"] @ ((x - arrays[f"{prefix}/in_mean"]) / arrays[f"{prefix}/in_std"])
    return v * arrays[f"{prefix}/out_std"] + arrays[f"{prefix}/out_mean"]


def make_dyn(nu=2, rank=3):
    encoder, decoder = MLP((2, 8, 8, 5)), MLP((5, 8, 8, 2), "softplus")
    hyper = LoRAHyperNet(encoder.spec.layer_shapes + decoder.spec.layer_shapes, nu, hidden=6,
                         embed=4, backbone=(10, 10), rank=rank, scale_init=1.0)
    return encoder, decoder, hyper


# ----------------------------------------------------------------------------- MLP

@pytest.mark.parametrize("activation,skip", [(a, False) for a in ACTIVATIONS] + [("tanh", True), ("relu", True)])
def test_mlp_forward_is_the_specified_formula(activation, skip):
    mlp = MLP((3, 6, 6, 2), activation, skip=skip)
    rng = np.random.default_rng(0)
    mlp.set_normalisation(rng.normal(size=3), [0.5, 1.0, 2.0], [1.0, -1.0], [3.0, 0.2])
    if skip:
        assert torch.equal(mlp.skip, torch.zeros(2, 3))      # starts as the network without it
        with torch.no_grad():
            mlp.skip.copy_(torch.as_tensor(rng.normal(size=(2, 3))))
    arrays = mlp.to_arrays("net")
    x = rng.normal(size=(4, 3))
    out = mlp(torch.tensor(x)).detach().numpy()
    for row, x_row in zip(out, x):
        np.testing.assert_allclose(row, numpy_mlp(arrays, "net", mlp.spec, x_row), rtol=1e-13)
    assert mlp(torch.zeros(7, 4, 3)).shape == (7, 4, 2)
    assert mlp.spec.to_card() == {"sizes": [3, 6, 6, 2], "activation": activation, **({"skip": True} if skip else {})}


def test_the_skip_path_keeps_growing_where_the_layers_saturate():
    mlp = MLP((1, 8, 1), "tanh", skip=True)
    with torch.no_grad():
        mlp.skip.fill_(0.5)
    far = mlp(torch.tensor([[1e3], [2e3]])).detach().numpy().ravel()
    plain = MLP.from_arrays({k: v for k, v in mlp.to_arrays("net").items() if k != "net/Wskip"}, "net",
                            MLPSpec((1, 8, 1), "tanh"))
    flat = plain(torch.tensor([[1e3], [2e3]])).detach().numpy().ravel()
    assert far[1] - far[0] == pytest.approx(500.0, rel=1e-9)     # slope 0.5 off the data
    assert flat[1] - flat[0] == pytest.approx(0.0, abs=1e-9)     # tanh levelled off


@pytest.mark.parametrize("entry, field", [({"sizes": [2, 3], "activation": "tanh", "skip": 1}, "skip"),
                                          ({"sizes": [2, 3], "activation": "tanh", "skip": "yes"}, "skip"),
                                          ({"sizes": [2, 3], "activation": "tanh", "bias": True}, "mlp")])
def test_an_mlp_card_with_a_bad_skip_entry_is_refused(entry, field):
    with pytest.raises(ValueError, match=f"'mlp{'.skip' if field == 'skip' else ''}'"):
        MLPSpec.from_card(entry)
    assert MLPSpec.from_card({"sizes": [2, 3], "activation": "tanh"}).skip is False
    with_skip = MLPSpec.from_card({"sizes": [2, 3], "activation": "tanh", "skip": True})
    assert with_skip.array_shapes("p")["p/Wskip"] == (3, 2)


def test_softplus_is_stable_for_large_inputs():
    mlp = MLP((1, 1, 1), "softplus")
    with torch.no_grad():
        mlp.layers[0].weight.fill_(1.0)
        mlp.layers[0].bias.fill_(0.0)
    x = torch.tensor([[-800.0], [-30.0], [0.0], [30.0], [800.0]])
    hidden = mlp.act(mlp.layers[0](x))
    expected = torch.tensor([[0.0], [np.log1p(np.exp(-30.0))], [np.log(2.0)],
                             [30.0 + np.log1p(np.exp(-30.0))], [800.0]])
    torch.testing.assert_close(hidden, expected, rtol=1e-15, atol=0)


def test_unknown_activation_lists_the_known_ones():
    with pytest.raises(ValueError, match="tanh, relu, softplus, identity"):
        MLP((2, 3), "gelu")


def test_set_normalisation_checks_shapes_and_scales():
    mlp = MLP((2, 3))
    with pytest.raises(ValueError, match="in_mean.*shape"):
        mlp.set_normalisation(np.zeros(3), np.ones(2), np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="out_std.*positive"):
        mlp.set_normalisation(np.zeros(2), np.ones(2), np.zeros(3), np.array([1.0, 0.0, 1.0]))
    mlp.set_normalisation(torch.zeros(2), torch.ones(2), np.zeros(3), [1.0, 2.0, 3.0])
    assert mlp.out_std.tolist() == [1.0, 2.0, 3.0]


# ----------------------------------------------------------------------------- GRU

def test_gru_is_the_bias_free_torch_cell_with_gate_order_r_z_n():
    gru = GRUContext(2, 4)
    arrays = gru.to_arrays("g")
    w = np.random.default_rng(0).normal(size=(7, 2))
    def sigmoid(v):
        return 1 / (1 + np.exp(-v))

    h = np.zeros(4)
    for x in w:
        gi, gh = arrays["g/W_ih"] @ x, arrays["g/W_hh"] @ h
        r, z = sigmoid(gi[:4] + gh[:4]), sigmoid(gi[4:8] + gh[4:8])
        n = np.tanh(gi[8:] + r * gh[8:])
        h = (1 - z) * n + z * h
    np.testing.assert_allclose(gru(torch.tensor(w)).detach().numpy(), h, rtol=1e-13)
    assert gru(torch.tensor(w)[None]).shape == (1, 4)
    assert {name: a.shape for name, a in arrays.items()} == {"g/W_ih": (12, 2), "g/W_hh": (12, 4)}


@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
def test_gru_equals_torch_nn_gru_and_supports_jvp_and_vmap():
    gru = GRUContext(2, 5)
    w, dw = torch.randn(3, 11, 2), torch.randn(3, 11, 2)
    torch.testing.assert_close(gru(w), gru.gru(w)[1][0], rtol=1e-13, atol=1e-15)
    torch.testing.assert_close(torch.func.vmap(gru)(w), gru(w), rtol=1e-14, atol=1e-15)
    _, tangent = torch.func.jvp(gru, (w,), (dw,))
    _, expected = torch.func.jvp(lambda w: gru.gru(w)[1][0], (w,), (dw,))
    torch.testing.assert_close(tangent, expected, rtol=1e-12, atol=1e-14)


def test_gru_state_stays_exactly_zero_for_a_zero_window():
    assert torch.equal(GRUContext(2, 5)(torch.zeros(3, 40, 2)), torch.zeros(3, 5))


def test_gru_rejects_a_window_of_the_wrong_width():
    with pytest.raises(ValueError, match="w: expected"):
        GRUContext(2, 5)(torch.zeros(3, 40, 1))


# ----------------------------------------------------------------------------- obs

def test_obs_gain_is_the_row_major_mlp_output_and_injection_is_linear_in_u():
    obs = ObsInjection(5, 2, hidden=6, proj=3, gain_hidden=(8, 8))
    z, w, u = torch.randn(4, 5), torch.randn(4, 10, 2), torch.randn(4, 2)
    flat = obs.gain_net(torch.cat([z, obs.proj(obs.context(w))], dim=-1))
    gain = obs.gain(z, w)
    assert gain.shape == (4, 5, 2)
    assert torch.equal(gain[:, 3, 1], flat[:, 3 * 2 + 1])
    torch.testing.assert_close(obs(z, w, u), (gain @ u[..., None])[..., 0], rtol=1e-14, atol=0)
    assert torch.equal(obs(z, w, torch.zeros(4, 2)), torch.zeros(4, 5))
    assert obs.spec.to_card() == {"context": {"hidden": 6, "proj": 3},
                                  "gain": {"sizes": [8, 8, 8, 10], "activation": "tanh"}}


def test_obs_defaults_are_the_papers():
    obs = ObsInjection(5, 1)
    assert obs.spec.to_card() == {"context": {"hidden": 64, "proj": 16},
                                  "gain": {"sizes": [21, 64, 64, 5], "activation": "tanh"}}
    assert obs.proj.bias is None and obs.context.gru.bias is False


def test_obs_rejects_misshaped_inputs():
    obs = ObsInjection(3, 2, hidden=4, proj=2, gain_hidden=(5,))
    with pytest.raises(ValueError, match="z: expected"):
        obs(torch.zeros(1, 4), torch.zeros(1, 3, 2), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="u: expected"):
        obs(torch.zeros(1, 3), torch.zeros(1, 3, 2), torch.zeros(1, 1))


# ----------------------------------------------------------------------------- dyn

def test_lora_factor_shapes_and_defaults():
    encoder, decoder, hyper = make_dyn(rank=3)
    factors = hyper(torch.randn(5, 12, 2))
    assert len(factors) == 6
    for (a, b), (d_out, d_in) in zip(factors, hyper.target_shapes):
        assert a.shape == (5, d_out, 3) and b.shape == (5, d_in, 3)
    default = LoRAHyperNet([(3, 2)], 1)
    assert default.spec.to_card() == {"hyper": {"hidden": 64, "embed": 16, "backbone": [64, 64],
                                                "rank": 4}}
    assert default.scale.item() == 0.01 and default.scale.requires_grad


def test_lora_collapses_exactly_for_a_zero_window():
    encoder, decoder, hyper = make_dyn()
    factors = hyper(torch.zeros(3, 20, 2))
    assert all(torch.equal(t, torch.zeros_like(t)) for pair in factors for t in pair)
    z = torch.randn(3, 5) * 3
    assert torch.equal(mlp_forward_lora(decoder, z, factors[3:], hyper.scale), decoder(z))


def test_lora_layer_equals_the_dense_weight_change():
    encoder, decoder, hyper = make_dyn()
    w, z = torch.randn(1, 9, 2), torch.randn(1, 5)
    factors = hyper(w)[3:]
    dense = MLP(decoder.spec.sizes, decoder.spec.activation)
    dense.load_state_dict(decoder.state_dict())
    with torch.no_grad():
        for layer, (a, b) in zip(dense.layers, factors):
            layer.weight += hyper.scale * a[0] @ b[0].T
    torch.testing.assert_close(mlp_forward_lora(decoder, z, factors, hyper.scale), dense(z),
                               rtol=1e-13, atol=1e-15)


def test_lora_deltas_are_per_sample():
    encoder, decoder, hyper = make_dyn()
    w, z = torch.randn(2, 15, 2), torch.randn(2, 5)
    batched = mlp_forward_lora(decoder, z, hyper(w)[3:], hyper.scale)
    for k in range(2):
        one = mlp_forward_lora(decoder, z[k:k + 1], hyper(w[k:k + 1])[3:], hyper.scale)
        torch.testing.assert_close(batched[k:k + 1], one, rtol=1e-14, atol=1e-15)
    swapped = mlp_forward_lora(decoder, z, hyper(w.flip(0))[3:], hyper.scale)
    assert not torch.allclose(batched, swapped)


@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
def test_lora_supports_jvp_in_x_and_w_and_vmap():
    encoder, decoder, hyper = make_dyn()
    x, w = torch.randn(4, 2), torch.randn(4, 8, 2)
    dx, dw = torch.randn(4, 2), torch.randn(4, 8, 2)

    def encode(x, w):
        return mlp_forward_lora(encoder, x, hyper(w)[:3], hyper.scale)

    _, tangent = torch.func.jvp(encode, (x, w), (dx, dw))
    jac_x, jac_w = torch.autograd.functional.jacobian(encode, (x, w))
    expected = torch.einsum("bibj,bj->bi", jac_x, dx) + torch.einsum("bibtk,btk->bi", jac_w, dw)
    torch.testing.assert_close(tangent, expected, rtol=1e-12, atol=1e-14)

    factors = hyper(w)[:3]
    mapped = torch.func.vmap(lambda x, f: mlp_forward_lora(encoder, x, f, hyper.scale))(x, factors)
    torch.testing.assert_close(mapped, encode(x, w), rtol=1e-14, atol=1e-15)


def test_mlp_forward_lora_rejects_factors_that_do_not_fit():
    encoder, decoder, hyper = make_dyn()
    factors = hyper(torch.randn(1, 4, 2))
    with pytest.raises(ValueError, match="expected 3"):
        mlp_forward_lora(decoder, torch.randn(1, 5), factors, hyper.scale)
    with pytest.raises(ValueError, match=r"factors\[0\]"):
        mlp_forward_lora(decoder, torch.randn(1, 5), factors[:3], hyper.scale)


# ----------------------------------------------------------------------------- arrays

@pytest.mark.parametrize("skip", [False, True])
def test_mlp_roundtrip_is_bitwise(skip):
    mlp = MLP((3, 7, 2), "relu", skip=skip)
    if skip:
        with torch.no_grad():
            mlp.skip.normal_()
    mlp.set_normalisation([1.0, 2.0, 3.0], [0.5, 0.25, 4.0], [0.0, 1.0], [2.0, 3.0])
    arrays = mlp.to_arrays("net")
    spec = MLPSpec.from_card(mlp.spec.to_card())
    assert {k: v.shape for k, v in arrays.items()} == spec.array_shapes("net")
    assert all(v.dtype == np.float64 for v in arrays.values())
    again = MLP.from_arrays(arrays, "net", spec)
    x = torch.randn(5, 3)
    assert torch.equal(again(x), mlp(x))


def test_gru_roundtrip_is_bitwise():
    gru = GRUContext(2, 5)
    again = GRUContext.from_arrays(gru.to_arrays("g"), "g", 2, 5)
    w = torch.randn(3, 8, 2)
    assert torch.equal(again(w), gru(w))


def test_obs_roundtrip_is_bitwise():
    obs = ObsInjection(4, 2, hidden=5, proj=3, gain_hidden=(6,), activation="softplus")
    arrays = obs.to_arrays()
    assert {k: v.shape for k, v in arrays.items()} == ObsSpec.from_card(
        obs.spec.to_card()).array_shapes()
    again = ObsInjection.from_arrays(arrays, "", ObsSpec.from_card(obs.spec.to_card()))
    z, w, u = torch.randn(3, 4), torch.randn(3, 6, 2), torch.randn(3, 2)
    assert torch.equal(again(z, w, u), obs(z, w, u))


def test_lora_roundtrip_is_bitwise():
    encoder, decoder, hyper = make_dyn()
    arch = {"encoder": encoder.spec.to_card(), "decoder": decoder.spec.to_card(), **hyper.spec.to_card()}
    arrays = hyper.to_arrays()
    targets = lora_target_shapes(encoder.spec, decoder.spec)
    assert {k: v.shape for k, v in arrays.items()} == HyperSpec.from_card(arch).array_shapes(
        "hyper", 2, targets)
    again = LoRAHyperNet.from_arrays(arrays, "hyper", HyperSpec.from_card(arch), targets, nu=2)
    w = torch.randn(3, 6, 2)
    for (a1, b1), (a2, b2) in zip(again(w), hyper(w)):
        assert torch.equal(a1, a2) and torch.equal(b1, b2)
    assert torch.equal(again.scale, hyper.scale)


def test_from_arrays_reports_missing_and_misshaped_arrays():
    mlp = MLP((3, 4, 2))
    arrays = mlp.to_arrays("net")
    with pytest.raises(ValueError, match="net/W0.*missing"):
        MLP.from_arrays({k: v for k, v in arrays.items() if k != "net/W0"}, "net", mlp.spec)
    obs = ObsInjection(3, 1, hidden=4, proj=2, gain_hidden=(5,))
    arrays = obs.to_arrays()
    arrays["context/proj/W"] = np.zeros((2, 5))
    with pytest.raises(ValueError, match=r"context/proj/W.*shape \(2, 4\)"):
        ObsInjection.from_arrays(arrays, "", obs.spec)
