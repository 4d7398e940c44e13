"""Torch networks of the HyperKKL observers.

The torch twin of :mod:`kklcasadi.nets.builders`; like the rest of :mod:`kklcasadi.train` it
imports torch, which the deploy side never does.

* :class:`MLP` -- encoder ``T``, decoder ``T*``, the obs gain MLP and the hypernetwork backbone.
* :class:`GRUContext` -- a bias-free GRU over the input window, final hidden state out.
* :class:`ObsInjection` -- HyperKKL_obs: ``phi(z, w, u) = G(z, P GRU(w)) u``.
* :class:`LoRAHyperNet` -- HyperKKL_dyn: per-sample rank-r factors for every encoder and decoder
  layer, applied by :func:`mlp_forward_lora`.

Every module converts to and from the named float64 arrays of the model file format
(``to_arrays`` / ``from_arrays``), built from the typed specs of :mod:`kklcasadi.nets.specs`
(which define the names and shapes, see ``docs/model-format.md``). Windows are
``(batch, window, nu)``, oldest sample first.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch
from torch import nn

from ..nets.specs import (
    HYPER,
    OBS_GAIN,
    OBS_GRU,
    OBS_PROJ,
    HyperSpec,
    MLPSpec,
    ObsSpec,
    array_name,
    check_activation,
    check_arrays,
    gru_array_shapes,
)

Tensor = torch.Tensor


def _softplus(x: Tensor) -> Tensor:
    # log(1 + exp(x)) without overflow and without torch's threshold switch, so that it equals
    # the CasADi export to rounding everywhere.
    return torch.clamp_min(x, 0.0) + torch.log1p(torch.exp(-torch.abs(x)))


_TORCH_ACTIVATIONS: dict[str, Callable[[Tensor], Tensor]] = {
    "tanh": torch.tanh,
    "relu": torch.relu,
    "softplus": _softplus,
    "identity": lambda x: x,
}


def _to_numpy(tensor: Tensor) -> np.ndarray:
    return tensor.detach().cpu().numpy().astype(np.float64)


def _load_into(param: Tensor, value: Any) -> None:
    with torch.no_grad():
        param.copy_(torch.as_tensor(np.array(value, dtype=np.float64)))


class MLP(nn.Module):
    """Fully connected network with input/output normalisation.

    ``v = (x - in_mean) / in_std``; ``v = act(W_i v + b_i)`` for every layer but the last, which
    is linear; ``out = v * out_std + out_mean``.

    Parameters
    ----------
    sizes : sequence of int
        Layer widths ``[d0, ..., dL]`` (at least two).
    activation : str
        Hidden activation, one of ``tanh``, ``relu``, ``softplus``, ``identity``.
    skip : bool
        Add a linear skip path ``Wskip v`` (no bias, zero at the start) to the last layer's output
        (:class:`kklcasadi.nets.specs.MLPSpec`).
    """

    def __init__(self, sizes: Sequence[int], activation: str = "tanh", *, skip: bool = False) -> None:
        super().__init__()
        self.spec = MLPSpec(tuple(sizes), activation, skip)
        self.act = _TORCH_ACTIVATIONS[check_activation(activation)]
        self.layers = nn.ModuleList(nn.Linear(d_in, d_out)
                                    for d_out, d_in in self.spec.layer_shapes)
        self.skip = nn.Parameter(torch.zeros(self.spec.n_out, self.spec.n_in)) if skip else None
        self.register_buffer("in_mean", torch.zeros(self.spec.n_in))
        self.register_buffer("in_std", torch.ones(self.spec.n_in))
        self.register_buffer("out_mean", torch.zeros(self.spec.n_out))
        self.register_buffer("out_std", torch.ones(self.spec.n_out))

    def set_normalisation(self, in_mean: Any, in_std: Any, out_mean: Any, out_std: Any) -> None:
        """Set the normalisation from data statistics.

        Parameters
        ----------
        in_mean, in_std : array_like, shape (d0,)
        out_mean, out_std : array_like, shape (dL,)
            Standard deviations must be positive and finite.
        """
        values = {"in_mean": in_mean, "in_std": in_std, "out_mean": out_mean, "out_std": out_std}
        shapes = {name: tuple(getattr(self, name).shape) for name in values}
        as_numpy = {name: _to_numpy(v) if isinstance(v, Tensor) else np.asarray(v, dtype=np.float64)
                    for name, v in values.items()}
        check_arrays({f"set_normalisation/{k}": v for k, v in as_numpy.items()},
                     {f"set_normalisation/{k}": s for k, s in shapes.items()}, "MLP")
        for name, value in as_numpy.items():
            _load_into(getattr(self, name), value)

    def forward(self, x: Tensor) -> Tensor:
        """Evaluate the network.

        Parameters
        ----------
        x : Tensor, shape (..., d0)

        Returns
        -------
        Tensor, shape (..., dL)
        """
        return _mlp_apply(self, x, None, None)

    def to_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """Float64 arrays ``P/in_mean, P/in_std, P/out_mean, P/out_std, P/W{i}, P/b{i}`` (and ``P/Wskip``)."""
        arrays = {f"{prefix}/{name}": _to_numpy(getattr(self, name))
                  for name in ("in_mean", "in_std", "out_mean", "out_std")}
        for i, layer in enumerate(self.layers):
            arrays[f"{prefix}/W{i}"] = _to_numpy(layer.weight)
            arrays[f"{prefix}/b{i}"] = _to_numpy(layer.bias)
        if self.skip is not None:
            arrays[f"{prefix}/Wskip"] = _to_numpy(self.skip)
        return arrays

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any], prefix: str, spec: MLPSpec,
                    *, dtype: torch.dtype = torch.float64) -> MLP:
        """Build an MLP from its arrays and its spec.

        Parameters
        ----------
        arrays : Mapping[str, array_like]
            Holds the arrays under ``prefix`` (see :meth:`to_arrays`).
        prefix : str
            E.g. ``"decoder"``.
        spec : MLPSpec
            Layer sizes and activation.
        dtype : torch.dtype
            Parameter dtype of the new module.
        """
        mlp = cls(spec.sizes, spec.activation, skip=spec.skip).to(dtype)
        mlp._load_arrays(arrays, prefix)
        return mlp

    def _load_arrays(self, arrays: Mapping[str, Any], prefix: str) -> None:
        check_arrays(arrays, self.spec.array_shapes(prefix), "arrays")
        for name in ("in_mean", "in_std", "out_mean", "out_std"):
            _load_into(getattr(self, name), arrays[f"{prefix}/{name}"])
        for i, layer in enumerate(self.layers):
            _load_into(layer.weight, arrays[f"{prefix}/W{i}"])
            _load_into(layer.bias, arrays[f"{prefix}/b{i}"])
        if self.skip is not None:
            _load_into(self.skip, arrays[f"{prefix}/Wskip"])


def _mlp_apply(mlp: MLP, x: Tensor, factors: Sequence[tuple[Tensor, Tensor]] | None,
               scale: Tensor | float | None) -> Tensor:
    v = x0 = (x - mlp.in_mean) / mlp.in_std
    last = len(mlp.layers) - 1
    for i, layer in enumerate(mlp.layers):
        y = nn.functional.linear(v, layer.weight, layer.bias)
        if factors is not None:
            a, b = factors[i]
            bv = torch.einsum("...ir,...i->...r", b, v)
            y = y + scale * torch.einsum("...or,...r->...o", a, bv)
        v = y if i == last else mlp.act(y)
    if mlp.skip is not None:
        v = v + nn.functional.linear(x0, mlp.skip)
    return v * mlp.out_std + mlp.out_mean


def mlp_forward_lora(mlp: MLP, x: Tensor, factors: Sequence[tuple[Tensor, Tensor]],
                     scale: Tensor | float) -> Tensor:
    """Evaluate ``mlp`` with per-sample low-rank weight changes ``dW_i = s a_i b_i^T``.

    Layer ``i`` computes ``W_i v + b_i + s * a_i (b_i^T v)``; ``dW_i`` is never formed. Works on
    any leading batch shape, and under ``torch.func.jvp`` / ``torch.func.vmap``.

    Parameters
    ----------
    mlp : MLP
        The base network (its weights and biases are used as they are).
    x : Tensor, shape (..., d0)
    factors : sequence of (a_i, b_i), one per layer of ``mlp``
        ``a_i`` of shape (..., d_{i+1}, r), ``b_i`` of shape (..., d_i, r), batched like ``x``.
    scale : Tensor or float
        The LoRA scale ``s``.

    Returns
    -------
    Tensor, shape (..., dL)

    Raises
    ------
    ValueError
        If the number of factor pairs or their trailing shapes do not fit ``mlp``.
    """
    if len(factors) != len(mlp.layers):
        raise ValueError(f"factors: expected {len(mlp.layers)} (a, b) pairs, one per layer of the "
                         f"MLP, received {len(factors)}.")
    for i, ((d_out, d_in), (a, b)) in enumerate(zip(mlp.spec.layer_shapes, factors)):
        if a.shape[-2] != d_out or b.shape[-2] != d_in or a.shape[-1] != b.shape[-1]:
            raise ValueError(f"factors[{i}]: expected a (..., {d_out}, r) and b (..., {d_in}, r), "
                             f"received {tuple(a.shape)} and {tuple(b.shape)}.")
    return _mlp_apply(mlp, x, factors, scale)


class GRUContext(nn.Module):
    """Bias-free single-layer GRU over an input window; returns the final hidden state.

    ``h_0 = 0``; torch gate order (r, z, n): ``r = sigmoid(W_ir x + W_hr h)``,
    ``z = sigmoid(W_iz x + W_hz h)``, ``n = tanh(W_in x + r * (W_hn h))``,
    ``h' = (1 - z) * n + z * h``. A zero window gives exactly ``h = 0``.

    The weights live in a bias-free ``nn.GRU(nu, hidden, bias=False, batch_first=True)``
    (``gru.weight_ih_l0``, ``gru.weight_hh_l0``, torch's initialisation), but the forward pass
    is written out with elementary ops: torch's fused GRU kernels (cuDNN, ``_thnn_fused_gru_cell``)
    have no forward-mode derivative on CUDA and no ``vmap`` batching rule, and HyperKKL_dyn
    training takes JVPs along the window.

    Parameters
    ----------
    nu : int
        Input size.
    hidden : int
        Hidden size H.
    """

    def __init__(self, nu: int, hidden: int) -> None:
        super().__init__()
        self.nu, self.hidden = nu, hidden
        self.gru = nn.GRU(nu, hidden, bias=False, batch_first=True)

    def forward(self, w: Tensor) -> Tensor:
        """Run over the window.

        Parameters
        ----------
        w : Tensor, shape (..., window, nu)
            Oldest sample first; any leading batch shape (also none, and under ``vmap``).

        Returns
        -------
        Tensor, shape (..., H)
            The final hidden state.
        """
        return self._run(w, keep=False)

    def sequence(self, u: Tensor) -> Tensor:
        """The hidden state after every sample: the streaming context of a whole input sequence.

        Parameters
        ----------
        u : Tensor, shape (..., N, nu)
            Oldest sample first; ``h_0 = 0`` before the first sample.

        Returns
        -------
        Tensor, shape (..., N, H)
            ``out[..., k, :]`` is the GRU's state after ``u_0, ..., u_k`` (one cell per sample,
            as the streaming observer applies it).
        """
        return self._run(u, keep=True)

    def _run(self, w: Tensor, keep: bool) -> Tensor:
        if w.dim() < 2 or w.shape[-1] != self.nu:
            raise ValueError(f"w: expected shape (..., window, {self.nu}), "
                             f"received {tuple(w.shape)}.")
        n_hidden = self.hidden
        gates_in = nn.functional.linear(w, self.gru.weight_ih_l0)
        h = torch.zeros_like(gates_in[..., 0, :n_hidden])
        states = []
        # unbind, not gates_in[..., k, :]: the backward of one unbind is one stack, whereas each
        # slice's backward fills a zero tensor of the whole window (most of a dyn step's time)
        for gi in gates_in.unbind(-2):
            gh = nn.functional.linear(h, self.gru.weight_hh_l0)
            r = torch.sigmoid(gi[..., :n_hidden] + gh[..., :n_hidden])
            z = torch.sigmoid(gi[..., n_hidden:2 * n_hidden] + gh[..., n_hidden:2 * n_hidden])
            n = torch.tanh(gi[..., 2 * n_hidden:] + r * gh[..., 2 * n_hidden:])
            h = (1 - z) * n + z * h
            if keep:
                states.append(h)
        return torch.stack(states, dim=-2) if keep else h

    def to_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """Float64 arrays ``P/W_ih`` (3H, nu) and ``P/W_hh`` (3H, H)."""
        return {f"{prefix}/W_ih": _to_numpy(self.gru.weight_ih_l0),
                f"{prefix}/W_hh": _to_numpy(self.gru.weight_hh_l0)}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any], prefix: str, nu: int, hidden: int,
                    *, dtype: torch.dtype = torch.float64) -> GRUContext:
        """Build from the arrays under ``prefix`` for input size ``nu`` and width ``hidden``."""
        context = cls(nu, hidden).to(dtype)
        context._load_arrays(arrays, prefix)
        return context

    def _load_arrays(self, arrays: Mapping[str, Any], prefix: str) -> None:
        check_arrays(arrays, gru_array_shapes(prefix, self.nu, self.hidden), "arrays")
        _load_into(self.gru.weight_ih_l0, arrays[f"{prefix}/W_ih"])
        _load_into(self.gru.weight_hh_l0, arrays[f"{prefix}/W_hh"])


class ObsInjection(nn.Module):
    """HyperKKL_obs input injection ``phi(z, w, u) = G(z, l) u`` with ``l = P GRU(w)``.

    ``G`` is the gain MLP's output on ``[z; l]`` reshaped row-major to (nz, nu), so the injection
    is exactly zero at ``u = 0``.

    Parameters
    ----------
    nz, nu : int
        Latent and input sizes.
    hidden : int
        GRU width H.
    proj : int
        Context size n_l of the bias-free projection ``P`` (n_l, H).
    gain_hidden : sequence of int
        Hidden widths of the gain MLP, sizes ``[nz + n_l, *gain_hidden, nz*nu]``.
    activation : str
        Hidden activation of the gain MLP.
    """

    def __init__(self, nz: int, nu: int, hidden: int = 64, proj: int = 16,
                 gain_hidden: Sequence[int] = (64, 64), activation: str = "tanh") -> None:
        super().__init__()
        self.spec = ObsSpec(hidden, proj, MLPSpec((nz + proj, *gain_hidden, nz * nu), activation))
        self.nz, self.nu = nz, nu
        self.context = GRUContext(nu, hidden)
        self.proj = nn.Linear(hidden, proj, bias=False)
        self.gain_net = MLP(self.spec.gain.sizes, activation)

    def gain(self, z: Tensor, w: Tensor) -> Tensor:
        """The input gain ``G(z, l)``.

        Parameters
        ----------
        z : Tensor, shape (batch, nz)
        w : Tensor, shape (batch, window, nu)

        Returns
        -------
        Tensor, shape (batch, nz, nu)
        """
        if z.dim() != 2 or z.shape[-1] != self.nz:
            raise ValueError(f"z: expected shape (batch, {self.nz}), received {tuple(z.shape)}.")
        if w.dim() != 3:
            raise ValueError(f"w: expected shape (batch, window, {self.nu}), "
                             f"received {tuple(w.shape)}.")
        return self.gain_of_hidden(z, self.context(w))

    def gain_of_hidden(self, z: Tensor, h: Tensor) -> Tensor:
        """The input gain ``G(z, P h)`` for a given GRU state ``h`` (..., H) (a streaming context).

        Returns
        -------
        Tensor, shape (..., nz, nu)
        """
        out = self.gain_net(torch.cat([z, self.proj(h)], dim=-1))
        return out.view(*out.shape[:-1], self.nz, self.nu)

    def forward(self, z: Tensor, w: Tensor, u: Tensor) -> Tensor:
        """The injection ``G(z, l) u``.

        Parameters
        ----------
        z : Tensor, shape (batch, nz)
        w : Tensor, shape (batch, window, nu)
        u : Tensor, shape (batch, nu)

        Returns
        -------
        Tensor, shape (batch, nz)
        """
        if u.dim() != 2 or u.shape[-1] != self.nu:
            raise ValueError(f"u: expected shape (batch, {self.nu}), received {tuple(u.shape)}.")
        return torch.einsum("bij,bj->bi", self.gain(z, w), u)

    def to_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """Float64 arrays ``context/gru/*``, ``context/proj/W``, ``gain/*`` under ``prefix``."""
        arrays = self.context.to_arrays(array_name(prefix, OBS_GRU))
        arrays[array_name(prefix, OBS_PROJ)] = _to_numpy(self.proj.weight)
        arrays.update(self.gain_net.to_arrays(array_name(prefix, OBS_GAIN)))
        return arrays

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any], prefix: str, spec: ObsSpec,
                    *, dtype: torch.dtype = torch.float64) -> ObsInjection:
        """Build from the arrays under ``prefix`` (empty in model files) and the spec."""
        check_arrays(arrays, spec.array_shapes(prefix), "arrays")
        obs = cls(spec.nz, spec.nu, spec.hidden, spec.proj, spec.gain.sizes[1:-1],
                  spec.gain.activation).to(dtype)
        obs.context._load_arrays(arrays, array_name(prefix, OBS_GRU))
        _load_into(obs.proj.weight, arrays[array_name(prefix, OBS_PROJ)])
        obs.gain_net._load_arrays(arrays, array_name(prefix, OBS_GAIN))
        return obs


class LoRAHyperNet(nn.Module):
    """HyperKKL_dyn hypernetwork: input window -> rank-r factors for every target layer.

    Per sample ``h = GRU(w)``; for target ``j``:
    ``f_j = backbone([h; e_j]) - backbone([0; e_j])`` (exactly zero for a zero window),
    ``a_j = reshape(Wa_j f_j, (d_out_j, r))``, ``b_j = reshape(Wb_j f_j, (d_in_j, r))``
    (row-major); the modulated layer is ``W_j v + bias_j + s * a_j (b_j^T v)``.

    Parameters
    ----------
    target_shapes : sequence of (d_out, d_in)
        The modulated layers; in model files all encoder layers then all decoder layers
        (:func:`kklcasadi.nets.specs.lora_target_shapes`).
    nu : int
        Input size.
    hidden : int
        GRU width H.
    embed : int
        Layer-embedding size E.
    backbone : sequence of int
        Backbone widths; the backbone MLP is ``[H + E, *backbone]``, tanh, and its last layer
        (width F) is linear.
    rank : int
        LoRA rank r.
    scale_init : float
        Initial value of the learnable scale ``s``.
    """

    def __init__(self, target_shapes: Sequence[tuple[int, int]], nu: int, hidden: int = 64,
                 embed: int = 16, backbone: Sequence[int] = (64, 64), rank: int = 4,
                 scale_init: float = 0.01) -> None:
        super().__init__()
        self.spec = HyperSpec(hidden, embed, tuple(backbone), rank)
        self.target_shapes = tuple((int(d_out), int(d_in)) for d_out, d_in in target_shapes)
        if not self.target_shapes:
            raise ValueError("target_shapes: expected at least one (d_out, d_in) pair, received none.")
        self.nu = nu
        self.gru = GRUContext(nu, hidden)
        self.embed = nn.Parameter(torch.randn(len(self.target_shapes), embed))
        self.backbone = MLP(self.spec.backbone_spec.sizes, self.spec.backbone_spec.activation)
        n_features = self.spec.backbone[-1]
        self.heads_a = nn.ModuleList(nn.Linear(n_features, d_out * rank, bias=False)
                                     for d_out, _ in self.target_shapes)
        self.heads_b = nn.ModuleList(nn.Linear(n_features, d_in * rank, bias=False)
                                     for _, d_in in self.target_shapes)
        self.scale = nn.Parameter(torch.tensor(float(scale_init)))

    def forward(self, w: Tensor) -> list[tuple[Tensor, Tensor]]:
        """Per-sample factors for every target.

        Parameters
        ----------
        w : Tensor, shape (batch, window, nu)

        Returns
        -------
        list of (a_j, b_j)
            ``a_j`` of shape (batch, d_out_j, r), ``b_j`` of shape (batch, d_in_j, r).
        """
        if w.dim() != 3:
            raise ValueError(f"w: expected shape (batch, window, {self.nu}), "
                             f"received {tuple(w.shape)}.")
        return self.factors_of_hidden(self.gru(w))

    def factors_of_hidden(self, h: Tensor) -> list[tuple[Tensor, Tensor]]:
        """Per-sample factors for a given GRU state ``h`` (batch, H) (a streaming context)."""
        n_batch, n_targets = h.shape[0], len(self.target_shapes)
        embed = self.embed.expand(n_batch, n_targets, -1)
        h = h.unsqueeze(1).expand(-1, n_targets, -1)
        # Same shapes in both calls: for h == 0 the two inputs are bitwise equal, so f == 0.
        features = (self.backbone(torch.cat([h, embed], dim=-1))
                    - self.backbone(torch.cat([torch.zeros_like(h), embed], dim=-1)))
        rank = self.spec.rank
        return [(head_a(features[:, j]).view(n_batch, d_out, rank),
                 head_b(features[:, j]).view(n_batch, d_in, rank))
                for j, ((d_out, d_in), head_a, head_b)
                in enumerate(zip(self.target_shapes, self.heads_a, self.heads_b))]

    def to_arrays(self, prefix: str = HYPER) -> dict[str, np.ndarray]:
        """Float64 arrays under ``prefix``.

        Names: ``gru/*``, ``embed``, ``backbone/*``, ``head{j}/Wa``, ``head{j}/Wb``, ``scale``.
        """
        arrays = self.gru.to_arrays(f"{prefix}/gru")
        arrays[f"{prefix}/embed"] = _to_numpy(self.embed)
        arrays.update(self.backbone.to_arrays(f"{prefix}/backbone"))
        for j, (head_a, head_b) in enumerate(zip(self.heads_a, self.heads_b)):
            arrays[f"{prefix}/head{j}/Wa"] = _to_numpy(head_a.weight)
            arrays[f"{prefix}/head{j}/Wb"] = _to_numpy(head_b.weight)
        arrays[f"{prefix}/scale"] = _to_numpy(self.scale)
        return arrays

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any], prefix: str, spec: HyperSpec,
                    targets: Sequence[tuple[int, int]], *, nu: int,
                    dtype: torch.dtype = torch.float64) -> LoRAHyperNet:
        """Build from arrays.

        Parameters
        ----------
        arrays : Mapping[str, array_like]
        prefix : str
            ``"hyper"`` in model files.
        spec : HyperSpec
        targets : sequence of (d_out, d_in)
            The modulated layers (:func:`kklcasadi.nets.specs.lora_target_shapes`).
        nu : int
            Input size.
        dtype : torch.dtype
        """
        check_arrays(arrays, spec.array_shapes(prefix, nu, targets), "arrays")
        hyper = cls(targets, nu, spec.hidden, spec.embed, spec.backbone, spec.rank).to(dtype)
        hyper.gru._load_arrays(arrays, f"{prefix}/gru")
        hyper.backbone._load_arrays(arrays, f"{prefix}/backbone")
        _load_into(hyper.embed, arrays[f"{prefix}/embed"])
        for j, (head_a, head_b) in enumerate(zip(hyper.heads_a, hyper.heads_b)):
            _load_into(head_a.weight, arrays[f"{prefix}/head{j}/Wa"])
            _load_into(head_b.weight, arrays[f"{prefix}/head{j}/Wb"])
        _load_into(hyper.scale, arrays[f"{prefix}/scale"])
        return hyper
