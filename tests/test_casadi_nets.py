"""CasADi networks against the torch networks (float64): values and Jacobians to 1e-10, exact
collapses, folded (not unrolled) GRU, SX/MX calls, argument errors."""

import itertools
import zlib

import casadi as ca
import numpy as np
import pytest
import torch

from kklcasadi.nets import builders as casadi_nets
from kklcasadi.nets.specs import ACTIVATIONS, check_arrays, gru_array_shapes
from kklcasadi.train.nets import MLP, GRUContext, LoRAHyperNet, ObsInjection, mlp_forward_lora

TOL = 1e-10
WINDOWS = (1, 5, 30)
NUS = (1, 2)


@pytest.fixture(autouse=True)
def float64():
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def seed_of(*params) -> int:
    """A stable seed per parametrised case."""
    return zlib.crc32(repr(params).encode())


def randomise_normalisation(mlp: MLP, rng: np.random.Generator) -> None:
    """Random normalisation (and a random skip path, which starts at zero)."""
    d_in, d_out = mlp.spec.n_in, mlp.spec.n_out
    mlp.set_normalisation(rng.normal(size=d_in), rng.uniform(0.5, 2.0, d_in),
                          rng.normal(size=d_out), rng.uniform(0.5, 2.0, d_out))
    if mlp.skip is not None:
        with torch.no_grad():
            mlp.skip.copy_(torch.as_tensor(rng.normal(size=(d_out, d_in))))


def colmajor(jac, out_shape, in_shape) -> np.ndarray:
    """Return a torch Jacobian (out_shape + in_shape) in CasADi's column-major vec layout."""
    jac = np.asarray(jac).reshape(*out_shape, *in_shape)
    n_out, n_in = len(out_shape), len(in_shape)
    axes = [*reversed(range(n_out)), *(n_out + k for k in reversed(range(n_in)))]
    return jac.transpose(axes).reshape(int(np.prod(out_shape)), int(np.prod(in_shape)))


def casadi_jacobians(f: ca.Function, args) -> list[np.ndarray]:
    """Values of ca.jacobian(f(...), arg_k) for every input k at the point ``args``."""
    syms = [ca.MX.sym(f.name_in(k), *f.size_in(k)) for k in range(f.n_in())]
    out = f(*syms)
    jac = ca.Function("jacobians", syms, [ca.jacobian(out, s) for s in syms])
    return [np.array(j) for j in jac.call(list(args))]


def torch_jacobians(fun, args) -> list:
    tensors = tuple(torch.tensor(a) for a in args)
    return list(torch.autograd.functional.jacobian(fun, tensors))


def check_values_and_jacobians(f: ca.Function, fun, args, out_shape) -> None:
    expected = fun(*(torch.tensor(a) for a in args)).detach().numpy()
    np.testing.assert_allclose(np.array(f(*args)).reshape(out_shape, order="F"), expected,
                               rtol=0, atol=TOL)
    for arg, j_torch, j_casadi in zip(args, torch_jacobians(fun, args), casadi_jacobians(f, args)):
        in_shape = np.shape(arg)
        np.testing.assert_allclose(j_casadi, colmajor(j_torch.numpy(), out_shape, in_shape),
                                   rtol=0, atol=TOL)


def check_sx_mx(f: ca.Function, args) -> None:
    """Calling with SX and with MX symbols gives the numeric result."""
    expected = np.array(f(*args))
    for sym in (ca.SX, ca.MX):
        syms = [sym.sym(f.name_in(k), *f.size_in(k)) for k in range(f.n_in())]
        wrapped = ca.Function("wrapped", syms, [f(*syms)])
        np.testing.assert_allclose(np.array(wrapped(*args)), expected, rtol=0, atol=1e-13)


# ----------------------------------------------------------------------------- MLP

MLP_SIZES = [(2, 5), (3, 7, 2), (5, 16, 16, 2), (1, 4, 6, 3, 1)]


@pytest.mark.parametrize("sizes,activation,skip", [(*case, False) for case in itertools.product(MLP_SIZES, ACTIVATIONS)]
                         + [(sizes, "tanh", True) for sizes in MLP_SIZES])
def test_mlp_matches_torch(sizes, activation, skip):
    torch.manual_seed(seed_of(sizes, activation, skip))
    rng = np.random.default_rng(seed_of(sizes, activation, skip))
    mlp = MLP(sizes, activation, skip=skip)
    randomise_normalisation(mlp, rng)
    f = casadi_nets.mlp_function(mlp.spec, mlp.to_arrays("net"), "net")
    assert (f.name(), f.name_in(), f.name_out()) == ("net", ["x"], ["y"])
    for _ in range(3):
        x = rng.normal(size=sizes[0]) * 2
        check_values_and_jacobians(f, mlp, [x], (sizes[-1],))
    check_sx_mx(f, [x])


