"""The CasADi twin of the torch networks: model-file arrays -> CasADi Functions (no torch needed).

Every builder takes a typed spec (:mod:`kklcasadi.nets.specs`) and the arrays it names, as
validated by :func:`kklcasadi.model.files.load_model`; nothing is re-parsed or re-checked here.

* :func:`mlp_function` -- an MLP, ``x -> y``, layers as MX ``mtimes`` with DM constants, the
  input/output normalisation folded into the first and last layers (and into the linear skip path,
  :func:`folded_skip`, of a network that has one).
* :func:`gru_function` -- the bias-free GRU, ``w (window, nu) -> h (H, 1)``: one cell Function
  folded over the window (``Function.fold``), never unrolled.
* :func:`obs_gain_function`, :func:`obs_injection_function` -- HyperKKL_obs
  ``(z, w) -> G`` and ``(z, w, u) -> G u``; their parts :func:`obs_context_function`
  ``w -> l`` and :func:`obs_context_gain_function` ``(z, l) -> G``.
* :func:`lora_mlp_function` -- HyperKKL_dyn: the decoder (or encoder) modulated by the
  hypernetwork, ``(z, w) -> xhat``, each layer evaluated as ``W v + b + s a (b^T v)``.

All returned Functions have named inputs and outputs and accept SX or MX arguments. The torch
twins are in :mod:`kklcasadi.train.nets`; the tests check that both agree to 1e-10 in values and
Jacobians.
"""

from __future__ import annotations

import re
from typing import Any, Callable, Mapping, Optional

import casadi as ca
import numpy as np

from ..validation import error, positive_int
from .specs import (
    DECODER,
    ENCODER,
    HYPER,
    OBS_GAIN,
    OBS_GRU,
    OBS_PROJ,
    HyperSpec,
    MLPSpec,
    ObsSpec,
)

__all__ = ["mlp_function", "folded_skip", "gru_cell_function", "gru_function", "obs_context_function",
           "obs_context_gain_function", "obs_gain_function", "obs_injection_function", "lora_mlp_function",
           "lora_mlp_of_hidden", "check_name"]

Arrays = Mapping[str, Any]
_NAME = re.compile(r"^[A-Za-z](?:_?[A-Za-z0-9])*$")

_CASADI_ACTIVATIONS: dict[str, Callable[[ca.MX], ca.MX]] = {
    "tanh": ca.tanh,
    "relu": lambda x: ca.fmax(x, 0),
    # Overflow-free log(1 + exp(x)); the torch side uses the same formula.
    "softplus": lambda x: ca.fmax(x, 0) + ca.log1p(ca.exp(-ca.fabs(x))),
    "identity": lambda x: x,
}


def check_name(name: Any) -> str:
    """Return ``name`` if it is a valid CasADi Function name, else raise a ValueError."""
    if not isinstance(name, str) or not _NAME.match(name) or name in ("null", "jac", "hess"):
        raise error("name", "a CasADi function name (a letter, then letters, digits and single "
                    "underscores; not null, jac or hess)", name)
    return name


def _array(arrays: Arrays, name: str) -> np.ndarray:
    return np.asarray(arrays[name], dtype=np.float64)


def _folded_layers(arrays: Arrays, prefix: str, spec: MLPSpec) -> list[tuple[ca.DM, ca.DM]]:
    """Return the MLP's layers as DM ``(W, b)`` pairs with the normalisation folded in.

    ``(x - in_mean) / in_std`` goes into the first layer, ``v * out_std + out_mean`` into the last.
    """
    weights = [_array(arrays, f"{prefix}/W{i}") for i in range(len(spec.layer_shapes))]
    biases = [_array(arrays, f"{prefix}/b{i}") for i in range(len(spec.layer_shapes))]
    in_mean, in_std = _array(arrays, f"{prefix}/in_mean"), _array(arrays, f"{prefix}/in_std")
    out_mean, out_std = _array(arrays, f"{prefix}/out_mean"), _array(arrays, f"{prefix}/out_std")
    biases[0] = biases[0] - weights[0] @ (in_mean / in_std)
    weights[0] = weights[0] / in_std[None, :]
    weights[-1] = out_std[:, None] * weights[-1]
    biases[-1] = out_std * biases[-1] + out_mean
    return [(ca.DM(w), ca.DM(b)) for w, b in zip(weights, biases)]


def _mlp_expr(layers: list[tuple[ca.DM, ca.DM]], activation: str, x: ca.MX,
              delta: Optional[Callable[[int, ca.MX], ca.MX]] = None) -> ca.MX:
    """Apply folded layers to ``x``; ``delta(i, v)`` adds a term to layer ``i``'s pre-activation."""
    act = _CASADI_ACTIVATIONS[activation]
    v = x
    for i, (weight, bias) in enumerate(layers):
        y = ca.mtimes(weight, v) + bias
        if delta is not None:
            y = y + delta(i, v)
        v = y if i == len(layers) - 1 else act(y)
    return v


