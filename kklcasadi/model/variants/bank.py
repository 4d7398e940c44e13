"""``bank``: a linear filter bank of the measurement and the input, and a decoder fitted on the
observer's own noisy runs (the operational decoder).

``zdot = A z + By y + Bu u + c`` (``A`` block diagonal: first-order filters of ``y`` and ``u`` at a
spread of pole speeds, optional resonators of ``y``, an optional clock ``c`` that tells the decoder
how long the observer has run), ``z(0) = 0``; ``xhat = D([z; y_k; u_k])`` with an optional per-state
``asinh`` output scale. The latent is linear, so its exact discretisation is used; the decoder reads
the newest measurement and input, which the observer's memory ``w = [y_k; u_k]`` carries. Built by
:mod:`kklcasadi.model.variants.filterbank` and trained by :mod:`kklcasadi.train.decoder` (on the samples of
:mod:`kklcasadi.model.operational`) for the noise level and input ranges its card records. There is no
encoder: the latent is not a KKL map of the state but a fixed filter of the signals, and the decoder learns
the state from it.

Angles (``System.angle_outputs``, ``angle_states``) are read and written continuously on the circle
(:class:`kklcasadi.model.variants.bankdecoder.Angles`).

The latent may end in model copies of the plant (:mod:`kklcasadi.model.variants.copies`): constant-gain
observers ``xhat_i' = f(xhat_i, u) + L_i (y - h(xhat_i))`` whose states the decoder reads beside the
filters; their linear part is in ``(A, By)`` and the rest in the input term, and the step takes RK4 for
them (the filters' stays exact).

The decoder may be an ensemble of ``K`` networks of one architecture, fitted from different seeds
on the same runs: ``xhat`` maps the mean of their outputs, and their disagreement
(:func:`kklcasadi.model.variants.bankdecoder.spread`) is the domain monitor's second test.

Card: ``design`` holds ``A`` and ``By`` (as ``B``); ``architecture`` holds ``decoder``
(``[nz + ny + n_angle_outputs + nu, ..., nx + n_free_angle_states]``) and ``bank`` (the design
parameters, for the record, the angle layout ``angles`` where there are angles, and ``members``
K where the decoder is an ensemble, ``copies`` where the latent has model copies); the arrays ``bank/Bu``
(nf, nu) and ``bank/c`` (nf,) of the ``nf`` filter latents, ``copies/*`` where there are copies,
``decoder/asinh_scale`` (nx,) and the MLP arrays of each member (``decoder``, ``decoder_1``, ...)
complete it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Optional

import casadi as ca
import numpy as np

from ...nets.specs import DECODER, MLPSpec, field_error
from ...plant.systems import System
from ...validation import Text, is_int, is_number
from .bankdecoder import (
    ASINH_SCALE,
    Angles,
    DecoderSpec,
    decoder_and_spread_expression,
    decoder_expression,
    feature_expression,
    member_prefixes,
)
from .base import Memory, Networks, Sizes, Variant
from .copies import ModelCopies
from .covariance import COVARIANCE, covariance_expression, n_entries
from .covariance import array_shapes as covariance_shapes
from .ekfblock import EKF_BLOCK, EKFBlock
from .filterbank import FilterBank, latent_step
from .inflation import INFLATION, MODEL, SPREAD, CopyLayout, Inflation, inflation_function

__all__ = ["Bank", "BankSpec", "ASINH_SCALE", "feedthrough_memory"]

_BANK_KEYS = ("y_poles", "u_poles", "y_resonators", "clock")
#: Keys of ``architecture.bank`` that cards written before them lack (``copies`` only where the latent has model
#: copies, ``ekf`` only where it has the augmented EKF's block).
_OPTIONAL_KEYS = ("time_scale", "angles", "members", "copies", EKF_BLOCK)


@dataclass(frozen=True, eq=False)
class BankSpec:
    """The decoder, the latent matrices, the bank's design parameters and its angle layout."""

    decoder: MLPSpec
    A: np.ndarray
    By: np.ndarray
    dt: float
    nu: int
    params: dict
    angles: Angles = Angles()
    covariance: Optional[MLPSpec] = None
    inflation: Optional[Inflation] = None

    @property
    def nz(self) -> int:
        return self.A.shape[0]

    @property
    def nx(self) -> int:
        return self.decoder.n_out - len(self.angles.free)

    @property
    def members(self) -> int:
        """Decoder networks averaged (``architecture.bank.members``; 1 where the card has none)."""
        return int(self.params.get("members", 1))

    @property
    def n_copies(self) -> int:
        """Model copies of the plant in the latent (``architecture.bank.copies``; 0 where the card has none)."""
        return len(self.params["copies"]["weights"]) if "copies" in self.params else 0

    @property
    def copy_states(self) -> Optional[tuple[int, ...]]:
        """The states each model copy carries (``architecture.bank.copies.states``; None where the card has none:
        all ``nx``, or no copies)."""
        states = self.params.get("copies", {}).get("states")
        return None if states is None else tuple(int(i) for i in states)

    @property
    def n_copy_latents(self) -> int:
        """The model copies' latents (after the filters')."""
        states = self.copy_states
        return self.n_copies * (self.nx if states is None else len(states))

    @property
    def n_ekf(self) -> int:
        """The augmented EKF block's latents (the last ones; 0 where the card has no ``architecture.bank.ekf``): the
        latent less the filters the card's design parameters give and the copies'."""
        if EKF_BLOCK not in self.params:
            return 0
        p, ny = self.params, self.By.shape[1]
        filters = (ny * len(p["y_poles"]) + 2 * ny * len(p["y_resonators"]) + self.nu * len(p["u_poles"])
                   + (p["clock"] is not None))
        return self.nz - filters - self.n_copy_latents

    @property
    def n_filters(self) -> int:
        """The filter bank's latents (the first ones; the model copies' follow, then the EKF block's)."""
        return self.nz - self.n_copy_latents - self.n_ekf

    @property
    def decoder_spec(self) -> DecoderSpec:
        """The decoder's typed spec (network, angle layout, ensemble, the copies' states) for
        :mod:`kklcasadi.model.variants.filterbank`."""
        return DecoderSpec(self.decoder, self.angles, self.members, self.copy_states)

    def filter_bank(self, arrays: Mapping[str, Any]) -> FilterBank:
        """The filter bank of the latent's first :attr:`n_filters` rows (``A``, ``By`` of the card's ``design``,
        ``bank/Bu`` and ``bank/c`` of the arrays)."""
        n = self.n_filters
        return FilterBank(self.A[:n, :n], self.By[:n], arrays["bank/Bu"], arrays["bank/c"])

    def filter_arrays(self, arrays: Mapping[str, Any]) -> dict:
        """The model's arrays with the filter bank's ``bank/A`` and ``bank/By`` (the card's ``design`` rows of
        the filters), as :mod:`kklcasadi.model.variants.filterbank`'s functions take them."""
        n = self.n_filters
        return {**arrays, "bank/A": self.A[:n, :n], "bank/By": self.By[:n]}

    def model_copies(self, arrays: Mapping[str, Any], system: System) -> Optional[ModelCopies]:
        """The latent's model copies of ``system`` from the arrays (None where the card has none), checked
        against the card's ``design``: its rows of the copies must be their linear part."""
        if not self.n_copies:
            return None
        copies = ModelCopies.from_arrays(arrays, system, int(self.params["copies"]["substeps"]), self.copy_states,
                                         self.params["copies"].get("params"))
        A, B = copies.linear_part()
        n, c = self.n_filters, self.n_filters + copies.nz
        if not (np.allclose(self.A[n:c, n:c], A, rtol=1e-9, atol=1e-12) and np.allclose(self.By[n:c], B, rtol=1e-9,
                                                                                           atol=1e-12)
                and not np.any(self.A[:n, n:c]) and not np.any(self.A[n:c, :n])):
            raise ValueError(f"design: expected the model copies' rows of A and B to be their linear part at "
                             f"{system.name}'s box centre (F - L H, L; docs/model-format.md), received others. The "
                             "card was written for another plant or edited; retrain it.")
        return copies

    def ekf_block(self, system: System) -> Optional[EKFBlock]:
        """The latent's augmented EKF block for ``system`` from the card's ``architecture.bank.ekf`` (None where the
        card has none), checked against the card's ``design``: its rows of ``A`` and ``B`` must be ``-I / dt`` and 0
        and its size ``na + na^2 + 1``, ``na = nx + n_params``."""
        if not self.n_ekf:
            return None
        block = EKFBlock.from_card(self.params[EKF_BLOCK], system, self.dt)
        c = self.nz - self.n_ekf
        A, B = block.linear_part()
        if block.nz != self.n_ekf or not (np.array_equal(self.A[c:, c:], A) and not np.any(self.By[c:])
                                          and not np.any(self.A[:c, c:]) and not np.any(self.A[c:, :c])):
            raise ValueError(f"design: expected the EKF block's last {block.nz} rows of A and B to be -I / dt and 0 "
                             f"({system.name}'s augmented EKF: nx + n_params = {block.na} states and their covariance, "
                             f"and a start flag; docs/model-format.md), received {self.n_ekf} rows or others. The "
                             "card was written for another plant or edited; retrain it.")
        return block

    def to_card(self) -> dict:
        bank = dict(self.params)
        if self.angles:
            bank["angles"] = self.angles.to_card()
        card = {DECODER: self.decoder.to_card(), "bank": bank}
        if self.covariance is not None:
            card[COVARIANCE] = self.covariance.to_card()
        if self.inflation is not None:
            card[INFLATION] = self.inflation.to_card()
        return card

    def array_shapes(self) -> dict[str, tuple[int, ...]]:
        n = self.n_filters
        shapes = {ASINH_SCALE: (self.nx,), "bank/Bu": (n, self.nu), "bank/c": (n,)}
        if self.n_copies:
            ny = self.By.shape[1]
            nk = self.nx if self.copy_states is None else len(self.copy_states)
            shapes.update({"copies/gains": (self.n_copies, nk, ny), "copies/reference": (nk,), "copies/bound": (nk,)})
        for prefix in member_prefixes(self.members):
            shapes.update(self.decoder.array_shapes(prefix))
        if self.covariance is not None:
            shapes.update(covariance_shapes(self.covariance, self.nx))
        return shapes


