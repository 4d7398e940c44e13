"""The training side of the variant table: each trained variant's hook and configuration class.

The variant table (:data:`kklcasadi.model.variants.VARIANTS`) says whether a variant is trained
(``Variant.trains``) and names nothing on this side; the module that trains a variant registers its hook
here (:func:`register`, at the end of :mod:`.phase1`, :mod:`.phase2`, :mod:`.stream` and :mod:`.bank`,
which :mod:`kklcasadi.train` imports). :func:`kklcasadi.train.train_observer` calls the hook and
:func:`kklcasadi.train.config.default_config` builds the class.

A hook is called as ``hook(system, design, base, config, *, dt, seed, device, progress, workdir, resume)``
and returns a :class:`kklcasadi.train.result.Trained`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..model import variants
from ..validation import Text, error

__all__ = ["Trainer", "TRAINERS", "register", "trainer"]


@dataclass(frozen=True)
class Trainer:
    """A variant's training.

    Attributes
    ----------
    hook : callable
        ``hook(system, design, base, config, *, dt, seed, device, progress, workdir, resume) -> Trained``.
    config : type
        Its configuration class (a frozen dataclass; ``config.for_system(name)`` where it has one).
    """

    hook: Callable[..., object]
    config: type


#: The registered trainers by method.
TRAINERS: dict[str, Trainer] = {}


def register(method: str, hook: Callable[..., object], config: type) -> None:
    """Register the training of ``method``, a variant of the table whose ``trains`` is set.

    Raises
    ------
    ValueError
        ``method`` is not in the table, is not trained, or is registered already.
    """
    variant = variants.get(method)
    if not variant.trains:
        raise error("method", "a variant whose trains is True", method,
                    "Set trains = True on its class in kklcasadi/model/variants/.")
    if method in TRAINERS:
        raise error("method", "a method not registered yet", method, "Register each trainer once.")
    if not isinstance(config, type):
        raise error("config", "a configuration class", Text(type(config).__name__), kind=TypeError)
    TRAINERS[method] = Trainer(hook, config)


def trainer(method: str) -> Trainer:
    """The registered training of ``method`` (a ValueError names the trained methods otherwise)."""
    if method not in TRAINERS:
        raise error("method", f"one of {sorted(TRAINERS)} (a trained method)", method)
    return TRAINERS[method]
