"""The observers that ship with kklcasadi, ``models/<system>/<method>/``, and the one lookup of them.

The shipped models live in the ``models/`` directory of the source tree, which the package reaches
as ``kklcasadi/_models`` (a link to it in the tree; ``pip install .`` copies the models' cards and
weights there as package data, so an installed kklcasadi finds them from any directory). A model
directory given by path is the user's; only these are "shipped". :func:`resolve` names them from any
directory: ``"duffing/bank"`` (or ``"models/duffing/bank"``) is the shipped model unless a directory
of that name exists where it is given, which wins.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Union

from ..validation import Text, error

__all__ = ["SHIPPED_ROOT", "METHOD_ORDER", "shipped", "shipped_models", "shipped_model", "is_shipped", "resolve"]

#: Where the shipped models live: the package's ``_models`` (in a source tree a link to ``models/``), resolved.
SHIPPED_ROOT = (Path(__file__).resolve().parents[1] / "_models").resolve()
#: Order of the shipped methods in tables; other model directories follow alphabetically.
METHOD_ORDER = ("autonomous", "inject", "obs", "obs-inject", "dyn", "curriculum")

PathLike = Union[str, os.PathLike]


def _ordered(paths: list[Path]) -> list[Path]:
    rank = {name: i for i, name in enumerate(METHOD_ORDER)}
    return sorted(paths, key=lambda p: (rank.get(p.name, len(rank)), p.name))


def shipped() -> dict[str, list[str]]:
    """The shipped models by system: ``{"duffing": ["autonomous", "inject", ...], ...}`` (table order)."""
    found: dict[str, list[Path]] = {}
    for card in sorted(SHIPPED_ROOT.glob("*/*/card.json")):
        found.setdefault(card.parent.parent.name, []).append(card.parent)
    return {system: [p.name for p in _ordered(paths)] for system, paths in found.items()}


def _listing() -> str:
    return "; ".join(f"{name}: {', '.join(methods)}" for name, methods in shipped().items()) or "none found"


def shipped_models(system: str) -> list[Path]:
    """The model directories shipped for ``system``, in table order (:data:`METHOD_ORDER`).

    Raises
    ------
    ValueError
        No model is shipped for ``system``.
    """
    found = _ordered([card.parent for card in (SHIPPED_ROOT / str(system)).glob("*/card.json")])
    if not found:
        raise error("system", f"a system with shipped models ({_listing()})", system,
                    "Pass model directories instead.")
    return found


def shipped_model(system: str, method: str) -> Path:
    """The shipped model ``models/<system>/<method>``.

    Raises
    ------
    ValueError
        No such shipped model; the message lists the shipped ones.
    """
    path = SHIPPED_ROOT / str(system) / str(method)
    if not (path / "card.json").exists():
        raise ValueError(f"no shipped model models/{system}/{method} (shipped: {_listing()}); "
                         "pass a model directory for another model.")
    return path


def is_shipped(path: PathLike) -> bool:
    """Whether the model directory ``path`` is one of the shipped models."""
    if not isinstance(path, (str, os.PathLike)):
        raise error("path", "a model directory path", Text(type(path).__name__), kind=TypeError)
    resolved = Path(path).resolve()
    return resolved.parent.parent == SHIPPED_ROOT and (resolved / "card.json").exists()


def resolve(path: PathLike) -> Path:
    """The model directory ``path`` names: the directory itself where it exists, else the shipped model
    ``SYSTEM/METHOD`` (also written ``models/SYSTEM/METHOD``), from any directory.

    Parameters
    ----------
    path : str or path-like
        A model directory, or a shipped model's name such as ``"duffing/bank"``.

    Returns
    -------
    pathlib.Path
        ``path`` as given where it exists (a path that exists wins over a shipped name), else the
        shipped model's directory.

    Raises
    ------
    ValueError
        Neither an existing path nor a shipped model's name; the message lists the shipped models.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise error("path", "a model directory or a shipped model's name (SYSTEM/METHOD)", Text(type(path).__name__),
                    kind=TypeError)
    given = Path(path)
    if given.exists():
        return given
    parts = given.parts[1:] if given.parts[:1] == ("models",) else given.parts
    if len(parts) == 2 and not given.is_absolute() and (SHIPPED_ROOT / parts[0] / parts[1] / "card.json").is_file():
        return SHIPPED_ROOT / parts[0] / parts[1]
    raise error("path", f"an existing model directory or a shipped model's name SYSTEM/METHOD ({_listing()})",
                str(path), "No directory of that name exists here, and no shipped model has that name.")