def mlp_function(spec: MLPSpec, arrays: Arrays, prefix: str,
                 name: Optional[str] = None) -> ca.Function:
    """Build an MLP.

    Parameters
    ----------
    spec : MLPSpec
        Its layer sizes and activation.
    arrays : Mapping[str, array_like]
        Holds ``spec.array_shapes(prefix)``: ``P/in_mean, P/in_std, P/out_mean, P/out_std,
        P/W{i}, P/b{i}`` (and ``P/Wskip`` with the skip path) for ``P = prefix``.
    prefix : str
        E.g. ``"decoder"``.
    name : str, optional
        Function name; defaults to ``prefix`` with ``/`` replaced by ``_``.

    Returns
    -------
    ca.Function
        ``y = f(x)``, ``x`` (d0, 1), ``y`` (dL, 1).
    """
    name = check_name(prefix.replace("/", "_") if name is None else name)
    x = ca.MX.sym("x", spec.n_in)
    y = _with_skip(_mlp_expr(_folded_layers(arrays, prefix, spec), spec.activation, x), arrays, prefix, spec, x)
    return ca.Function(name, [x], [y], ["x"], ["y"])


def folded_skip(arrays: Arrays, prefix: str) -> tuple[np.ndarray, np.ndarray]:
    """A network's skip path on its raw input, ``W x + b`` (the normalisation folded in).

    Returns
    -------
    W : numpy.ndarray, shape (dL, d0)
        ``diag(out_std) Wskip diag(1 / in_std)``.
    b : numpy.ndarray, shape (dL,)
        ``-W in_mean``.
    """
    in_mean, in_std = _array(arrays, f"{prefix}/in_mean"), _array(arrays, f"{prefix}/in_std")
    weight = _array(arrays, f"{prefix}/out_std")[:, None] * _array(arrays, f"{prefix}/Wskip") / in_std[None, :]
    return weight, -weight @ in_mean


def _with_skip(y: ca.MX, arrays: Arrays, prefix: str, spec: MLPSpec, x: ca.MX) -> ca.MX:
    """``y`` plus the skip path (:func:`folded_skip`) of a network that has one."""
    if not spec.skip:
        return y
    weight, bias = folded_skip(arrays, prefix)
    return y + ca.mtimes(ca.DM(weight), x) + ca.DM(bias)


def gru_cell_function(arrays: Arrays, prefix: str, nu: int, hidden: int, name: str) -> ca.Function:
    """One bias-free GRU step ``(h (H,1), x (nu,1)) -> h' (H,1)`` in torch's gate order (r, z, n).

    Exactly ``h' = 0`` for ``h = 0`` and ``x = 0``. A streaming context applies it once per sample.
    """
    w_ih, w_hh = ca.DM(_array(arrays, f"{prefix}/W_ih")), ca.DM(_array(arrays, f"{prefix}/W_hh"))
    h, x = ca.MX.sym("h", hidden), ca.MX.sym("x", nu)
    gi, gh = ca.mtimes(w_ih, x), ca.mtimes(w_hh, h)
    r = 1 / (1 + ca.exp(-(gi[:hidden] + gh[:hidden])))
    z = 1 / (1 + ca.exp(-(gi[hidden:2 * hidden] + gh[hidden:2 * hidden])))
    n = ca.tanh(gi[2 * hidden:] + r * gh[2 * hidden:])
    return ca.Function(name, [h, x], [(1 - z) * n + z * h], ["h", "x"], ["h_next"])


def gru_function(arrays: Arrays, prefix: str, nu: int, hidden: int, window: int,
                 name: Optional[str] = None) -> ca.Function:
    """Build the bias-free GRU context over a window.

    Parameters
    ----------
    arrays : Mapping[str, array_like]
        Holds ``P/W_ih`` (3H, nu) and ``P/W_hh`` (3H, H) (:func:`gru_array_shapes`).
    prefix : str
        E.g. ``"context/gru"``.
    nu, hidden : int
        Input and hidden sizes.
    window : int
        Window length in samples.
    name : str, optional
        Function name; defaults to ``prefix`` with ``/`` replaced by ``_``.

    Returns
    -------
    ca.Function
        ``h = f(w)``, ``w`` (window, nu) oldest sample first, ``h`` (H, 1) the final hidden
        state from ``h_0 = 0``. The cell is one Function folded ``window`` times.
    """
    nu, hidden = positive_int(nu, "nu"), positive_int(hidden, "hidden")
    window = positive_int(window, "window")
    name = check_name(prefix.replace("/", "_") if name is None else name)
    folded = gru_cell_function(arrays, prefix, nu, hidden, f"{name}_cell").fold(window)
    w = ca.MX.sym("w", window, nu)
    return ca.Function(name, [w], [folded(ca.DM.zeros(hidden, 1), w.T)], ["w"], ["h"])


