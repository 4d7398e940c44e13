"""What an observer variant is: its typed architecture spec, its CasADi networks and its hooks.

A variant (one per card ``method``) owns, in one place,

* which architecture entries its card holds and their typed spec (:meth:`Variant.parse`, the
  spec's ``to_card`` and ``array_shapes``),
* its CasADi parts (:meth:`Variant.networks`): the encoder, the decoder ``(z, w) -> xhat``, and
  the latent input term added to ``A z + B y`` (``None`` for a linear latent),
* whether it is trained (:attr:`Variant.trains`; the training side registers its hook and
  configuration class, and the model layer names nothing there),
* the extra top-level card fields it reads (:attr:`Variant.card_fields`).

Nothing here imports torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Mapping, Optional

import casadi as ca
import numpy as np

from ...nets.builders import mlp_function
from ...nets.specs import DECODER, ENCODER, MLPSpec, field_error
from ...plant.systems import System

__all__ = ["Sizes", "MapsSpec", "Networks", "Memory", "Variant", "InputTerm", "window_memory"]

#: ``input_term(z, u, context) -> dz`` (nz, 1), exactly 0 at ``u = 0``; ``context`` is the
#: output of :attr:`Networks.context` for the step's window (None if the variant has none).
InputTerm = Callable[[ca.MX, ca.MX, Optional[ca.MX]], ca.MX]


@dataclass(frozen=True)
class Sizes:
    """The sizes a card fixes: state ``nx``, input ``nu``, output ``ny``, latent ``nz``; and ``arrays``, how many
    arrays the weights hold where that is known (a count the card gives may not exceed it)."""

    nx: int
    nu: int
    ny: int
    nz: int
    arrays: Optional[int] = None


@dataclass(frozen=True)
class MapsSpec:
    """Encoder ``T: x -> z`` and decoder ``T*: z -> x``, the maps every variant has.

    Card entries ``"encoder"`` and ``"decoder"`` (:class:`kklcasadi.nets.specs.MLPSpec`).
    """

    encoder: MLPSpec
    decoder: MLPSpec

    @classmethod
    def parse_maps(cls, architecture: Mapping[str, Any], sizes: Sizes, where: str) -> MapsSpec:
        """Parse and size-check the ``encoder`` and ``decoder`` entries."""
        specs = {}
        for name, n_in, n_out in ((ENCODER, sizes.nx, sizes.nz), (DECODER, sizes.nz, sizes.nx)):
            spec = MLPSpec.from_card(architecture[name], where, f"architecture.{name}")
            if (spec.n_in, spec.n_out) != (n_in, n_out):
                raise field_error(where, f"architecture.{name}.sizes",
                                  f"[{n_in}, ..., {n_out}] (nx={sizes.nx}, nz={sizes.nz})",
                                  list(spec.sizes),
                                  "The encoder maps x to z and the decoder z to x; fix the sizes or "
                                  "the system/design entries.")
            specs[name] = spec
        return MapsSpec(specs[ENCODER], specs[DECODER])

    def to_card(self) -> dict:
        """The ``architecture`` card entries."""
        return {ENCODER: self.encoder.to_card(), DECODER: self.decoder.to_card()}

    def array_shapes(self) -> dict[str, tuple[int, ...]]:
        """Names and shapes of every array of the model file."""
        return {**self.encoder.array_shapes(ENCODER), **self.decoder.array_shapes(DECODER)}

    def maps(self) -> MapsSpec:
        """The encoder/decoder part alone (what a Phase-2 variant inherits from its base)."""
        return MapsSpec(self.encoder, self.decoder)


@dataclass(frozen=True)
class Memory:
    """What the observer remembers of the inputs between samples, ``w``: its shape and updates.

    The windowed variants remember the input window (:func:`window_memory`); a streaming variant
    remembers a context state updated once per sample (O(1) per step) and the held input.

    Attributes
    ----------
    shape : (int, int)
        Shape of ``w``.
    init : casadi.Function
        ``init(y0 (ny,1), u0 (nu,1)) -> w0``: the memory at the first sample.
    next : casadi.Function
        ``next(w, y_next (ny,1), u_next (nu,1)) -> w_next``: the memory at the next sample (a
        memory may keep the newest measurement, for a decoder that reads it).
    held : callable
        ``held(w) -> u_k`` (nu, 1), the input held over the current sample interval (MX).
    """

    shape: tuple[int, int]
    init: ca.Function
    next: ca.Function
    held: Callable[[ca.MX], ca.MX]


def window_memory(window: int, nu: int, ny: int) -> Memory:
    """The input window of ``docs/design.md``: ``(window, nu)``, oldest first, filled with ``u_0``."""
    y, u, w = ca.MX.sym("y", ny), ca.MX.sym("u", nu), ca.MX.sym("w", window, nu)
    init = ca.Function("memory_init", [y, u], [ca.repmat(u.T, window, 1)], ["y0", "u0"], ["w0"])
    shift = ca.Function("memory_next", [w, y, u], [ca.vertcat(w[1:, :], u.T)], ["w", "y_next", "u_next"],
                        ["w_next"])
    return Memory((window, nu), init, shift, lambda m: m[window - 1, :].T)


@dataclass(frozen=True)
class Networks:
    """The CasADi parts of one observer.

    Attributes
    ----------
    encoder : casadi.Function or None
        ``encoder(x) -> z`` (the window-free T); None for a latent that is not a map of the state.
    decoder : casadi.Function
        ``decoder(z (nz,1), w (window,nu)) -> xhat (nx,1)``.
    context : casadi.Function or None
        ``context(w) -> c``, evaluated once per sample interval and passed to ``input_term``.
    input_term : callable or None
        ``input_term(z, u, c) -> dz``, added to ``A z + B y``; exactly 0 at ``u = 0``. None for
        a linear latent ``zdot = A z + B y``.
    model_injection : casadi.Function or None
        ``model_injection(z, u) -> dz``, the model-based term, when the variant uses it.
    memory : Memory or None
        The observer's input memory ``w``; None for the input window of ``docs/design.md``.
    exact_step : casadi.Function or None
        ``exact_step(z, y, y_next, u) -> z_next``: the exact step of a linear latent with more
        than ``A z + B y`` (e.g. an input term); None for the first-order-hold step of ``(A, B)``.
    spread : casadi.Function or None
        ``spread(z (nz,1), w) -> s (1,1)``: how far the members of a decoder ensemble disagree
        (the domain monitor's second test); None for a single decoder.
    covariance : casadi.Function or None
        ``covariance(z (nz,1), w, xhat (nx,1)) -> P (nx,nx)``: the covariance of the estimate ``xhat``
        (:mod:`kklcasadi.model.variants.covariance`); None for a model without a covariance head.
    decoded : casadi.Function or None
        ``decoded(z, w) -> (xhat, s)``: ``decoder`` and ``spread`` from one evaluation of the ensemble's members
        (the same values); None without a spread.
    inflation : casadi.Function or None
        ``inflation(m, y, xhat, P, z) -> (m_next, P_inflated)``: the covariance head's inflation by the measurement
        residual (:mod:`kklcasadi.model.variants.inflation`); None for a model without one.
    inflation_start : numpy.ndarray or None
        Its carried state ``m`` at a run's start (:meth:`kklcasadi.model.variants.inflation.Inflation.initial_state`).
    exact_only : bool
        Whether only :attr:`exact_step` runs the latent: part of it is a discrete filter with no continuous-time
        field (the augmented EKF block of :mod:`kklcasadi.model.variants.ekfblock`), so ``A z + B y + input_term``
        is not its field there and the RK4 step and the integrator are refused.
    """

    encoder: Optional[ca.Function]
    decoder: ca.Function
    context: Optional[ca.Function] = None
    input_term: Optional[InputTerm] = None
    model_injection: Optional[ca.Function] = None
    memory: Optional[Memory] = None
    exact_step: Optional[ca.Function] = None
    spread: Optional[ca.Function] = None
    covariance: Optional[ca.Function] = None
    decoded: Optional[ca.Function] = None
    inflation: Optional[ca.Function] = None
    inflation_start: Optional[np.ndarray] = None
    exact_only: bool = False


class Variant:
    """Base class of the observer variants; subclasses set the class attributes and override
    :meth:`parse` and :meth:`networks`.

    Attributes
    ----------
    name : str
        The card's ``method``.
    summary : str
        One line for listings and the CLI help.
    entries : tuple of str
        The ``architecture`` entries of its card.
    optional_entries : tuple of str
        Entries its card may hold besides them (``bank``: ``covariance``, the covariance head).
    linear : bool
        Whether the latent dynamics are ``zdot = A z + B y`` (the exact discretisation applies).
    windowed : bool
        Whether the networks read the input window (else the card's window is 1).
    needs_base : bool
        Whether it is built on a Phase-1 model (``base`` argument of training).
    trains : bool
        Whether it is trained: the training side registers its hook and configuration class under
        :attr:`name` (the model layer names no training module).
    card_fields : tuple of str
        Extra top-level card fields it reads.
    derives_from : tuple of str
        The methods whose models it is made from without training (:meth:`derive`).
    modulated : bool
        Whether the maps T and T* depend on the input window (the hypernetwork of dyn).
    certified : bool
        Whether Proposition 1 of the paper applies: an encoder T and the input-window convention
        (:func:`kklcasadi.evaluation.certificate.certificate`).
    input_free : bool
        Whether the observer never reads ``u``: the latent is ``zdot = A z + B y`` and the estimate
        ``T*(z)`` (the autonomous observer and the curriculum baseline; the benchmark's
        hand-written dense C step is written for them).
    """

    name: ClassVar[str]
    summary: ClassVar[str]
    entries: ClassVar[tuple[str, ...]] = (ENCODER, DECODER)
    optional_entries: ClassVar[tuple[str, ...]] = ()
    linear: ClassVar[bool] = True
    windowed: ClassVar[bool] = False
    needs_base: ClassVar[bool] = True
    trains: ClassVar[bool] = False
    card_fields: ClassVar[tuple[str, ...]] = ()
    derives_from: ClassVar[tuple[str, ...]] = ()
    modulated: ClassVar[bool] = False
    certified: ClassVar[bool] = True
    input_free: ClassVar[bool] = False

    def parse(self, card: Mapping[str, Any], sizes: Sizes, where: str) -> Any:
        """The typed spec of a card whose common fields are valid.

        Parameters
        ----------
        card : Mapping
            The card (``card["architecture"]`` has exactly :attr:`entries`).
        sizes : Sizes
        where : str
            Used in error messages (the card's path).

        Returns
        -------
        spec
            A frozen dataclass with ``to_card()`` (the architecture entries),
            ``array_shapes()`` and the variant's parameters.
        """
        return MapsSpec.parse_maps(card["architecture"], sizes, where)

    def card_entries(self, spec: Any) -> dict:
        """The extra top-level card fields of ``spec`` (the inverse of :meth:`parse` for them)."""
        return {}

    def networks(self, spec: Any, arrays: Mapping[str, Any], system: System,
                 window: int) -> Networks:
        """Build the CasADi parts from a validated spec and its arrays."""
        return Networks(*plain_maps(spec, arrays, window, system.nu))

    def derive(self, base_method: str, spec: Any,
               arrays: Mapping[str, Any]) -> tuple[Any, dict, dict]:
        """The spec, arrays and training record of a model made from a base model, no training.

        Only variants with a non-empty :attr:`derives_from` implement it.
        """
        raise ValueError(f"method: {self.name!r} cannot be made from a base model without training.")

    def __repr__(self) -> str:
        return f"<variant {self.name!r}: {self.summary}>"


def plain_maps(spec: MapsSpec, arrays: Mapping[str, Any], window: int,
               nu: int) -> tuple[ca.Function, ca.Function]:
    """The encoder ``x -> z`` and the window-free decoder as ``(z, w) -> xhat``."""
    encoder = mlp_function(spec.encoder, arrays, ENCODER, "encoder")
    return encoder, window_free(mlp_function(spec.decoder, arrays, DECODER, "decoder"), window, nu)


def window_free(decoder: ca.Function, window: int, nu: int) -> ca.Function:
    """``decoder(z) -> xhat`` as ``(z, w (window, nu)) -> xhat``, ignoring the window."""
    return ignoring_memory(decoder, (window, nu))


def ignoring_memory(decoder: ca.Function, shape: tuple[int, int]) -> ca.Function:
    """``decoder(z) -> xhat`` as ``(z, w) -> xhat`` for a memory ``w`` of ``shape``, ignoring it."""
    z = ca.MX.sym("z", decoder.size1_in(0))
    w = ca.MX.sym("w", *shape)
    return ca.Function("decoder", [z, w], [decoder(z)], ["z", "w"], ["xhat"])
