"""The table of observer variants: one object per card ``method``.

Everything that depends on the method -- the card's architecture entries and their typed spec,
the array names and shapes, the CasADi networks and latent input term, the torch training hook,
the CLI choices and the test parametrisations -- reads this table. Adding a variant is one new
module with a :class:`~kklcasadi.model.variants.base.Variant` subclass and one line in :data:`VARIANTS`.
"""

from __future__ import annotations

from ...validation import error
from .autonomous import Autonomous, Curriculum
from .bank import Bank, BankSpec
from .base import MapsSpec, Memory, Networks, Sizes, Variant, window_memory
from .dyn import Dyn, DynModelSpec
from .inject import Inject, model_injection_function
from .obs import MODEL_BASED_INJECTION, Obs, ObsModelSpec
from .stream import DynStream, ObsStream

__all__ = ["VARIANTS", "get", "names", "trainable", "Variant", "Networks", "Memory", "window_memory", "Sizes",
           "MapsSpec", "BankSpec",
           "ObsModelSpec", "DynModelSpec", "MODEL_BASED_INJECTION", "model_injection_function"]

#: Every observer variant, by card ``method``.
VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Autonomous(),
    Curriculum(),
    Obs(),
    Dyn(),
    Inject(),
    ObsStream(),
    DynStream(),
    Bank(),
)}


def names() -> tuple[str, ...]:
    """The known methods, in table order."""
    return tuple(VARIANTS)


def trainable() -> tuple[str, ...]:
    """The methods ``kklcasadi train`` makes (those with a training hook or derived from a base)."""
    return tuple(name for name, v in VARIANTS.items() if v.trains or v.derives_from)


def get(method: str) -> Variant:
    """The variant of ``method``; a ValueError lists the known ones."""
    if method not in VARIANTS:
        raise error("method", f"one of {list(VARIANTS)}", method,
                    "This kklcasadi version cannot run it; upgrade kklcasadi or use a known method.")
    return VARIANTS[method]