def _positive_numbers(value: Any) -> bool:
    return isinstance(value, list) and all(is_number(v) and math.isfinite(v) and v > 0 for v in value)


def _intensities(value: Any) -> bool:
    """One model copy's intensities per state: a list of finite numbers >= 0, not all 0."""
    return (isinstance(value, list) and bool(value) and all(is_number(v) and math.isfinite(v) and v >= 0 for v in value)
            and any(v > 0 for v in value))


def _copy_params(value: Any, m: int) -> bool:
    """The model copies' parameter values: ``m`` lists of one length >= 1 of finite numbers."""
    return (isinstance(value, list) and len(value) == m
            and all(isinstance(row, list) and row and len(row) == len(value[0])
                    and all(is_number(v) and math.isfinite(v) for v in row) for row in value))


def _params(entry: Any, where: str, sizes: Sizes) -> dict:
    fix = ('Write "bank" as {"y_poles": [p, ...], "u_poles": [p, ...], "y_resonators": [[zeta, omega], ...], '
           '"clock": rate or null} (optionally "time_scale": rate, "angles": {...} and "members": K, the decoder '
           'networks averaged).')
    if (not isinstance(entry, Mapping) or not set(_BANK_KEYS) <= set(entry)
            or not set(entry) <= set(_BANK_KEYS + _OPTIONAL_KEYS)):
        raise field_error(where, "architecture.bank", f"an object with the keys {list(_BANK_KEYS)} (and optionally "
                          f"{list(_OPTIONAL_KEYS)})", entry, fix)
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
    if "time_scale" in entry and not _positive_numbers([entry["time_scale"]]):
        raise field_error(where, "architecture.bank.time_scale", "a rate > 0 (rad/s)", entry["time_scale"], fix)
    if "members" in entry and not (is_int(entry["members"]) and entry["members"] >= 1):
        raise field_error(where, "architecture.bank.members", "a positive integer (decoder networks averaged)",
                          entry["members"], fix)
    if "members" in entry and sizes.arrays is not None and entry["members"] > sizes.arrays:
        raise field_error(where, "architecture.bank.members", f"at most the {sizes.arrays} arrays the weights hold",
                          entry["members"], fix)
    if "copies" in entry:
        copies = entry["copies"]
        if not (isinstance(copies, Mapping) and {"weights", "substeps"} <= set(copies) <= {"weights", "substeps",
                                                                                          "states", "params"}
                and isinstance(copies["weights"], list) and copies["weights"]
                and all(_positive_numbers([w]) or _intensities(w) for w in copies["weights"])
                and is_int(copies["substeps"]) and copies["substeps"] >= 1
                and ("params" not in copies or _copy_params(copies["params"], len(copies["weights"])))):
            raise field_error(where, "architecture.bank.copies", '{"weights": [w > 0 or [w_1 >= 0, ...], ...], '
                              '"substeps": n >= 1} (the model copies\' process intensities, one or one per state, '
                              'and RK4 steps per sample; optionally "states": [i, ...], the states they carry, and '
                              '"params": [[p_1, ...], ...], each copy\'s parameter values: one list each, of the '
                              "plant's n_params finite numbers)", copies, fix)
        states = copies.get("states")
        if "states" in copies and not (isinstance(states, list) and states and all(is_int(i) for i in states)
                                       and states == sorted(set(states)) and states[0] >= 0
                                       and states[-1] < sizes.nx and len(states) < sizes.nx):
            raise field_error(where, "architecture.bank.copies.states", f"ascending distinct state indices in [0, "
                              f"nx = {sizes.nx}), fewer than nx (the states the model copies carry; absent where "
                              "they carry every one)", states, fix)
    if EKF_BLOCK in entry:
        EKFBlock.check_card(entry[EKF_BLOCK], where, sizes.nx)
    return {key: entry[key] for key in _BANK_KEYS + ("time_scale", "members", "copies", EKF_BLOCK) if key in entry}


