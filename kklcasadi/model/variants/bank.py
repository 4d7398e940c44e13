"""``bank``: a linear filter bank of the measurement and the input, and a decoder fitted on the
observer's own noisy runs (the operational decoder).

``zdot = A z + By y + Bu u + c`` (``A`` block diagonal: first-order filters of ``y`` and ``u`` at a
spread of pole speeds, optional resonators of ``y``, an optional clock ``c`` that tells the decoder
how long the observer has run), ``z(0) = 0``; ``xhat = D([z; y_k; u_k])`` with an optional per-state
``asinh`` output scale. The latent is linear, so its exact discretisation is used; the decoder reads
the newest measurement and input, which the observer's memory ``w = [y_k; u_k]`` carries. Built by
:mod:`kklcasadi.model.variants.filterbank` and trained by :mod:`kklcasadi.train.operational` for the noise level
and input ranges its card records. There is no encoder: the latent is not a KKL map of the state
but a fixed filter of the signals, and the decoder learns the state from it.

Card: ``design`` holds ``A`` and ``By`` (as ``B``); ``architecture`` holds ``decoder``
(``[nz + ny + nu, ..., nx]``) and ``bank`` (the design parameters, for the record); the arrays
``bank/Bu`` (nz, nu), ``bank/c`` (nz,) and ``decoder/asinh_scale`` (nx,) complete it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Optional

import casadi as ca
import numpy as np

from ...nets.builders import mlp_function
from ...nets.specs import DECODER, MLPSpec, field_error
from ...plant.systems import System
from ...validation import is_number
from .base import Memory, Networks, Sizes, Variant
from .filterbank import FilterBank

__all__ = ["Bank", "BankSpec", "ASINH_SCALE", "feedthrough_memory"]

#: Array of the per-state output scales: ``xhat_i = s_i sinh(v_i)`` where ``s_i > 0``, else ``v_i``.
ASINH_SCALE = f"{DECODER}/asinh_scale"
_BANK_KEYS = ("y_poles", "u_poles", "y_resonators", "clock")


@dataclass(frozen=True, eq=False)
class BankSpec:
    """The decoder, the latent matrices and the bank's design parameters."""

    decoder: MLPSpec
    A: np.ndarray
    By: np.ndarray
    dt: float
    nu: int
    params: dict

    @property
    def nz(self) -> int:
        return self.A.shape[0]

    def to_card(self) -> dict:
        return {DECODER: self.decoder.to_card(), "bank": dict(self.params)}

    def array_shapes(self) -> dict[str, tuple[int, ...]]:
        return {**self.decoder.array_shapes(DECODER), ASINH_SCALE: (self.decoder.n_out,),
                "bank/Bu": (self.nz, self.nu), "bank/c": (self.nz,)}


def _positive_numbers(value: Any) -> bool:
    return isinstance(value, list) and all(is_number(v) and math.isfinite(v) and v > 0 for v in value)


def _params(entry: Any, where: str) -> dict:
    fix = ('Write "bank" as {"y_poles": [p, ...], "u_poles": [p, ...], "y_resonators": [[zeta, omega], ...], '
           '"clock": rate or null}.')
    if not isinstance(entry, Mapping) or set(entry) != set(_BANK_KEYS):
        raise field_error(where, "architecture.bank", f"an object with exactly the keys {list(_BANK_KEYS)}",
                          entry, fix)
    for name in ("y_poles", "u_poles"):
        if not _positive_numbers(entry[name]):
            raise field_error(where, f"architecture.bank.{name}", "a list of positive numbers", entry[name], fix)
    resonators = entry["y_resonators"]
    if not (isinstance(resonators, list) and all(_positive_numbers(r) and len(r) == 2 for r in resonators)):
        raise field_error(where, "architecture.bank.y_resonators", "a list of positive [zeta, omega] pairs",
                          resonators, fix)
    clock = entry["clock"]
    if clock is not None and not _positive_numbers([clock]):
        raise field_error(where, "architecture.bank.clock", "a rate > 0 or null", clock, fix)
    return {key: entry[key] for key in _BANK_KEYS}


def feedthrough_memory(ny: int, nu: int) -> Memory:
    """The memory ``w = [y_k; u_k]`` (ny + nu, 1): the newest measurement and the held input."""
    y, u, w = ca.MX.sym("y", ny), ca.MX.sym("u", nu), ca.MX.sym("w", ny + nu)
    init = ca.Function("memory_init", [y, u], [ca.vertcat(y, u)], ["y0", "u0"], ["w0"])
    step = ca.Function("memory_next", [w, y, u], [ca.vertcat(y, u)], ["w", "y_next", "u_next"], ["w_next"])
    return Memory((ny + nu, 1), init, step, lambda m: m[ny:])


class Bank(Variant):
    """A linear filter bank of ``y`` and ``u`` with an operational decoder (issue: accuracy under noise)."""

    name = "bank"
    summary = "ours: linear filter bank of y and u, decoder fitted on noisy closed-loop runs (for noise)"
    entries = (DECODER, "bank")
    linear = True
    needs_base = False
    certified = False
    trainer = "kklcasadi.train.bank:train_bank"
    config = "kklcasadi.train.bank:BankConfig"

    def parse(self, card: Mapping[str, Any], sizes: Sizes, where: str) -> BankSpec:
        decoder = MLPSpec.from_card(card["architecture"][DECODER], where, "architecture.decoder")
        n_in = sizes.nz + sizes.ny + sizes.nu
        if (decoder.n_in, decoder.n_out) != (n_in, sizes.nx):
            raise field_error(where, "architecture.decoder.sizes", f"[nz + ny + nu = {n_in}, ..., nx = {sizes.nx}]",
                              list(decoder.sizes), "The bank's decoder maps [z; y; u] to x.")
        A = np.array(card["design"]["A"], dtype=float)
        By = np.array(card["design"]["B"], dtype=float)
        if np.max(np.linalg.eigvals(A).real) >= 0:
            raise field_error(where, "design.A", "a Hurwitz matrix (the filter bank is stable)",
                              float(np.max(np.linalg.eigvals(A).real)), "Use the bank's A.")
        return BankSpec(decoder, A, By, float(card["dt"]), sizes.nu, _params(card["architecture"]["bank"], where))

    def networks(self, spec: BankSpec, arrays: Mapping[str, Any], system: System, window: int) -> Networks:
        bank = FilterBank(spec.A, spec.By, np.asarray(arrays["bank/Bu"]), np.asarray(arrays["bank/c"]))
        mlp = mlp_function(spec.decoder, arrays, DECODER, "decoder_mlp")
        memory = feedthrough_memory(system.ny, system.nu)
        z, w = ca.MX.sym("z", spec.nz), ca.MX.sym("w", *memory.shape)
        v = mlp(ca.vertcat(z, w))
        scale = np.asarray(arrays[ASINH_SCALE], dtype=float)
        xhat = ca.vertcat(*[float(s) * ca.sinh(v[i]) if s > 0 else v[i] for i, s in enumerate(scale)])
        decoder = ca.Function("decoder", [z, w], [xhat], ["z", "w"], ["xhat"])
        bu, c = ca.DM(bank.Bu), ca.DM(bank.c)

        def input_term(zz: ca.MX, u: ca.MX, context: Optional[ca.MX]) -> ca.MX:
            return ca.mtimes(bu, u) + c

        return Networks(None, decoder, None, input_term, memory=memory,
                        exact_step=bank.step_function(spec.dt, "latent_step"))
