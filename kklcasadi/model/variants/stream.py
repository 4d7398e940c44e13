"""Streaming contexts: HyperKKL_obs and HyperKKL_dyn with a context updated once per sample.

The window GRU of ``obs``/``dyn`` re-reads the last ``window`` inputs at every step (``window``
GRU cells per step). The streaming variants carry the GRU's hidden state ``h`` instead and apply
one cell per sample, ``h_k+1 = cell(h_k, u_k+1)`` from ``h = 0`` before ``t = 0``, so the observer
is a finite-dimensional system with O(1) cost per step. The observer's memory is
``w = [h; u_k]`` (H + nu, 1): the context and the input held over the current interval. Same
arrays and card entries as ``obs``/``dyn``; the card's window is 1.

Both collapse exactly to the autonomous observer at ``u = 0``: the GRU is bias-free, so ``h``
stays exactly 0, and the learned terms vanish for ``u = 0`` / ``h = 0``.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

import casadi as ca

from ...nets.builders import gru_cell_function, lora_mlp_of_hidden, mlp_function, obs_context_gain_function
from ...nets.specs import DECODER, ENCODER, HYPER, OBS_GRU, OBS_PROJ
from ...plant.systems import System
from .base import Memory, Networks, ignoring_memory
from .dyn import Dyn, DynModelSpec
from .inject import model_injection_function
from .obs import Obs, ObsModelSpec

__all__ = ["ObsStream", "DynStream", "stream_memory"]


def stream_memory(cell: ca.Function, ny: int) -> Memory:
    """The memory ``w = [h; u_k]`` of a GRU ``cell (h, u) -> h'`` applied once per sample.

    ``init(y0, u0) = [cell(0, u0); u0]``, ``next(w, y', u') = [cell(h, u'); u']``, ``held(w) = u_k``.
    """
    hidden, nu = cell.size1_in(0), cell.size1_in(1)
    y, u, w = ca.MX.sym("y", ny), ca.MX.sym("u", nu), ca.MX.sym("w", hidden + nu)
    init = ca.Function("memory_init", [y, u], [ca.vertcat(cell(ca.DM.zeros(hidden), u), u)], ["y0", "u0"],
                       ["w0"])
    step = ca.Function("memory_next", [w, y, u], [ca.vertcat(cell(w[:hidden], u), u)], ["w", "y_next", "u_next"],
                       ["w_next"])
    return Memory((hidden + nu, 1), init, step, lambda m: m[hidden:])


class ObsStream(Obs):
    """HyperKKL_obs with a streaming context: ``zdot = A z + B y + G(z, P h_k) u``."""

    name = "obs_stream"
    summary = "HyperKKL_obs with a streaming GRU context (one cell per sample, O(1) per step)"
    windowed = False
    certified = False
    trains = True

    def networks(self, spec: ObsModelSpec, arrays: Mapping[str, Any], system: System,
                 window: int) -> Networks:
        obs = spec.obs
        memory = stream_memory(gru_cell_function(arrays, OBS_GRU, system.nu, obs.hidden, "obs_context_cell"), system.ny)
        encoder = mlp_function(spec.encoder, arrays, ENCODER, "encoder")
        decoder = ignoring_memory(mlp_function(spec.decoder, arrays, DECODER, "decoder"), memory.shape)
        w = ca.MX.sym("w", *memory.shape)
        projection = ca.DM(arrays[OBS_PROJ])
        context = ca.Function("obs_context", [w], [ca.mtimes(projection, w[:obs.hidden])], ["w"], ["l"])
        gain = obs_context_gain_function(obs, arrays)
        injection = model_injection_function(encoder, decoder, system) if spec.model_based_injection else None

        def input_term(z: ca.MX, u: ca.MX, l_context: Optional[ca.MX]) -> ca.MX:
            learned = ca.mtimes(gain(z, l_context), u)
            return learned if injection is None else injection(z, u) + learned

        return Networks(encoder, decoder, context, input_term, injection, memory)


class DynStream(Dyn):
    """HyperKKL_dyn with a streaming context: ``xhat = T*(z; LoRA(h_k))``."""

    name = "dyn_stream"
    summary = "HyperKKL_dyn with a streaming GRU context (one cell per sample, O(1) per step)"
    windowed = False
    certified = False
    trains = True

    def networks(self, spec: DynModelSpec, arrays: Mapping[str, Any], system: System,
                 window: int) -> Networks:
        hyper = spec.hyper
        cell = gru_cell_function(arrays, f"{HYPER}/gru", system.nu, hyper.hidden, "hyper_cell")
        memory = stream_memory(cell, system.ny)
        encoder = mlp_function(spec.encoder, arrays, ENCODER, "encoder")
        modulated = lora_mlp_of_hidden(spec.encoder, spec.decoder, hyper, arrays, DECODER, "decoder_of_h")
        z, w = ca.MX.sym("z", modulated.size1_in(0)), ca.MX.sym("w", *memory.shape)
        decoder = ca.Function("decoder", [z, w], [modulated(z, w[:hyper.hidden])], ["z", "w"], ["xhat"])
        return Networks(encoder, decoder, memory=memory)
