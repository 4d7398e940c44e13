"""The observers that ship with kklcasadi, ``models/<system>/<method>/``, and the one lookup of them.

The shipped models live in the ``models/`` directory of the source tree, which the package reaches
as ``kklcasadi/_models`` (a link to it in the tree; ``pip install .`` copies the models' cards and
weights there as package data, so an installed kklcasadi finds them from any directory). Which models
ship is :data:`SHIPPED_MODELS`, not what happens to lie under ``models/``: a model directory a user
adds there (``models/duffing/mine``), like any directory given by path, is the user's. The command
line never writes into a shipped model (:func:`inside_shipped`). :func:`resolve` names them from any
directory: ``"duffing/bank"`` (or ``"models/duffing/bank"``) is the shipped model unless a directory
of that name exists where it is given, which wins.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Union

from ..validation import Text, error

__all__ = ["SHIPPED_ROOT", "SHIPPED_MODELS", "METHOD_ORDER", "shipped", "shipped_models", "shipped_model", "is_shipped",
           "inside_shipped", "resolve"]

#: Where the shipped models live: the package's ``_models`` (in a source tree a link to ``models/``), resolved.
SHIPPED_ROOT = (Path(__file__).resolve().parents[1] / "_models").resolve()
#: The models that ship, by system: the package's own (``models/<system>/<method>/`` of the source tree).
SHIPPED_MODELS = {
    "duffing": ("autonomous", "bank", "compact", "curriculum", "dyn", "inject", "obs", "obs-inject", "obs_stream",
                "robust"),
    "fhn": ("autonomous", "bank", "compact", "curriculum", "dyn", "inject", "obs"),
    "rossler": ("autonomous", "bank", "compact", "curriculum", "dyn", "dyn_stream", "inject", "obs", "obs_stream"),
    "vdp": ("autonomous", "bank", "compact", "curriculum", "dyn", "dyn_stream", "inject", "obs", "obs_stream",
            "robust"),
}
#: Order of the shipped methods in tables; other model directories follow alphabetically.
METHOD_ORDER = ("autonomous", "inject", "obs", "obs-inject", "dyn", "curriculum")

PathLike = Union[str, os.PathLike]


def _ordered(paths: list[Path]) -> list[Path]:
    rank = {name: i for i, name in enumerate(METHOD_ORDER)}
    return sorted(paths, key=lambda p: (rank.get(p.name, len(rank)), p.name))


def _present(system: str) -> list[Path]:
    return [SHIPPED_ROOT / system / method for method in SHIPPED_MODELS.get(system, ())
            if (SHIPPED_ROOT / system / method / "card.json").is_file()]


def shipped() -> dict[str, list[str]]:
    """The shipped models by system: ``{"duffing": ["autonomous", "inject", ...], ...}`` (table order)."""
    found = {system: _ordered(_present(system)) for system in sorted(SHIPPED_MODELS)}
    return {system: [p.name for p in paths] for system, paths in found.items() if paths}


def _listing() -> str:
    return "; ".join(f"{name}: {', '.join(methods)}" for name, methods in shipped().items()) or "none found"


def shipped_models(system: str) -> list[Path]:
    """The model directories shipped for ``system``, in table order (:data:`METHOD_ORDER`).

    Raises
    ------
    ValueError
        No model is shipped for ``system``.
    """
    found = _ordered(_present(str(system)))
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
    if path not in _present(str(system)):
        raise ValueError(f"no shipped model models/{system}/{method} (shipped: {_listing()}); "
                         "pass a model directory for another model.")
    return path


def _resolved(path: PathLike) -> Path:
    if not isinstance(path, (str, os.PathLike)):
        raise error("path", "a model directory path", Text(type(path).__name__), kind=TypeError)
    return Path(path).resolve()


def is_shipped(path: PathLike) -> bool:
    """Whether the model directory ``path`` is one of the shipped models (:data:`SHIPPED_MODELS`)."""
    resolved = _resolved(path)
    return resolved.parent.parent == SHIPPED_ROOT and resolved in _present(resolved.parent.name)


def inside_shipped(path: PathLike) -> bool:
    """Whether ``path`` is a shipped model's directory or lies inside one (a path the command line must not write)."""
    resolved = _resolved(path)
    return any(resolved == model or model in resolved.parents
               for system in SHIPPED_MODELS for model in (SHIPPED_ROOT / system / m for m in SHIPPED_MODELS[system]))


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
    if len(parts) == 2 and not given.is_absolute() and SHIPPED_ROOT / parts[0] / parts[1] in _present(parts[0]):
        return SHIPPED_ROOT / parts[0] / parts[1]
    raise error("path", f"an existing model directory or a shipped model's name SYSTEM/METHOD ({_listing()})",
                str(path), "No directory of that name exists here, and no shipped model has that name.")
