"""``inject``: the autonomous maps plus the exact model-based input correction (no training).

``zdot = A z + B y + dT/dx(xhat) (f(xhat, u) - f(xhat, 0))`` at ``xhat = T*(z)``, built
symbolically from the exported encoder and the plant.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

import casadi as ca

from ...plant.systems import System
from .base import MapsSpec, Networks, Variant, plain_maps

__all__ = ["Inject", "model_injection_function"]


def model_injection_function(encoder: ca.Function, decoder: ca.Function,
                             system: System) -> ca.Function:
    """``dz = dT/dx(xhat) (f(xhat, u) - f(xhat, 0))`` at ``xhat = T*(z)``, exact (a JVP).

    Parameters
    ----------
    encoder : casadi.Function
        ``T: x (nx,1) -> z (nz,1)``.
    decoder : casadi.Function
        ``T*: (z (nz,1), w) -> xhat (nx,1)``; the window is not used (pass a window-free decoder).
    system : System
        The plant, for ``f``.

    Returns
    -------
    casadi.Function
        ``model_injection(z (nz,1), u (nu,1)) -> dz (nz,1)``; the difference of two evaluations
        of the same plant function, so exactly 0 at ``u = 0``.
    """
    x, v = ca.MX.sym("x", system.nx), ca.MX.sym("v", system.nx)
    jvp = ca.Function("encoder_jvp", [x, v], [ca.jtimes(encoder(x), x, v)], ["x", "v"], ["dz"])
    z, u = ca.MX.sym("z", encoder.size1_out(0)), ca.MX.sym("u", system.nu)
    xhat = decoder(z, ca.DM.zeros(*decoder.size_in(1)))
    f = system.f
    dz = jvp(xhat, f(xhat, u) - f(xhat, ca.DM.zeros(system.nu)))
    return ca.Function("model_injection", [z, u], [dz], ["z", "u"], ["dz"])


class Inject(Variant):
    """The base model's encoder and decoder with the model-based input term; nothing to train."""

    name = "inject"
    summary = "ours: autonomous maps + exact model-based term dT/dx(xhat)(f(xhat,u) - f(xhat,0))"
    linear = False

    def networks(self, spec: MapsSpec, arrays: Mapping[str, Any], system: System,
                 window: int) -> Networks:
        encoder, decoder = plain_maps(spec, arrays, window, system.nu)
        injection = model_injection_function(encoder, decoder, system)

        def input_term(z: ca.MX, u: ca.MX, context: Optional[ca.MX]) -> ca.MX:
            return injection(z, u)

        return Networks(encoder, decoder, None, input_term, injection)

    #: The methods whose model an ``inject`` model is made from (a Phase-1 encoder/decoder pair).
    derives_from = ("autonomous", "curriculum")

    def derive(self, base_method: str, spec: MapsSpec,
               arrays: Mapping[str, Any]) -> tuple[MapsSpec, dict, dict]:
        """The spec, arrays and training record of an ``inject`` model made from a base model.

        Parameters
        ----------
        base_method : str
            The base model's method, one of :attr:`derives_from`.
        spec : MapsSpec
            The base model's spec.
        arrays : Mapping[str, array_like]
            The base model's arrays.

        Returns
        -------
        spec, arrays, training
            The encoder/decoder spec and arrays, and the card's training record.
        """
        maps = spec.maps()
        kept = {name: arrays[name] for name in maps.array_shapes()}
        training = {"note": "model-based input injection: the base model's encoder and decoder "
                            "with the exact term dT/dx(xhat) (f(xhat, u) - f(xhat, 0)); no training",
                    "base_method": base_method}
        return maps, kept, training