def test_mlp_layers_are_mx_with_dm_constants_and_folded_normalisation():
    torch.manual_seed(0)
    mlp = MLP((3, 8, 2), "tanh")
    randomise_normalisation(mlp, np.random.default_rng(0))
    f = casadi_nets.mlp_function(mlp.spec, mlp.to_arrays("net"), "net")
    assert f.is_a("MXFunction")
    ops = [f.instruction_id(k) for k in range(f.n_instructions())]
    assert ops.count(ca.OP_MTIMES) == 2                     # one matrix product per layer
    # folded: no elementwise subtraction/division of the input before the first product
    assert ca.OP_DIV not in ops and ca.OP_SUB not in ops


# ----------------------------------------------------------------------------- GRU

@pytest.mark.parametrize("nu,window,hidden", list(itertools.product(NUS, WINDOWS, (3, 8))))
def test_gru_matches_torch(nu, window, hidden):
    torch.manual_seed(seed_of(nu, window, hidden))
    rng = np.random.default_rng(seed_of(nu, window, hidden))
    gru = GRUContext(nu, hidden)
    f = casadi_nets.gru_function(gru.to_arrays("g"), "g", nu, hidden, window)
    assert (f.name_in(), f.name_out()) == (["w"], ["h"])
    w = rng.normal(size=(window, nu))
    check_values_and_jacobians(f, gru, [w], (hidden,))
    check_sx_mx(f, [w])
    assert np.array_equal(np.array(f(np.zeros((window, nu)))), np.zeros((hidden, 1)))


def test_gru_is_folded_not_unrolled():
    gru = GRUContext(2, 8)
    arrays = gru.to_arrays("g")
    short, long = (casadi_nets.gru_function(arrays, "g", 2, 8, n) for n in (5, 200))
    assert short.n_instructions() == long.n_instructions()
    assert short.n_nodes() == long.n_nodes()


# ----------------------------------------------------------------------------- obs

@pytest.mark.parametrize("nu,window,activation", list(itertools.product(NUS, WINDOWS, ACTIVATIONS)))
def test_obs_injection_matches_torch(nu, window, activation):
    nz = 5
    torch.manual_seed(seed_of(nu, window, activation))
    rng = np.random.default_rng(seed_of(nu, window, activation))
    obs = ObsInjection(nz, nu, hidden=6, proj=3, gain_hidden=(10, 10), activation=activation)
    randomise_normalisation(obs.gain_net, rng)
    arrays = obs.to_arrays()
    gain = casadi_nets.obs_gain_function(obs.spec, arrays, window)
    inj = casadi_nets.obs_injection_function(obs.spec, arrays, window)
    assert (gain.name_in(), gain.name_out()) == (["z", "w"], ["G"])
    assert (inj.name_in(), inj.name_out()) == (["z", "w", "u"], ["phi"])
    z, w, u = rng.normal(size=nz), rng.normal(size=(window, nu)), rng.normal(size=nu)
    check_values_and_jacobians(gain, lambda z, w: obs.gain(z[None], w[None])[0], [z, w], (nz, nu))
    check_values_and_jacobians(inj, lambda z, w, u: obs(z[None], w[None], u[None])[0],
                               [z, w, u], (nz,))
    check_sx_mx(inj, [z, w, u])
    # exact collapse: the injection is exactly zero at u = 0, whatever z and w
    assert np.array_equal(np.array(inj(z, w, np.zeros(nu))), np.zeros((nz, 1)))


# ----------------------------------------------------------------------------- dyn