def _angles(entry: Mapping[str, Any], where: str, sizes: Sizes) -> Angles:
    if "angles" not in entry:
        return Angles()
    fix = 'Write "angles" as {"outputs": [j, ...], "measured": [[i, j], ...], "free": [[i, centre], ...]}.'
    try:
        angles = Angles.from_card(entry["angles"])
    except ValueError as exc:
        raise field_error(where, "architecture.bank.angles", "an angle layout", entry["angles"], fix) from exc
    states = [i for i, _ in angles.measured] + [i for i, _ in angles.free]
    if any(j >= sizes.ny for j in angles.outputs) or any(i >= sizes.nx for i in states):
        raise field_error(where, "architecture.bank.angles", f"outputs < ny = {sizes.ny} and states < nx = {sizes.nx}",
                          entry["angles"], fix)
    return angles


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
    optional_entries = (COVARIANCE, INFLATION)
    linear = True
    needs_base = False
    certified = False
    trains = True

    def parse(self, card: Mapping[str, Any], sizes: Sizes, where: str) -> BankSpec:
        decoder = MLPSpec.from_card(card["architecture"][DECODER], where, "architecture.decoder")
        entry = card["architecture"]["bank"]
        angles = _angles(entry, where, sizes) if isinstance(entry, Mapping) else Angles()
        n_in, n_out = angles.n_features(sizes.nz, sizes.ny, sizes.nu), angles.n_outputs(sizes.nx)
        if (decoder.n_in, decoder.n_out) != (n_in, n_out):
            raise field_error(where, "architecture.decoder.sizes",
                              f"[nz + ny + angle outputs + nu = {n_in}, ..., nx + free angle states = {n_out}]",
                              list(decoder.sizes), "The bank's decoder maps [z; y; u] (angle outputs as sin and cos) "
                              "to x (free angle states as cos and sin).")
        A = np.array(card["design"]["A"], dtype=float)
        By = np.array(card["design"]["B"], dtype=float)
        if np.max(np.linalg.eigvals(A).real) >= 0:
            raise field_error(where, "design.A", "a Hurwitz matrix (the filter bank is stable)",
                              float(np.max(np.linalg.eigvals(A).real)), "Use the bank's A.")
        head = None
        if COVARIANCE in card["architecture"]:
            head = MLPSpec.from_card(card["architecture"][COVARIANCE], where, f"architecture.{COVARIANCE}")
            if head.n_in != n_in or head.n_out != n_entries(sizes.nx) or angles.measured or angles.free:
                raise field_error(where, f"architecture.{COVARIANCE}.sizes", f"[{n_in} (the decoder's input), ..., "
                                  f"nx (nx + 1) / 2 = {n_entries(sizes.nx)}] on a plant without angle states",
                                  list(head.sizes), "The covariance head reads the decoder's features and gives the "
                                  "factor of the estimate's covariance (docs/model-format.md); an angle state's "
                                  "error lives on the circle, which it does not model.")
        inflation = None
        if INFLATION in card["architecture"]:
            if head is None:
                raise field_error(where, f"architecture.{INFLATION}", f"an entry beside architecture.{COVARIANCE} "
                                  "(it inflates the covariance head's output)", card["architecture"][INFLATION],
                                  f"Remove architecture.{INFLATION} or add the head (docs/model-format.md).")
            inflation = Inflation.from_card(card["architecture"][INFLATION], where, sizes.ny)
        spec = BankSpec(decoder, A, By, float(card["dt"]), sizes.nu, _params(entry, where, sizes), angles, head,
                        inflation)
        if inflation is not None and inflation.model is not None and inflation.model.copy >= spec.n_copies:
            raise field_error(where, f"architecture.{INFLATION}.{MODEL}.copy", f"one of the latent's {spec.n_copies} "
                              "model copies (0-based)", inflation.model.copy,
                              "The model test reads a model copy's innovation (architecture.bank.copies).")
        if EKF_BLOCK in spec.params:
            na = (math.isqrt(max(4 * spec.n_ekf - 3, 0)) - 1) // 2          # n_ekf = na + na^2 + 1
            if na <= sizes.nx or na + na * na + 1 != spec.n_ekf or spec.angles:
                raise field_error(where, "architecture.bank.ekf", "the block of the augmented EKF on a plant with "
                                  f"parameters and without angles: na + na^2 + 1 latents after the filters and "
                                  f"the copies, na = nx + n_params > nx = {sizes.nx}",
                                  Text(f"{spec.n_ekf} latents{' and angles' if spec.angles else ''}"),
                                  "The card was written for another plant or edited; retrain it.")
        if inflation is not None and inflation.spread is not None and spec.members < 2:
            raise field_error(where, f"architecture.{INFLATION}.{SPREAD}", "an entry of a bank with a decoder ensemble "
                              "(architecture.bank.members >= 2)", inflation.spread.to_card(),
                              "The spread test reads the members' disagreement; remove it for a single decoder.")
        if spec.n_copies and spec.n_filters < 1:
            nk = spec.nx if spec.copy_states is None else len(spec.copy_states)
            raise field_error(where, "architecture.bank.copies", f"model copies of {spec.n_copies} x {nk} states = "
                              f"{spec.n_copies * nk} latents after at least one filter", entry["copies"],
                              f"The latent has nz = {spec.nz}.")
        return spec

    def networks(self, spec: BankSpec, arrays: Mapping[str, Any], system: System, window: int) -> Networks:
        n = spec.n_filters
        bank = spec.filter_bank(arrays)
        copies = spec.model_copies(arrays, system)
        ekf = spec.ekf_block(system)
        memory = feedthrough_memory(system.ny, system.nu)
        z, w = ca.MX.sym("z", spec.nz), ca.MX.sym("w", *memory.shape)
        decoder_spec, y, u = spec.decoder_spec, w[:system.ny], w[system.ny:]
        spread = decoded = None
        if spec.members < 2:
            xhat = decoder_expression(decoder_spec, arrays, bank, z, y, u)
        else:                                       # the members run once for the estimate and their spread
            xhat, s = decoder_and_spread_expression(decoder_spec, arrays, bank, z, y, u)
            spread = ca.Function("spread", [z, w], [s], ["z", "w"], ["spread"])
            decoded = ca.Function("decoded", [z, w], [xhat, s], ["z", "w"], ["xhat", "spread"])
        decoder = ca.Function("decoder", [z, w], [xhat], ["z", "w"], ["xhat"])
        covariance = None
        if spec.covariance is not None:
            xs = ca.MX.sym("xhat", spec.nx)
            features = feature_expression(bank, z, y, u, angles=spec.angles, states=decoder_spec.carried)
            P = covariance_expression(spec.covariance, arrays, features, xs, np.asarray(arrays[f"{DECODER}/out_std"]),
                                      np.asarray(arrays[ASINH_SCALE]))
            covariance = ca.Function("covariance", [z, w, xs], [P], ["z", "w", "xhat"], ["P"])
        inflation = None
        if spec.inflation is not None:
            layout = None if spec.inflation.model is None else CopyLayout(
                n + spec.inflation.model.copy * spec.nx, tuple(float(v) for v in arrays["copies/reference"]))
            inflation = inflation_function(spec.inflation, system, spec.dt, spec.nz, layout)
        bu, c = ca.DM(bank.Bu), ca.DM(bank.c)

        def input_term(zz: ca.MX, u: ca.MX, context: Optional[ca.MX]) -> ca.MX:
            filters = ca.mtimes(bu, u) + c
            parts = [filters] + ([] if copies is None else [copies.remainder(zz[n:n + copies.nz], u)])
            return ca.vertcat(*parts, *([] if ekf is None else [ca.MX.zeros(ekf.nz)]))   # the block: exact step only

        return Networks(None, decoder, None, input_term, memory=memory,
                        exact_step=latent_step(bank, spec.dt, copies=copies, ekf=ekf), exact_only=ekf is not None,
                        spread=spread, covariance=covariance,
                        decoded=decoded, inflation=inflation,
                        inflation_start=None if spec.inflation is None else spec.inflation.initial_state())
