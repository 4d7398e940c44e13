"""HyperKKL_dyn: ``zdot = A z + B y``, ``xhat = T*(z; eta + dEta(w))`` (LoRA hypernetwork).

The hypernetwork (GRU -> backbone -> per-layer heads) emits rank-r factors; the modulation is
exactly 0 for a zero window, so the observer is the autonomous one at ``u = 0``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Optional

from ...nets.builders import lora_mlp_function, mlp_function
from ...nets.specs import DECODER, ENCODER, HYPER, HyperSpec, lora_target_shapes
from ...plant.systems import System
from .base import MapsSpec, Networks, Sizes, Variant

__all__ = ["Dyn", "DynModelSpec"]


@dataclass(frozen=True)
class DynModelSpec(MapsSpec):
    """Encoder, decoder and the LoRA hypernetwork; ``nu`` is the GRU's input size."""

    hyper: Optional[HyperSpec] = None
    nu: int = 1

    def to_card(self) -> dict:
        return {**super().to_card(), **self.hyper.to_card()}

    def array_shapes(self) -> dict[str, tuple[int, ...]]:
        targets = lora_target_shapes(self.encoder, self.decoder)
        return {**super().array_shapes(), **self.hyper.array_shapes(HYPER, self.nu, targets)}


class Dyn(Variant):
    """HyperKKL_dyn (the paper's Algorithm 3): a linear latent and a window-modulated decoder."""

    name = "dyn"
    summary = "HyperKKL_dyn: zdot = A z + B y, xhat = T*(z; LoRA(GRU(w)))"
    entries = ("encoder", "decoder", "hyper")
    windowed = True
    modulated = True
    trains = True

    def parse(self, card: Mapping[str, Any], sizes: Sizes, where: str) -> DynModelSpec:
        maps = MapsSpec.parse_maps(card["architecture"], sizes, where)
        return DynModelSpec(maps.encoder, maps.decoder, HyperSpec.from_card(card["architecture"], where),
                            sizes.nu)

    def networks(self, spec: DynModelSpec, arrays: Mapping[str, Any], system: System,
                 window: int) -> Networks:
        encoder = mlp_function(spec.encoder, arrays, ENCODER, "encoder")
        decoder = lora_mlp_function(spec.encoder, spec.decoder, spec.hyper, arrays, system.nu, window,
                                    DECODER, "decoder")
        return Networks(encoder, decoder)