def make_dyn(nu, activation, rank, seed, skip=False):
    """Encoder, decoder and a hypernetwork whose modulation is large enough to be tested."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    nx, nz = 2, 5
    encoder, decoder = MLP((nx, 9, 9, nz), activation), MLP((nz, 9, 9, nx), activation, skip=skip)
    randomise_normalisation(encoder, rng)
    randomise_normalisation(decoder, rng)
    hyper = LoRAHyperNet(encoder.spec.layer_shapes + decoder.spec.layer_shapes, nu, hidden=6,
                         embed=4, backbone=(10, 10), rank=rank, scale_init=1.0)
    with torch.no_grad():                         # default initialisations modulate by ~1e-4
        for head in [*hyper.heads_a, *hyper.heads_b]:
            head.weight.mul_(8.0)
        for weight in hyper.gru.parameters():
            weight.mul_(3.0)
    arch = (encoder.spec, decoder.spec, hyper.spec)
    arrays = {**encoder.to_arrays("encoder"), **decoder.to_arrays("decoder"), **hyper.to_arrays()}
    return encoder, decoder, hyper, arch, arrays


@pytest.mark.parametrize("nu,window,activation,skip", [(*case, False) for case in itertools.product(NUS, WINDOWS,
                                                                                                    ACTIVATIONS)]
                         + [(2, 5, "tanh", True)])
def test_dyn_decoder_matches_torch(nu, window, activation, skip):
    rank = 1 + seed_of(nu, window, activation) % 4
    encoder, decoder, hyper, arch, arrays = make_dyn(nu, activation, rank,
                                                     seed_of(nu, window, activation), skip)
    f = casadi_nets.lora_mlp_function(*arch, arrays, nu, window)
    assert (f.name_in(), f.name_out()) == (["z", "w"], ["xhat"])
    rng = np.random.default_rng(seed_of(nu, window, activation))
    z, w = rng.normal(size=5), rng.normal(size=(window, nu))

    def torch_dyn(z, w):
        factors = hyper(w[None])[len(encoder.layers):]
        return mlp_forward_lora(decoder, z[None], factors, hyper.scale)[0]

    modulation = torch_dyn(torch.tensor(z), torch.tensor(w)) - decoder(torch.tensor(z))
    assert modulation.abs().max() > 1e-3          # the comparison below exercises the LoRA term
    check_values_and_jacobians(f, torch_dyn, [z, w], (2,))
    check_sx_mx(f, [z, w])


@pytest.mark.parametrize("window", WINDOWS)
def test_dyn_encoder_matches_torch(window):
    encoder, decoder, hyper, arch, arrays = make_dyn(2, "tanh", 3, seed_of(window))
    f = casadi_nets.lora_mlp_function(*arch, arrays, 2, window, target="encoder")
    assert (f.name(), f.name_in(), f.name_out()) == ("encoder_dyn", ["x", "w"], ["z"])
    rng = np.random.default_rng(window)
    x, w = rng.normal(size=2), rng.normal(size=(window, 2))
    check_values_and_jacobians(
        f, lambda x, w: mlp_forward_lora(encoder, x[None], hyper(w[None])[:3], hyper.scale)[0],
        [x, w], (5,))


@pytest.mark.parametrize("activation", ACTIVATIONS)
def test_dyn_decoder_collapses_exactly_at_zero_window(activation):
    _, _, _, arch, arrays = make_dyn(2, activation, 4, seed_of(activation))
    dyn = casadi_nets.lora_mlp_function(*arch, arrays, 2, 30)
    plain = casadi_nets.mlp_function(arch[1], arrays, "decoder")
    rng = np.random.default_rng(1)
    for _ in range(5):
        z = rng.normal(size=5) * 3
        assert np.array_equal(np.array(dyn(z, np.zeros((30, 2)))), np.array(plain(z)))


def test_exported_window_functions_do_not_grow_with_the_window():
    obs = ObsInjection(5, 2, hidden=6, proj=3, gain_hidden=(8,))
    _, _, _, arch, arrays = make_dyn(2, "tanh", 2, 0)
    for build in (lambda n: casadi_nets.obs_injection_function(obs.spec, obs.to_arrays(), n),
                  lambda n: casadi_nets.lora_mlp_function(*arch, arrays, 2, n)):
        assert build(3).n_instructions() == build(100).n_instructions()


# ----------------------------------------------------------------------------- errors
# The builders take validated (spec, arrays); the arrays are checked once, by check_arrays (on load).

@pytest.fixture
def mlp_case():
    mlp = MLP((3, 4, 2))
    return mlp.to_arrays("net"), mlp.spec


def test_missing_array_names_it(mlp_case):
    arrays, spec = mlp_case
    del arrays["net/W1"]
    with pytest.raises(ValueError, match="net/W1"):
        check_arrays(arrays, spec.array_shapes("net"), "arrays")


def test_misshaped_array_names_it(mlp_case):
    arrays, spec = mlp_case
    arrays["net/b0"] = np.zeros(5)
    with pytest.raises(ValueError, match=r"net/b0.*shape \(4,\)"):
        check_arrays(arrays, spec.array_shapes("net"), "arrays")


def test_bad_arguments(mlp_case):
    arrays, spec = mlp_case
    with pytest.raises(TypeError, match="arrays"):
        check_arrays([1, 2], spec.array_shapes("net"), "arrays")
    with pytest.raises(ValueError, match="name"):
        casadi_nets.mlp_function(spec, arrays, "net", name="not a name")
    gru = GRUContext(1, 3).to_arrays("g")
    with pytest.raises(ValueError, match="window"):
        casadi_nets.gru_function(gru, "g", 1, 3, 0)
    with pytest.raises(TypeError, match="window"):
        casadi_nets.gru_function(gru, "g", 1, 3, 2.5)
    with pytest.raises(ValueError, match="g/W_ih"):
        check_arrays(gru, gru_array_shapes("g", 2, 3), "arrays")            # arrays are for nu = 1
    _, _, _, dyn_arch, dyn_arrays = make_dyn(1, "tanh", 2, 0)
    with pytest.raises(ValueError, match="target"):
        casadi_nets.lora_mlp_function(*dyn_arch, dyn_arrays, 1, 4, target="middle")
