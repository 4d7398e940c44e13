"""On-disk cache of the protocol's simulated plant trials (one ``.npz`` per cell).

The trials of a docs/protocol.md cell ``(system, input regime, noise)`` are seeded and deterministic,
so they are simulated once and reused by every method and every later run. A cell file holds the
arrays of a :class:`~kklcasadi.plant.simulate.TrajectoryBatch` (``t``, ``x``, ``u``, ``y``, ``ok``) as a
plain ``.npz`` (read with ``allow_pickle=False``), the JSON description of what it was simulated
from, and a SHA-256 digest of the arrays.

A cell is anything with ``describe() -> dict`` (a plain JSON description of what its trials are
simulated from), ``label`` (a file-name part), ``shape() -> (trials, samples)`` and
``simulate(system) -> TrajectoryBatch``: the
protocol's cells (:meth:`kklcasadi.evaluation.protocol.Protocol.cell`) are. The key of a cell
hashes:

- the system: its name and :attr:`~kklcasadi.plant.systems.System.definition_digest` (sizes, X0
  box and the serialised CasADi Functions ``f`` and ``h``);
- the cell's description (for the protocol: every field of the protocol and the input regime);
- the versions of kklcasadi, CasADi, NumPy and SciPy (integrator, random streams, Latin
  hypercube).

Every cell read or simulated is also kept in memory, so the methods of one run share its arrays;
``TrialCache(None)`` keeps cells in memory only.

A file that cannot be read, whose digest does not match its arrays, or whose description is not
the one asked for, is reported (:class:`TrialCacheWarning`) and simulated again; it is never used.
Writes go to a temporary file in the cache directory, then ``os.replace`` it into place.

The default directory is ``$KKLCASADI_CACHE/trials``, else ``$XDG_CACHE_HOME/kklcasadi/trials``,
else ``~/.cache/kklcasadi/trials``.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import typing
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import casadi as ca
import numpy as np
import scipy

from ..plant.simulate import TrajectoryBatch
from ..plant.systems import System
from ..version import __version__

__all__ = ["TrialCache", "TrialCacheWarning", "Cell", "cache_root", "cell_description", "CACHE_ENV", "CACHE_FORMAT"]

#: Environment variable naming the root of kklcasadi's caches (trials and compiled code).
CACHE_ENV = "KKLCASADI_CACHE"
#: Version of the cell file layout; part of every key.
CACHE_FORMAT = 1

_ARRAYS = ("t", "x", "u", "y", "ok")

PathLike = Union[str, os.PathLike]


class TrialCacheWarning(UserWarning):
    """A cached cell was unreadable or did not match its key; it is simulated again."""


def cache_root() -> Path:
    """The root of kklcasadi's on-disk caches.

    Returns
    -------
    Path
        ``$KKLCASADI_CACHE`` if set, else ``$XDG_CACHE_HOME/kklcasadi``, else
        ``~/.cache/kklcasadi``. Not created here.
    """
    explicit = os.environ.get(CACHE_ENV)
    if explicit:
        return Path(explicit).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "kklcasadi"


class Cell(typing.Protocol):
    """What the cache needs of a cell (a protocol's cell is one)."""

    label: str

    def describe(self) -> dict:
        """What the trials are simulated from, as plain JSON values."""

    def shape(self) -> tuple[int, int]:
        """Trials and samples per trial."""

    def simulate(self, system: System) -> TrajectoryBatch:
        """Simulate the cell's trials."""


def cell_description(system: System, cell: Cell) -> dict:
    """What a cell's trials are simulated from (the material of its key), as plain JSON values.

    Parameters
    ----------
    system : System
    cell : Cell

    Returns
    -------
    dict
        Format, package versions, the system's name and definition digest, and the cell's own
        description (for the protocol: ``{"protocol": {...its fields}, "kind": ...}``).
    """
    if not isinstance(system, System):
        raise TypeError(f"system: expected a kklcasadi.System, received {type(system).__name__}.")
    description = cell.describe()
    if not isinstance(description, dict):
        raise TypeError(f"cell: expected describe() to return a dict, received {type(description).__name__}.")
    return {"format": CACHE_FORMAT,
            "versions": {"kklcasadi": __version__, "casadi": ca.__version__, "numpy": np.__version__,
                         "scipy": scipy.__version__},
            "system": {"name": system.name, "fingerprint": system.definition_digest},
            **({} if system.u_box is None else {"inputs": "mapped onto the plant's u_box"}),
            **description}


def _digest(arrays: dict) -> str:
    digest = hashlib.sha256()
    for name in _ARRAYS:
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}:{array.dtype.str}:{array.shape};".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


