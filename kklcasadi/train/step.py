"""The observer step in torch, in its fastest honest form: the benchmark's torch baseline.

:func:`torch_step` builds ``step(z, w, y, y_next, u_next) -> (z_next, w_next, xhat_next)`` for a
:class:`kklcasadi.KKLObserver`, the same computation as ``observer.step``: the exact or RK4 latent
update and the decoder, batch 1, float64, without autograd. :data:`PARTS` gives each variant's torch parts
by method (the variant table names nothing on the training side); a window GRU is a plain
``torch.nn.GRU`` holding the model's bias-free weights (not the Python loop training uses for its
JVPs). Variants whose step needs the CasADi plant (the model-based term of ``inject``) have none.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np
import torch

from ..nets.specs import DECODER, HYPER, lora_target_shapes
from ..plant.rk4 import rk4_step
from .nets import MLP, LoRAHyperNet, ObsInjection, mlp_forward_lora

__all__ = ["TorchParts", "torch_step", "maps_parts", "obs_parts", "dyn_parts", "PARTS"]

Tensor = torch.Tensor


@dataclass(frozen=True)
class TorchParts:
    """What a variant contributes to the torch step (``w`` is the observer's input memory).

    Attributes
    ----------
    decode : callable
        ``decode(z (nz,), w) -> xhat (nx,)``.
    context : callable or None
        ``context(w)``, once per step, passed to ``input_term``.
    input_term : callable or None
        ``input_term(z (nz,), u (nu,), context) -> dz (nz,)``; None for a linear latent.
    memory_next : callable or None
        ``memory_next(w, y_next, u_next) -> w_next``; None for the input window (shifted by one).
    held : callable or None
        ``held(w) -> u_k``; None for the window's newest entry.
    """

    decode: Callable[[Tensor, Tensor], Tensor]
    context: Optional[Callable[[Tensor], Any]] = None
    input_term: Optional[Callable[[Tensor, Tensor, Any], Tensor]] = None
    memory_next: Optional[Callable[[Tensor, Tensor, Tensor], Tensor]] = None
    held: Optional[Callable[[Tensor], Tensor]] = None


def _arrays(observer: Any) -> dict[str, np.ndarray]:
    # writable copies: the loaded arrays are read-only, which torch.as_tensor warns about
    return {name: np.array(value) for name, value in observer.model.arrays.items()}


def _decoder(observer: Any, arrays: dict) -> MLP:
    return MLP.from_arrays(arrays, DECODER, observer.model.spec.architecture.decoder).requires_grad_(False)


def _torch_gru(context: Any) -> torch.nn.GRU:
    """The bias-free ``nn.GRU`` inside a :class:`kklcasadi.train.nets.GRUContext` (torch's fused kernel)."""
    return context.gru


def _cell(gru: torch.nn.GRU) -> Callable[[Tensor, Tensor], Tensor]:
    """One step of a bias-free GRU on (H,) and (nu,) tensors."""
    cell = torch.nn.GRUCell(gru.input_size, gru.hidden_size, bias=False, dtype=gru.weight_ih_l0.dtype)
    with torch.no_grad():
        cell.weight_ih.copy_(gru.weight_ih_l0)
        cell.weight_hh.copy_(gru.weight_hh_l0)
    cell.requires_grad_(False)
    return lambda h, u: cell(u[None], h[None])[0]


def _stream(gru: torch.nn.GRU, nu: int) -> tuple[Callable, Callable]:
    """``memory_next`` and ``held`` of a streaming memory ``w = [h; u_k]`` (H + nu, 1)."""
    cell, hidden = _cell(gru), gru.hidden_size

    def memory_next(w: Tensor, y_next: Tensor, u_next: Tensor) -> Tensor:
        return torch.cat([cell(w[:hidden, 0], u_next), u_next])[:, None]

    return memory_next, lambda w: w[hidden:, 0]


def maps_parts(observer: Any) -> TorchParts:
    """``autonomous`` and ``curriculum``: the decoder only."""
    decoder = _decoder(observer, _arrays(observer))
    return TorchParts(lambda z, w: decoder(z))


def _obs_injection(observer: Any) -> tuple[ObsInjection, Callable]:
    arrays = _arrays(observer)
    injection = ObsInjection.from_arrays(arrays, "", observer.model.spec.architecture.obs).requires_grad_(False)
    nz, nu = observer.nz, observer.nu

    def input_term(z: Tensor, u: Tensor, context: Tensor) -> Tensor:
        return injection.gain_net(torch.cat([z, context])).view(nz, nu) @ u

    return injection, input_term


def obs_parts(observer: Any) -> Optional[TorchParts]:
    """HyperKKL_obs: the window's context through ``nn.GRU``, the gain times ``u``."""
    if observer.model_based_injection:
        return None
    injection, input_term = _obs_injection(observer)
    decoder = _decoder(observer, _arrays(observer))
    gru = _torch_gru(injection.context)
    return TorchParts(lambda z, w: decoder(z), lambda w: injection.proj(gru(w[None])[1][0, 0]), input_term)


def obs_stream_parts(observer: Any) -> Optional[TorchParts]:
    """HyperKKL_obs with a streaming context: one GRU cell per step."""
    if observer.model_based_injection:
        return None
    injection, input_term = _obs_injection(observer)
    decoder = _decoder(observer, _arrays(observer))
    hidden = injection.spec.hidden
    memory_next, held = _stream(_torch_gru(injection.context), observer.nu)
    return TorchParts(lambda z, w: decoder(z), lambda w: injection.proj(w[:hidden, 0]), input_term, memory_next,
                      held)


def _lora_decode(observer: Any, hidden_of: Callable[[LoRAHyperNet, Tensor], Tensor]) -> tuple[Callable, LoRAHyperNet]:
    """The LoRA-modulated decoder with the context ``hidden_of(hyper, w)`` (1, H), and the hypernetwork."""
    arrays = _arrays(observer)
    arch = observer.model.spec.architecture
    decoder = _decoder(observer, arrays)
    hyper = LoRAHyperNet.from_arrays(arrays, HYPER, arch.hyper, lora_target_shapes(arch.encoder, arch.decoder),
                                     nu=observer.nu).requires_grad_(False)
    n_encoder = len(arch.encoder.layer_shapes)
    targets = hyper.target_shapes[n_encoder:]
    heads = list(zip(hyper.heads_a, hyper.heads_b))[n_encoder:]
    embed, rank = hyper.embed[n_encoder:], hyper.spec.rank

    def decode(z: Tensor, w: Tensor) -> Tensor:
        # LoRAHyperNet.factors_of_hidden for the decoder's layers only
        h = hidden_of(hyper, w).expand(len(targets), -1)
        features = (hyper.backbone(torch.cat([h, embed], dim=-1))
                    - hyper.backbone(torch.cat([torch.zeros_like(h), embed], dim=-1)))
        factors = [(head_a(features[j]).view(1, d_out, rank), head_b(features[j]).view(1, d_in, rank))
                   for j, ((d_out, d_in), (head_a, head_b)) in enumerate(zip(targets, heads))]
        return mlp_forward_lora(decoder, z[None], factors, hyper.scale)[0]

    return decode, hyper


def dyn_parts(observer: Any) -> TorchParts:
    """HyperKKL_dyn: the window's context through ``nn.GRU``, the LoRA-modulated decoder."""
    decode, _ = _lora_decode(observer, lambda hyper, w: _torch_gru(hyper.gru)(w[None])[1][0])
    return TorchParts(decode)


def dyn_stream_parts(observer: Any) -> TorchParts:
    """HyperKKL_dyn with a streaming context: one GRU cell per step."""
    hidden = observer.model.spec.architecture.hyper.hidden
    decode, hyper = _lora_decode(observer, lambda hyper, w: w[:hidden, 0][None])
    memory_next, held = _stream(_torch_gru(hyper.gru), observer.nu)
    return TorchParts(decode, memory_next=memory_next, held=held)


#: The function giving each variant's torch parts, by method (None where a variant has none: ``inject``, ``bank``).
PARTS: dict[str, Callable[[Any], Optional[TorchParts]]] = {
    "autonomous": maps_parts, "curriculum": maps_parts, "obs": obs_parts, "dyn": dyn_parts,
    "obs_stream": obs_stream_parts, "dyn_stream": dyn_stream_parts}


def torch_step(observer: Any) -> Optional[Callable[..., tuple[Tensor, Tensor, Tensor]]]:
    """The observer step in torch, or None where the variant has no torch form (``inject``).

    Returns
    -------
    callable or None
        ``step(z (nz,), w, y (ny,), y_next (ny,), u_next (nu,)) -> (z_next, w_next, xhat_next)``
        on float64 tensors, ``w`` shaped like ``observer.memory_shape``.
    """
    hook = PARTS.get(observer.variant.name)
    parts = None if hook is None else hook(observer)
    if parts is None:
        return None
    held = parts.held or (lambda w: w[-1])
    memory_next = parts.memory_next or (lambda w, y_next, u_next: torch.cat([w[1:], u_next[None]]))
    if observer.foh_matrices is not None:
        m = observer.foh_matrices
        ad, gy, gy_next = (torch.as_tensor(np.array(a)) for a in (m.Ad, m.Gy, m.Gy_next))

        def advance(z: Tensor, w: Tensor, y: Tensor, y_next: Tensor) -> Tensor:
            return ad @ z + gy @ y + gy_next @ y_next
    else:
        a, b = torch.as_tensor(np.array(observer.A)), torch.as_tensor(np.array(observer.B))

        def advance(z: Tensor, w: Tensor, y: Tensor, y_next: Tensor) -> Tensor:
            u = held(w)
            context = None if parts.context is None else parts.context(w)        # once per step

            def field(s: float, zz: Tensor) -> Tensor:
                zdot = a @ zz + b @ (y + s * (y_next - y))
                return zdot if parts.input_term is None else zdot + parts.input_term(zz, u, context)

            return rk4_step(field, z, observer.dt, observer.substeps)

    def step(z: Tensor, w: Tensor, y: Tensor, y_next: Tensor, u_next: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        z_next = advance(z, w, y, y_next)
        w_next = memory_next(w, y_next, u_next)
        return z_next, w_next, parts.decode(z_next, w_next)

    return step
