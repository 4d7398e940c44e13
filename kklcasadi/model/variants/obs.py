"""HyperKKL_obs: ``zdot = A z + B y + G(z, P GRU(w)) u``; T and T* frozen from Phase 1.

With the card field ``"model_based_injection": true`` the learned term is a residual on top of the
``inject`` term. The GRU is bias-free and the gain multiplies ``u``, so the observer is exactly the
autonomous one at ``u = 0``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Optional

import casadi as ca

from ...nets.builders import obs_context_function, obs_context_gain_function
from ...nets.specs import ObsSpec, field_error
from ...plant.systems import System
from .base import MapsSpec, Networks, Sizes, Variant, plain_maps
from .inject import model_injection_function

__all__ = ["Obs", "ObsModelSpec", "MODEL_BASED_INJECTION"]

#: Top-level card field: add the model-based (``inject``) term under the learned injection.
MODEL_BASED_INJECTION = "model_based_injection"


@dataclass(frozen=True)
class ObsModelSpec(MapsSpec):
    """Encoder, decoder, the obs context and gain, and whether the model-based term is added."""

    obs: Optional[ObsSpec] = None
    model_based_injection: bool = False

    def to_card(self) -> dict:
        return {**super().to_card(), **self.obs.to_card()}

    def array_shapes(self) -> dict[str, tuple[int, ...]]:
        return {**super().array_shapes(), **self.obs.array_shapes()}


class Obs(Variant):
    """HyperKKL_obs (the paper's Algorithm 2) with a bias-free context."""

    name = "obs"
    summary = "HyperKKL_obs: zdot = A z + B y + G(z, P GRU(w)) u (learned input gain)"
    entries = ("encoder", "decoder", "context", "gain")
    linear = False
    windowed = True
    trains = True
    card_fields = (MODEL_BASED_INJECTION,)

    def parse(self, card: Mapping[str, Any], sizes: Sizes, where: str) -> ObsModelSpec:
        maps = MapsSpec.parse_maps(card["architecture"], sizes, where)
        obs = ObsSpec.from_card(card["architecture"], where)
        if (obs.nz, obs.gain.n_out) != (sizes.nz, sizes.nz * sizes.nu):
            raise field_error(where, "architecture.gain.sizes",
                              f"[nz + proj = {sizes.nz + obs.proj}, ..., nz*nu = {sizes.nz * sizes.nu}]",
                              list(obs.gain.sizes), "Size the gain MLP from the design and the system.")
        flag = card.get(MODEL_BASED_INJECTION, False)
        if not isinstance(flag, bool):
            raise field_error(where, MODEL_BASED_INJECTION, "true or false", flag,
                              "Set it to true to add the model-based term under the learned injection, "
                              "or remove it.")
        return ObsModelSpec(maps.encoder, maps.decoder, obs, flag)

    def card_entries(self, spec: ObsModelSpec) -> dict:
        return {MODEL_BASED_INJECTION: spec.model_based_injection}

    def networks(self, spec: ObsModelSpec, arrays: Mapping[str, Any], system: System,
                 window: int) -> Networks:
        encoder, decoder = plain_maps(spec, arrays, window, system.nu)
        context = obs_context_function(spec.obs, arrays, window)
        gain = obs_context_gain_function(spec.obs, arrays)
        injection = (model_injection_function(encoder, decoder, system)
                     if spec.model_based_injection else None)

        def input_term(z: ca.MX, u: ca.MX, context: Optional[ca.MX]) -> ca.MX:
            learned = ca.mtimes(gain(z, context), u)
            return learned if injection is None else injection(z, u) + learned

        return Networks(encoder, decoder, context, input_term, injection)