@dataclass(frozen=True)
class TrialCache:
    """Simulated cells, kept in memory and (with a directory) one ``.npz`` file per cell on disk.

    Parameters
    ----------
    directory : Path or None
        Where the cell files live (created on the first write); None keeps cells in memory only.

    Examples
    --------
    >>> cache = TrialCache.default()                          # doctest: +SKIP
    >>> batch = cache.trials(kc.systems.get("duffing"), Protocol().cell("square"))   # doctest: +SKIP
    """

    directory: Optional[Path]
    _memory: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.directory is None:
            return
        if not isinstance(self.directory, (str, os.PathLike)):
            raise TypeError(f"directory: expected a path or None, received {type(self.directory).__name__}.")
        object.__setattr__(self, "directory", Path(self.directory).expanduser())

    @classmethod
    def default(cls) -> TrialCache:
        """The cache under :func:`cache_root`: ``<root>/trials``."""
        return cls(cache_root() / "trials")

    def key(self, system: System, cell: Cell) -> str:
        """SHA-256 (64 hex digits) of :func:`cell_description`."""
        text = json.dumps(cell_description(system, cell), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()

    def path(self, system: System, cell: Cell) -> Path:
        """The cell's file: ``<directory>/<system>-<cell label>-<key[:16]>.npz``."""
        if self.directory is None:
            raise ValueError("directory: expected a cache directory, received None (an in-memory cache has "
                             "no files).")
        return self.directory / f"{system.name}-{cell.label}-{self.key(system, cell)[:16]}.npz"

    def load(self, system: System, cell: Cell) -> TrajectoryBatch | None:
        """The cached cell from disk, or None if absent or not usable (then a :class:`TrialCacheWarning`).

        Returns
        -------
        TrajectoryBatch or None
            Read-only arrays ``t`` (N,), ``x`` (M, N, nx), ``u`` (M, N, nu), ``y`` (M, N, ny),
            ``ok`` (M,).
        """
        path = self.path(system, cell)
        if not path.exists():
            return None
        expected = cell_description(system, cell)
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {name: data[name] for name in _ARRAYS}
                description = json.loads(str(data["description"]))
                digest = str(data["digest"])
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as err:
            return self._reject(path, f"unreadable ({type(err).__name__}: {err})")
        if description != expected:
            return self._reject(path, "it was simulated for another system, protocol, regime or "
                                      "package version than its name says")
        if _digest(arrays) != digest:
            return self._reject(path, "its arrays do not match their SHA-256 digest")
        problem = _shape_problem(arrays, system, cell.shape())
        if problem:
            return self._reject(path, problem)
        for array in arrays.values():
            array.setflags(write=False)
        return TrajectoryBatch(arrays["t"], arrays["x"], arrays["u"], arrays["y"], arrays["ok"])

    def store(self, system: System, cell: Cell, batch: TrajectoryBatch) -> Path:
        """Write a simulated cell atomically (temporary file, then ``os.replace``).

        Returns
        -------
        Path
            The cell's file.
        """
        if not isinstance(batch, TrajectoryBatch):
            raise TypeError(f"batch: expected a kklcasadi.TrajectoryBatch, received {type(batch).__name__}.")
        arrays = {"t": np.asarray(batch.t, dtype=float), "x": np.asarray(batch.x, dtype=float),
                  "u": np.asarray(batch.u, dtype=float), "y": np.asarray(batch.y, dtype=float),
                  "ok": np.asarray(batch.ok, dtype=bool)}
        problem = _shape_problem(arrays, system, cell.shape())
        if problem:
            raise ValueError(f"batch: does not fit the cell ({problem}).")
        path = self.path(system, cell)
        path.parent.mkdir(parents=True, exist_ok=True)
        description = json.dumps(cell_description(system, cell), sort_keys=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}-", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as handle:
                np.savez(handle, description=np.array(description), digest=np.array(_digest(arrays)),
                         **arrays)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    def trials(self, system: System, cell: Cell) -> TrajectoryBatch:
        """The cell's trials: from memory, else from disk, else simulated (``cell.simulate``) and stored.

        Returns
        -------
        TrajectoryBatch
            Bitwise the batch ``cell.simulate(system)`` returns.
        """
        key = self.key(system, cell)
        batch = self._memory.get(key)
        if batch is None:
            batch = None if self.directory is None else self.load(system, cell)
            if batch is None:
                batch = cell.simulate(system)
                if self.directory is not None:
                    self.store(system, cell, batch)
            self._memory[key] = batch
        return batch

    @staticmethod
    def _reject(path: Path, why: str) -> None:
        warnings.warn(f"trial cache: ignoring {path}: {why}; simulating the cell again.", TrialCacheWarning,
                      stacklevel=3)
        return None


def _shape_problem(arrays: dict, system: System, shape: tuple[int, int]) -> str:
    """An empty string if the arrays fit the cell (``shape``: trials, samples), else what is wrong with them."""
    t, x, u, y, ok = (arrays[name] for name in _ARRAYS)
    m, n = shape
    expected = {"t": (n,), "x": (m, n, system.nx), "u": (m, n, system.nu), "y": (m, n, system.ny), "ok": (m,)}
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            return f"{name} has shape {arrays[name].shape}, expected {shape}"
    for name, array in (("t", t), ("x", x), ("u", u), ("y", y)):
        if array.dtype != np.float64:
            return f"{name} has dtype {array.dtype}, expected float64"
    if ok.dtype != np.bool_:
        return f"ok has dtype {ok.dtype}, expected bool"
    return ""