def obs_context_function(spec: ObsSpec, arrays: Arrays, window: int,
                         name: str = "obs_context") -> ca.Function:
    """Build the HyperKKL_obs context ``l = P GRU(w)``.

    It depends on the window only, so an observer step evaluates it once and reuses it at every
    Runge-Kutta stage (see :func:`obs_context_gain_function`).

    Parameters
    ----------
    spec : ObsSpec
    arrays : Mapping[str, array_like]
        Holds ``context/gru/*`` and ``context/proj/W``.
    window : int
        Window length in samples.
    name : str

    Returns
    -------
    ca.Function
        ``l = f(w)``, ``w`` (window, nu), ``l`` (n_l, 1); exactly 0 for a zero window.
    """
    window = positive_int(window, "window")
    name = check_name(name)
    gru = gru_function(arrays, OBS_GRU, spec.nu, spec.hidden, window, f"{name}_gru")
    w = ca.MX.sym("w", window, spec.nu)
    return ca.Function(name, [w], [ca.mtimes(ca.DM(_array(arrays, OBS_PROJ)), gru(w))], ["w"],
                       ["l"])


def obs_context_gain_function(spec: ObsSpec, arrays: Arrays,
                              name: str = "obs_context_gain") -> ca.Function:
    """Build the HyperKKL_obs input gain as a function of the context, ``G(z, l)``.

    Parameters
    ----------
    spec : ObsSpec
    arrays : Mapping[str, array_like]
        Holds ``gain/*``.
    name : str

    Returns
    -------
    ca.Function
        ``G = f(z, l)``, ``z`` (nz, 1), ``l`` (n_l, 1), ``G`` (nz, nu) (the gain MLP's output
        reshaped row-major).
    """
    name = check_name(name)
    gain = mlp_function(spec.gain, arrays, OBS_GAIN, f"{name}_mlp")
    z, context = ca.MX.sym("z", spec.nz), ca.MX.sym("l", spec.proj)
    gain_matrix = ca.reshape(gain(ca.vertcat(z, context)), spec.nu, spec.nz).T
    return ca.Function(name, [z, context], [gain_matrix], ["z", "l"], ["G"])


def obs_gain_function(spec: ObsSpec, arrays: Arrays, window: int,
                      name: str = "obs_gain") -> ca.Function:
    """Build the HyperKKL_obs input gain ``G(z, P GRU(w))``.

    Parameters
    ----------
    spec : ObsSpec
    arrays : Mapping[str, array_like]
        Holds ``context/gru/*``, ``context/proj/W`` and ``gain/*``.
    window : int
        Window length in samples.
    name : str

    Returns
    -------
    ca.Function
        ``G = f(z, w)``, ``z`` (nz, 1), ``w`` (window, nu), ``G`` (nz, nu):
        :func:`obs_context_gain_function` of :func:`obs_context_function`.
    """
    name = check_name(name)
    context = obs_context_function(spec, arrays, window, f"{name}_context")
    gain = obs_context_gain_function(spec, arrays, f"{name}_of_l")
    z = ca.MX.sym("z", gain.size1_in(0))
    w = ca.MX.sym("w", *context.size_in(0))
    return ca.Function(name, [z, w], [gain(z, context(w))], ["z", "w"], ["G"])


def obs_injection_function(spec: ObsSpec, arrays: Arrays, window: int,
                           name: str = "obs_injection") -> ca.Function:
    """Build the HyperKKL_obs injection ``phi = G(z, w) u``, exactly zero at ``u = 0``.

    Parameters are those of :func:`obs_gain_function`.

    Returns
    -------
    ca.Function
        ``phi = f(z, w, u)``, ``z`` (nz, 1), ``w`` (window, nu), ``u`` (nu, 1), ``phi`` (nz, 1).
    """
    name = check_name(name)
    gain = obs_gain_function(spec, arrays, window, f"{name}_gain")
    z = ca.MX.sym("z", gain.size1_in(0))
    w = ca.MX.sym("w", *gain.size_in(1))
    u = ca.MX.sym("u", gain.size2_out(0))
    return ca.Function(name, [z, w, u], [ca.mtimes(gain(z, w), u)], ["z", "w", "u"], ["phi"])


