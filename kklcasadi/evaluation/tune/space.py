"""The search space of a design search (``kklcasadi tune``): dimensions that name the fields of a method's
training configuration by dotted path, one entry of :data:`SPACES` per method that trains."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, is_dataclass, replace
from typing import Any, Optional, Sequence, Union

import numpy as np

from ...validation import Text, error, positive_int

__all__ = ["Float", "Int", "Filters", "Layers", "MaybeRate", "Budget", "Space", "SPACES", "search_space", "field_names"]


def _paths(paths: Union[str, Sequence[str]]) -> tuple[str, ...]:
    return (paths,) if isinstance(paths, str) else tuple(paths)


@dataclass(frozen=True)
class Float:
    """A real field (or several fields set to one value), uniform or log-uniform on ``[low, high]``."""

    name: str
    paths: Union[str, tuple]
    low: float
    high: float
    log: bool = False

    def suggest(self, trial: Any) -> float:
        return trial.suggest_float(self.name, self.low, self.high, log=self.log)

    def describe(self) -> dict:
        return {"name": self.name, "kind": "float", "paths": list(_paths(self.paths)), "low": self.low,
                "high": self.high, "log": self.log}


@dataclass(frozen=True)
class Int:
    """An integer field (or several), uniform or log-uniform on ``[low, high]``."""

    name: str
    paths: Union[str, tuple]
    low: int
    high: int
    log: bool = False

    def suggest(self, trial: Any) -> int:
        return trial.suggest_int(self.name, self.low, self.high, log=self.log)

    def describe(self) -> dict:
        return {"name": self.name, "kind": "int", "paths": list(_paths(self.paths)), "low": self.low,
                "high": self.high, "log": self.log}


@dataclass(frozen=True)
class Filters:
    """A tuple of filter rates (rad/s): ``count`` of them log-spaced from ``slow`` to ``slow * span``.

    Optuna parameters ``NAME_n``, then (``n >= 1``) ``NAME_slow`` and (``n >= 2``) ``NAME_span``.
    """

    name: str
    paths: Union[str, tuple]
    count: tuple
    slow: tuple
    span: tuple

    def suggest(self, trial: Any) -> tuple:
        n = trial.suggest_int(f"{self.name}_n", *self.count)
        if n == 0:
            return ()
        slow = trial.suggest_float(f"{self.name}_slow", *self.slow, log=True)
        if n == 1:
            return (slow,)
        span = trial.suggest_float(f"{self.name}_span", *self.span, log=True)
        return tuple(float(v) for v in np.geomspace(slow, slow * span, n))

    def describe(self) -> dict:
        return {"name": self.name, "kind": "filters", "paths": list(_paths(self.paths)), "count": list(self.count),
                "slow": list(self.slow), "span": list(self.span)}


@dataclass(frozen=True)
class Layers:
    """Hidden layer widths: ``depth`` layers of one ``width`` (``NAME_width`` log-uniform, ``NAME_depth``)."""

    name: str
    paths: Union[str, tuple]
    width: tuple
    depth: tuple

    def suggest(self, trial: Any) -> tuple:
        width = trial.suggest_int(f"{self.name}_width", *self.width, log=True)
        return (width,) * trial.suggest_int(f"{self.name}_depth", *self.depth)

    def describe(self) -> dict:
        return {"name": self.name, "kind": "layers", "paths": list(_paths(self.paths)), "width": list(self.width),
                "depth": list(self.depth)}


@dataclass(frozen=True)
class MaybeRate:
    """None or a rate log-uniform on ``[low, high]`` (``NAME_on``, then ``NAME_rate``)."""

    name: str
    paths: Union[str, tuple]
    low: float
    high: float

    def suggest(self, trial: Any) -> Optional[float]:
        if not trial.suggest_categorical(f"{self.name}_on", [True, False]):
            return None
        return trial.suggest_float(f"{self.name}_rate", self.low, self.high, log=True)

    def describe(self) -> dict:
        return {"name": self.name, "kind": "maybe_rate", "paths": list(_paths(self.paths)), "low": self.low,
                "high": self.high}


@dataclass(frozen=True)
class Budget:
    """A budget (runs, epochs): an integer from ``fraction`` of the cap up to the cap, log-uniform.

    The cap is the configuration's own value at the first path unless :func:`search_space` is given
    one; the baseline is trained at the cap.
    """

    name: str
    paths: Union[str, tuple]
    fraction: float = 0.5

    def resolve(self, cap: int) -> Int:
        cap = positive_int(cap, f"{self.name} budget")
        return Int(self.name, self.paths, max(1, math.ceil(self.fraction * cap)), cap, log=True)


#: The search space of every method that trains, by the dotted names of its configuration's fields.
#: ``bank``: the output and input filters (counts and rates), the clock, the decoder's width and
#: depth, the training noise, the learning rate and the budget (runs and epochs); the others: what
#: their configurations expose. The recipe's values lie inside every range.
SPACES: dict[str, tuple] = {
    "bank": (
        Filters("y_filters", "y_poles", count=(3, 12), slow=(0.05, 1.0), span=(5.0, 500.0)),
        Filters("u_filters", "u_poles", count=(0, 4), slow=(0.1, 1.0), span=(2.0, 100.0)),
        MaybeRate("clock", "clock", 0.05, 1.0),
        Layers("decoder", "decoder.hidden", width=(32, 384), depth=(1, 4)),
        Float("noise", ("measurement_std", "process_std"), 0.05, 0.2, log=True),
        Float("lr", "decoder.loop.lr", 3e-4, 3e-3, log=True),
        Budget("runs", "rollouts.n_traj"),
        Budget("epochs", "decoder.loop.epochs"),
    ),
    "autonomous": (
        Int("width", "width", 32, 256, log=True),
        Int("depth", "depth", 2, 4),
        Float("lr", ("encoder.lr", "decoder.lr"), 3e-4, 5e-3, log=True),
        Float("noise", "measurement_std", 0.0, 0.2),
        Budget("runs", "n_traj"),
        Budget("epochs", ("encoder.epochs", "decoder.epochs")),
    ),
    "curriculum": (
        Float("lr", "loop.lr", 3e-5, 1e-3, log=True),
        Float("nu_pde", "nu_pde", 0.01, 1.0, log=True),
        Budget("runs", "n_traj"),
        Budget("epochs", "loop.epochs"),
    ),
    **{method: (
        Int("hidden", "hidden", 16, 128, log=True),
        Int("proj", "proj", 4, 32, log=True),
        Layers("gain", "gain_hidden", width=(16, 128), depth=(1, 3)),
        Int("window", "data.window", 10, 100, log=True),
        Float("lr", "loop.lr", 3e-4, 3e-3, log=True),
        Budget("runs", "data.n_traj"),
        Budget("epochs", "loop.epochs"),
    ) for method in ("obs", "obs_stream")},
    **{method: (
        Int("hidden", "hidden", 16, 128, log=True),
        Int("rank", "rank", 1, 8),
        Layers("backbone", "backbone", width=(16, 128), depth=(1, 3)),
        Float("nu_pde", "nu_pde", 0.01, 1.0, log=True),
        Int("window", "data.window", 10, 100, log=True),
        Float("lr", "loop.lr", 3e-4, 3e-3, log=True),
        Budget("runs", "data.n_traj"),
        Budget("epochs", "loop.epochs"),
    ) for method in ("dyn", "dyn_stream")},
}


def field_names(config: Any) -> list[str]:
    return [f.name for f in fields(config)] if is_dataclass(config) else []


def _get(config: Any, path: str) -> Any:
    value = config
    for i, part in enumerate(path.split(".")):
        if part not in field_names(value):
            raise error("space", f"a field {part!r} of {type(value).__name__} for {path!r} (fields: "
                        f"{field_names(value)})", Text(".".join(path.split(".")[:i + 1])),
                        "The configuration class changed: update kklcasadi.evaluation.tune.SPACES.")
        value = getattr(value, part)
    return value


def _set(config: Any, path: str, value: Any) -> Any:
    _get(config, path)
    head, _, rest = path.partition(".")
    return replace(config, **{head: _set(getattr(config, head), rest, value) if rest else value})


@dataclass(frozen=True)
class Space:
    """One method's search space over a base configuration.

    Attributes
    ----------
    method : str
    base : dataclass
        The configuration the dimensions change (the method's default, with the caller's changes).
    dims : tuple
        :class:`Float`, :class:`Int`, :class:`Filters`, :class:`Layers`, :class:`MaybeRate` (budget
        dimensions resolved to :class:`Int` with their caps).
    budget : tuple of str
        Names of the budget dimensions (set to their caps in :meth:`baseline`).
    """

    method: str
    base: Any
    dims: tuple
    budget: tuple

    def __post_init__(self) -> None:
        for dim in self.dims:
            for path in _paths(dim.paths):
                _get(self.base, path)

    def suggest(self, trial: Any) -> Any:
        """The configuration of an Optuna trial (or ``optuna.trial.FixedTrial(params)`` to replay one)."""
        config = self.base
        for dim in self.dims:
            value = dim.suggest(trial)
            for path in _paths(dim.paths):
                config = _set(config, path, value)
        return config

    def baseline(self) -> Any:
        """The base configuration with every budget at its cap: the recipe, at the study's budget."""
        config = self.base
        for dim in self.dims:
            if dim.name in self.budget:
                for path in _paths(dim.paths):
                    config = _set(config, path, dim.high)
        return config

    def describe(self) -> list[dict]:
        """One JSON entry per dimension (for the study and the card)."""
        return [{**dim.describe(), "budget": dim.name in self.budget} for dim in self.dims]


def search_space(method: str, config: Any = None, *, system: str = "", caps: Optional[dict] = None) -> Space:
    """The search space of ``method`` (:data:`SPACES`) over ``config``.

    Parameters
    ----------
    method : str
        A method with an entry in :data:`SPACES`.
    config : dataclass, optional
        The base configuration; default ``kklcasadi.train.default_config(system, method)``.
    system : str
        The plant's name, for the default configuration.
    caps : dict, optional
        Budget caps by dimension name (``{"runs": 500, "epochs": 15}``); default the configuration's
        own values.
    """
    if method not in SPACES:
        raise error("method", f"one of {sorted(SPACES)} (a method with a search space)", method)
    if config is None:
        from ...train import default_config

        config = default_config(system, method)
    caps = dict(caps or {})
    dims, budget = [], []
    for dim in SPACES[method]:
        if isinstance(dim, Budget):
            cap = caps.pop(dim.name, None)
            dim = dim.resolve(_get(config, _paths(dim.paths)[0]) if cap is None else cap)
            budget.append(dim.name)
        dims.append(dim)
    if caps:
        raise error("caps", f"budget names among {budget}", Text(f"unknown {sorted(caps)}"))
    return Space(method, config, tuple(dims), tuple(budget))