def lora_mlp_function(encoder: MLPSpec, decoder: MLPSpec, hyper: HyperSpec, arrays: Arrays,
                      nu: int, window: int, target: str = DECODER,
                      name: Optional[str] = None) -> ca.Function:
    """Build the HyperKKL_dyn decoder (or encoder) modulated by the LoRA hypernetwork.

    Layer ``i`` (target ``j``) computes ``W_i v + b_i + s * a_j (b_j^T v)`` with
    ``f_j = backbone([GRU(w); e_j]) - backbone([0; e_j])``, ``a_j = reshape(Wa_j f_j)``,
    ``b_j = reshape(Wb_j f_j)``; both backbone evaluations use the same CasADi Function, so at
    ``w = 0`` the output equals the unmodulated network's exactly.

    Parameters
    ----------
    encoder, decoder : MLPSpec
        The two maps; the hypernetwork targets all encoder layers, then all decoder layers.
    hyper : HyperSpec
    arrays : Mapping[str, array_like]
        Holds the ``encoder/*``, ``decoder/*`` and ``hyper/*`` arrays.
    nu : int
        Input size.
    window : int
        Window length in samples.
    target : {"decoder", "encoder"}
        Which network to modulate.
    name : str, optional
        Function name; defaults to ``target + "_dyn"``.

    Returns
    -------
    ca.Function
        Decoder: ``xhat = f(z, w)``; encoder: ``z = f(x, w)``; ``w`` is (window, nu).
    """
    nu, window = positive_int(nu, "nu"), positive_int(window, "window")
    name = check_name(f"{target}_dyn" if name is None else name)
    modulated = lora_mlp_of_hidden(encoder, decoder, hyper, arrays, target, f"{name}_of_h")
    gru = gru_function(arrays, f"{HYPER}/gru", nu, hyper.hidden, window, f"{name}_gru")
    in_name, out_name = modulated.name_in(0), modulated.name_out(0)
    x, w = ca.MX.sym(in_name, modulated.size1_in(0)), ca.MX.sym("w", window, nu)
    return ca.Function(name, [x, w], [modulated(x, gru(w))], [in_name, "w"], [out_name])


def lora_mlp_of_hidden(encoder: MLPSpec, decoder: MLPSpec, hyper: HyperSpec, arrays: Arrays,
                       target: str = DECODER, name: Optional[str] = None) -> ca.Function:
    """The HyperKKL_dyn network modulated by a given GRU hidden state ``h`` (H, 1).

    :func:`lora_mlp_function` with the window's GRU replaced by its output ``h``: a streaming
    context passes the hidden state it carries from sample to sample. Exactly the unmodulated
    network at ``h = 0``.

    Returns
    -------
    ca.Function
        Decoder: ``xhat = f(z, h)``; encoder: ``z = f(x, h)``.
    """
    if target not in (ENCODER, DECODER):
        raise error("target", f"{ENCODER!r} or {DECODER!r}", target)
    name = check_name(f"{target}_dyn_of_h" if name is None else name)
    spec = decoder if target == DECODER else encoder

    n_layers = len(spec.layer_shapes)
    offset = 0 if target == ENCODER else len(encoder.layer_shapes)
    backbone = mlp_function(hyper.backbone_spec, arrays, f"{HYPER}/backbone",
                            f"{name}_backbone").map(n_layers)
    embed = ca.DM(_array(arrays, f"{HYPER}/embed")[offset:offset + n_layers].T)
    in_name, out_name = ("z", "xhat") if target == DECODER else ("x", "z")
    x, h = ca.MX.sym(in_name, spec.n_in), ca.MX.sym("h", hyper.hidden)
    features = (backbone(ca.vertcat(ca.repmat(h, 1, n_layers), embed))
                - backbone(ca.vertcat(ca.DM.zeros(hyper.hidden, n_layers), embed)))
    scale = float(_array(arrays, f"{HYPER}/scale"))
    in_mean, in_std = _array(arrays, f"{target}/in_mean"), _array(arrays, f"{target}/in_std")
    out_std = ca.DM(_array(arrays, f"{target}/out_std"))

    def delta(i: int, v: ca.MX) -> ca.MX:
        # The factors act on the normalised coordinates of the torch network: undo the folding
        # for the first layer's input and scale the last layer's output like its weights.
        if i == 0:
            v = (v - ca.DM(in_mean)) / ca.DM(in_std)
        d_out, d_in = spec.layer_shapes[i]
        j = offset + i
        a_t = ca.reshape(ca.mtimes(ca.DM(_array(arrays, f"{HYPER}/head{j}/Wa")), features[:, i]),
                         hyper.rank, d_out)
        b_t = ca.reshape(ca.mtimes(ca.DM(_array(arrays, f"{HYPER}/head{j}/Wb")), features[:, i]),
                         hyper.rank, d_in)
        term = scale * ca.mtimes(a_t.T, ca.mtimes(b_t, v))
        return term * out_std if i == n_layers - 1 else term

    y = _with_skip(_mlp_expr(_folded_layers(arrays, target, spec), spec.activation, x, delta), arrays, target,
                   spec, x)
    return ca.Function(name, [x, h], [y], [in_name, "h"], [out_name])
