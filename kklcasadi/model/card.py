"""The model card: the typed, validated form of ``card.json`` (:class:`ModelSpec`) and the one way to write one.

A card says what the arrays of ``weights.npz`` mean: the system, the observer design ``(A, B)``, the sample period,
the input-window length, the network architecture, the base model, the noise level and free-form training notes.
:func:`parse_card` checks every field once, the common fields here and the method's architecture by its variant
(:mod:`kklcasadi.model.variants`), which also names the arrays and their shapes; :func:`make_card` is the one way to
write a card. Reading and writing model directories is :mod:`kklcasadi.model.files`; the format is described for
users in ``docs/model-format.md``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping, Optional, Sequence, Union

import numpy as np

from ..nets.specs import field_error
from ..plant.data import LABEL_KINDS, LabelReport
from ..validation import Text, is_int, is_number
from . import variants
from .monitor import MonitorSpec, parse_monitor

if TYPE_CHECKING:
    from ..plant.design import Design
    from ..plant.systems import System

__all__ = ["FORMAT", "FORMAT_VERSION", "CARD_FILE", "ModelSpec", "SystemSpec", "BaseRef", "Domain", "Search",
           "make_card", "parse_card", "model_array_shapes"]

FORMAT = "kklcasadi.model"
FORMAT_VERSION = 1
CARD_FILE = "card.json"

_SHA256 = re.compile(r"^[0-9a-f]{64}$")
_FIX_NEW = "Save the model again with kklcasadi.model.files.save_model."


def _positive_field(value: Any, where: str, field_name: str, fix: str) -> int:
    if not is_int(value) or value < 1:
        raise field_error(where, field_name, "a positive integer", value, fix)
    return int(value)


def _matrix(value: Any, where: str, field_name: str, n_cols: Optional[int], fix: str) -> np.ndarray:
    ok = (isinstance(value, list) and value and all(isinstance(row, list) and row for row in value)
          and all(is_number(v) for row in value for v in row)
          and len({len(row) for row in value}) == 1)
    if not ok:
        raise field_error(where, field_name, "a non-empty list of equal-length lists of numbers",
                     value, fix)
    matrix = np.array(value, dtype=np.float64)
    if not np.all(np.isfinite(matrix)):
        raise field_error(where, field_name, "finite numbers", value, fix)
    if n_cols is not None and matrix.shape[1] != n_cols:
        raise field_error(where, field_name, f"{n_cols} columns", matrix.shape[1], fix)
    return matrix


@dataclass(frozen=True)
class SystemSpec:
    """The plant a model was trained for: its name, sizes and :attr:`kklcasadi.System.fingerprint`
    (None in cards written before fingerprints)."""

    name: str
    nx: int
    nu: int
    ny: int
    fingerprint: Optional[str] = None


@dataclass(frozen=True, eq=False)
class Domain:
    """Where a model's maps were trained: the state box and the latent box of its training data.

    Card entry ``"domain": {"x_lo": [nx], "x_hi": [nx], "z_lo": [nz], "z_hi": [nz]}``; the
    observer's domain monitor (:meth:`kklcasadi.KKLObserver.in_domain`) compares estimates with it.
    """

    x_lo: np.ndarray
    x_hi: np.ndarray
    z_lo: np.ndarray
    z_hi: np.ndarray

    @classmethod
    def of(cls, x: Any, z: Any) -> Domain:
        """The componentwise range of training states ``x`` (M, nx) and their latents ``z`` (M, nz)."""
        x, z = np.asarray(x, dtype=float), np.asarray(z, dtype=float)
        return cls(x.min(0), x.max(0), z.min(0), z.max(0))

    def to_card(self) -> dict:
        """The card entry."""
        return {k: np.asarray(getattr(self, k)).tolist() for k in ("x_lo", "x_hi", "z_lo", "z_hi")}


@dataclass(frozen=True, eq=False)
class Search:
    """The design search a model was chosen by (``kklcasadi tune``): card entry ``"search"``.

    Attributes
    ----------
    study, storage : str
        The Optuna study's name and its storage URL (password hidden).
    trial : int
        The number of the trial whose configuration this model was trained with.
    value : float
        Its validation score (lower is better; ``objective`` says what it is).
    params : dict
        The trial's parameters (Optuna names, JSON values).
    space : list of dict
        The search space: one entry per dimension, each with at least ``name``.
    objective : dict
        What the score is and the validation cells it was measured on.
    baseline : float or None
        The hand-made recipe's score on the same validation cells, where it was measured.
    """

    study: str
    storage: str
    trial: int
    value: float
    params: dict
    space: list
    objective: dict
    baseline: Optional[float] = None

    def to_card(self) -> dict:
        """The card entry."""
        return {"study": self.study, "storage": self.storage, "trial": int(self.trial), "value": float(self.value),
                "params": dict(self.params), "space": [dict(d) for d in self.space],
                "objective": dict(self.objective),
                "baseline": None if self.baseline is None else float(self.baseline)}


@dataclass(frozen=True)
class BaseRef:
    """The model a model was built on: ``path`` relative to the model directory, and its SHA-256."""

    path: str
    weights_sha256: str


@dataclass(frozen=True, eq=False)
class ModelSpec:
    """A parsed, validated card.

    Attributes
    ----------
    method : str
        The card's method (a key of :data:`kklcasadi.model.variants.VARIANTS`).
    system : SystemSpec
    A : numpy.ndarray, shape (nz, nz)
    B : numpy.ndarray, shape (nz, ny)
    dt : float
        Sample period in seconds.
    window : int
        Input-window length in samples.
    architecture
        The variant's typed spec (``to_card()``, ``array_shapes()``).
    base : BaseRef or None
    measurement_std : float
        The noise level the decoder was fit for (0: noise-free).
    domain : Domain or None
        Where the maps were trained (None in cards written before domains were recorded).
    coverage : kklcasadi.plant.data.LabelReport or None
        How the Phase-1 labels were made and how well they cover the X0 box (None for models
        without Phase-1 labels and in cards written before coverage was recorded).
    process_std : float, tuple of float (nx,) or None
        The process-noise level the training data had (one for every state, or one per state),
        where the method uses one (None: not recorded).
    search : Search or None
        The design search the model was chosen by (``kklcasadi tune``), where it was.
    monitor : MonitorSpec or None
        The decoder-input domain monitor (:mod:`kklcasadi.model.monitor`), where the card has one.
    fit_families : dict or None
        The input families the maps were fit on, ``{family: {parameter: (lo, hi)}}``, where the
        card records them.
    """

    method: str
    system: SystemSpec
    A: np.ndarray
    B: np.ndarray
    dt: float
    window: int
    architecture: Any
    base: Optional[BaseRef]
    measurement_std: float
    domain: Optional[Domain] = None
    coverage: Optional[LabelReport] = None
    process_std: Optional[Union[float, tuple]] = None
    search: Optional[Search] = None
    monitor: Optional[MonitorSpec] = None
    fit_families: Optional[dict] = None

    @property
    def variant(self) -> variants.Variant:
        """The method's variant."""
        return variants.get(self.method)

    @property
    def nz(self) -> int:
        """Latent size."""
        return self.A.shape[0]

    def array_shapes(self) -> dict[str, tuple[int, ...]]:
        """Names and shapes of every array of the model file."""
        return {**self.architecture.array_shapes(), **({} if self.monitor is None else self.monitor.array_shapes())}


def parse_card(card: Any, where: str = CARD_FILE, *, require_sha: bool = True) -> ModelSpec:
    """Check a card's fields, their types and the consistency of its sizes; return it typed.

    Parameters
    ----------
    card : Mapping
        The parsed ``card.json``.
    where : str
        Used in error messages (the card's path).
    require_sha : bool
        Whether ``weights_sha256`` must be present (False while saving: it is computed then).

    Returns
    -------
    ModelSpec

    Raises
    ------
    ValueError
        Naming the field, what was expected, what was received and what to do.
    """
    fix_new = _FIX_NEW
    if not isinstance(card, Mapping):
        raise field_error(where, "<card>", "a JSON object", Text(type(card).__name__), fix_new)
    required = ["format", "format_version", "kklcasadi_version", "method", "system", "design",
                "dt", "window", "architecture", "base", "noise", "training"]
    if require_sha:
        required.append("weights_sha256")
    for key in required:
        if key not in card:
            raise field_error(where, key, "a required field", Text("missing"), fix_new)
    if card["format"] != FORMAT:
        raise field_error(where, "format", repr(FORMAT), card["format"],
                          "This is not a kklcasadi model card.")
    if not is_int(card["format_version"]) or card["format_version"] != FORMAT_VERSION:
        raise field_error(where, "format_version", FORMAT_VERSION, card["format_version"],
                          "Read it with the kklcasadi version that wrote it, or save it again.")
    if not isinstance(card["kklcasadi_version"], str):
        raise field_error(where, "kklcasadi_version", "a string", card["kklcasadi_version"], fix_new)
    if card["method"] not in variants.VARIANTS:
        raise field_error(where, "method", f"one of {list(variants.names())}", card["method"],
                          "This kklcasadi version cannot run it; upgrade kklcasadi or save the "
                          "model with a known method.")
    variant = variants.get(card["method"])

    system = card["system"]
    fix_sys = 'Write "system" as {"name": str, "nx": int, "nu": int, "ny": int}.'
    if not isinstance(system, Mapping) or not {"name", "nx", "nu", "ny"} <= set(system):
        raise field_error(where, "system", "an object with name, nx, nu, ny", system, fix_sys)
    if not isinstance(system["name"], str):
        raise field_error(where, "system.name", "a string", system["name"], fix_sys)
    nx, nu, ny = (_positive_field(system[key], where, f"system.{key}", fix_sys)
                  for key in ("nx", "nu", "ny"))
    fingerprint = system.get("fingerprint")
    if fingerprint is not None and (not isinstance(fingerprint, str) or not _SHA256.match(fingerprint)):
        raise field_error(where, "system.fingerprint", "64 lowercase hex digits (kklcasadi.System.fingerprint)",
                          fingerprint, fix_sys)

    design = card["design"]
    fix_design = 'Write "design" as {"A": nz x nz list of lists, "B": nz x ny list of lists}.'
    if not isinstance(design, Mapping) or not {"A", "B"} <= set(design):
        raise field_error(where, "design", "an object with A and B", design, fix_design)
    a = _matrix(design["A"], where, "design.A", None, fix_design)
    if a.shape[0] != a.shape[1]:
        raise field_error(where, "design.A", "a square matrix", Text(f"shape {a.shape}"), fix_design)
    b = _matrix(design["B"], where, "design.B", ny, fix_design)
    if b.shape[0] != a.shape[0]:
        raise field_error(where, "design.B", f"{a.shape[0]} rows (nz, from A)", b.shape[0], fix_design)

    if not is_number(card["dt"]) or not math.isfinite(card["dt"]) or card["dt"] <= 0:
        raise field_error(where, "dt", "a positive number (seconds)", card["dt"], fix_new)
    window = _positive_field(card["window"], where, "window", fix_new)

    arch = card["architecture"]
    if (not isinstance(arch, Mapping) or not set(variant.entries) <= set(arch)
            or not set(arch) <= set(variant.entries) | set(variant.optional_entries)):
        found = sorted(arch) if isinstance(arch, Mapping) else arch
        optional = f" (and optionally {sorted(variant.optional_entries)})" if variant.optional_entries else ""
        raise field_error(where, "architecture", f"an object with exactly the keys "
                          f"{sorted(variant.entries)}{optional} for method {card['method']!r}", found, fix_new)

    base = card["base"]
    if base is not None:
        fix_base = 'Write "base" as null or {"path": "../autonomous", "weights_sha256": "<hex>"}.'
        if (not isinstance(base, Mapping) or set(base) != {"path", "weights_sha256"}
                or not isinstance(base["path"], str)):
            raise field_error(where, "base", "null or an object with path and weights_sha256", base,
                              fix_base)
        if not isinstance(base["weights_sha256"], str) or not _SHA256.match(base["weights_sha256"]):
            raise field_error(where, "base.weights_sha256", "64 lowercase hex digits",
                              base["weights_sha256"], fix_base)
        base = BaseRef(base["path"], base["weights_sha256"])

    noise = card["noise"]
    fix_noise = 'Write "noise" as {"measurement_std": 0.0} or {"measurement_std": 0.1, "process_std": 0.1}.'
    if (not isinstance(noise, Mapping) or "measurement_std" not in noise
            or not is_number(noise["measurement_std"])
            or not math.isfinite(noise["measurement_std"]) or noise["measurement_std"] < 0):
        raise field_error(where, "noise.measurement_std", "a number >= 0", noise, fix_noise)
    if not set(noise) <= {"measurement_std", "process_std"}:
        raise field_error(where, "noise", "the keys measurement_std and optionally process_std", sorted(noise),
                          fix_noise)
    process_std = noise.get("process_std")
    level = lambda v: is_number(v) and math.isfinite(v) and v >= 0  # noqa: E731
    if process_std is not None and not (level(process_std) or (
            isinstance(process_std, list) and len(process_std) == nx and all(map(level, process_std)))):
        raise field_error(where, "noise.process_std", f"a number >= 0 or a list of nx = {nx} of them",
                          process_std, fix_noise)
    if not isinstance(card["training"], Mapping):
        raise field_error(where, "training", "an object", card["training"],
                          "Use {} if there is nothing to record.")
    if require_sha and (not isinstance(card["weights_sha256"], str)
                        or not _SHA256.match(card["weights_sha256"])):
        raise field_error(where, "weights_sha256", "64 lowercase hex digits", card["weights_sha256"],
                          fix_new)
    for name in (set(card) & _VARIANT_FIELDS) - set(variant.card_fields):
        owners = [v.name for v in variants.VARIANTS.values() if name in v.card_fields]
        raise field_error(where, name, f"no such field for method {card['method']!r} (only "
                          f"{', '.join(map(repr, owners))} take it)", card[name],
                          "Remove the field, or use a method that takes it.")
    spec = variant.parse(card, variants.Sizes(nx, nu, ny, a.shape[0]), where)
    domain = _domain(card.get("domain"), nx, a.shape[0], where)
    coverage = _coverage(card.get("coverage"), nx, where)
    search = _search(card.get("search"), where)
    monitor = parse_monitor(card.get("monitor"), where)
    families = _fit_families(card.get("fit_families"), where)
    for matrix in (a, b):
        matrix.setflags(write=False)
    return ModelSpec(card["method"], SystemSpec(system["name"], nx, nu, ny, fingerprint), a, b, float(card["dt"]),
                     window, spec, base, float(noise["measurement_std"]), domain, coverage,
                     _levels(process_std), search, monitor, families)


_COVERAGE_KEYS = ("labels", "runs", "escaped", "burn_in", "per_state", "grid", "cells_per_axis")


def _coverage(entry: Any, nx: int, where: str) -> Optional[LabelReport]:
    if entry is None:
        return None
    fix = ('Write "coverage" as {"labels": kind, "runs": int, "escaped": int, "burn_in": seconds, '
           '"per_state": [nx shares], "grid": share, "cells_per_axis": int} (shares in [0, 1]), or remove it.')
    if not isinstance(entry, Mapping) or set(entry) != set(_COVERAGE_KEYS):
        raise field_error(where, "coverage", f"an object with exactly the keys {list(_COVERAGE_KEYS)}", entry, fix)
    kinds = [k for k in LABEL_KINDS if k != "auto"]
    if entry["labels"] not in kinds:
        raise field_error(where, "coverage.labels", f"one of {kinds}", entry["labels"], fix)
    for key, lowest in (("runs", 1), ("escaped", 0), ("cells_per_axis", 1)):
        if not is_int(entry[key]) or entry[key] < lowest:
            raise field_error(where, f"coverage.{key}", f"an integer >= {lowest}", entry[key], fix)
    if entry["escaped"] > entry["runs"]:
        raise field_error(where, "coverage.escaped", f"at most runs = {entry['runs']}", entry["escaped"], fix)
    if not (is_number(entry["burn_in"]) and math.isfinite(entry["burn_in"]) and entry["burn_in"] >= 0):
        raise field_error(where, "coverage.burn_in", "a number of seconds >= 0", entry["burn_in"], fix)
    share = lambda v: is_number(v) and 0 <= v <= 1  # noqa: E731
    per_state = entry["per_state"]
    if not (isinstance(per_state, list) and len(per_state) == nx and all(share(v) for v in per_state)):
        raise field_error(where, "coverage.per_state", f"a list of {nx} numbers in [0, 1]", per_state, fix)
    if not share(entry["grid"]):
        raise field_error(where, "coverage.grid", "a number in [0, 1]", entry["grid"], fix)
    return LabelReport(entry["labels"], int(entry["runs"]), int(entry["escaped"]), float(entry["burn_in"]),
                       tuple(float(v) for v in per_state), float(entry["grid"]), int(entry["cells_per_axis"]))


def _finite(value: Any) -> bool:
    return is_number(value) and math.isfinite(value)


def _search(entry: Any, where: str) -> Optional[Search]:
    if entry is None:
        return None
    keys = ("study", "storage", "trial", "value", "params", "space", "objective", "baseline")
    fix = ('Write "search" as {"study": str, "storage": str, "trial": int >= 0, "value": number, "params": {...}, '
           '"space": [{"name": str, ...}, ...], "objective": {...}, "baseline": number or null} (kklcasadi tune '
           'writes it), or remove it.')
    if not isinstance(entry, Mapping) or set(entry) != set(keys):
        found = sorted(entry) if isinstance(entry, Mapping) else entry
        raise field_error(where, "search", f"an object with exactly the keys {list(keys)}", found, fix)
    for key in ("study", "storage"):
        if not isinstance(entry[key], str) or (key == "study" and not entry[key]):
            raise field_error(where, f"search.{key}", "a non-empty string" if key == "study" else "a string",
                              entry[key], fix)
    if not is_int(entry["trial"]) or entry["trial"] < 0:
        raise field_error(where, "search.trial", "an integer >= 0 (the Optuna trial number)", entry["trial"], fix)
    if not _finite(entry["value"]):
        raise field_error(where, "search.value", "a finite number", entry["value"], fix)
    if entry["baseline"] is not None and not _finite(entry["baseline"]):
        raise field_error(where, "search.baseline", "null or a finite number", entry["baseline"], fix)
    params = entry["params"]
    if not isinstance(params, Mapping) or not all(
            value is None or isinstance(value, (str, bool)) or _finite(value) for value in params.values()):
        raise field_error(where, "search.params", "an object of finite numbers, strings, booleans or nulls",
                          params, fix)
    space = entry["space"]
    if (not isinstance(space, list) or not space
            or not all(isinstance(d, Mapping) and isinstance(d.get("name"), str) for d in space)):
        raise field_error(where, "search.space", "a non-empty list of objects, each with a string 'name'", space, fix)
    if not isinstance(entry["objective"], Mapping):
        raise field_error(where, "search.objective", "an object", entry["objective"], fix)
    return Search(entry["study"], entry["storage"], int(entry["trial"]), float(entry["value"]), dict(params),
                  [dict(d) for d in space], dict(entry["objective"]),
                  None if entry["baseline"] is None else float(entry["baseline"]))


def _levels(value: Any) -> float | tuple[float, ...] | None:
    """A card's process-noise level as the spec keeps it: a float, a tuple per state, or None."""
    if value is None:
        return None
    return float(value) if np.ndim(value) == 0 else tuple(float(v) for v in value)


def _card_levels(value: Any) -> float | list[float]:
    return float(value) if np.ndim(value) == 0 else [float(v) for v in value]


def _fit_families(entry: Any, where: str) -> Optional[dict]:
    """The card's ``fit_families``: ``{family: {parameter: [lo, hi]}}`` (lo <= hi, finite), or None."""
    if entry is None:
        return None
    fix = ('Write "fit_families" as {"constant": {"value": [-1.0, 1.0]}, "zero": {}, ...}: each input family the '
           'maps were fit on with the range of each of its parameters (kklcasadi.plant.signals.family_ranges).')
    if not isinstance(entry, Mapping) or not entry:
        raise field_error(where, "fit_families", "a non-empty object of families", entry, fix)
    out = {}
    for family, ranges in entry.items():
        if not isinstance(ranges, Mapping):
            raise field_error(where, f"fit_families.{family}", "an object of parameter ranges", ranges, fix)
        out[family] = {}
        for name, bounds in ranges.items():
            ok = (isinstance(bounds, list) and len(bounds) == 2
                  and all(is_number(v) and math.isfinite(v) for v in bounds) and bounds[0] <= bounds[1])
            if not ok:
                raise field_error(where, f"fit_families.{family}.{name}",
                                  "a range [lo, hi] of finite numbers, lo <= hi", bounds, fix)
            out[family][name] = (float(bounds[0]), float(bounds[1]))
    return out


def _domain(entry: Any, nx: int, nz: int, where: str) -> Optional[Domain]:
    if entry is None:
        return None
    fix = 'Write "domain" as {"x_lo": [nx], "x_hi": [nx], "z_lo": [nz], "z_hi": [nz]} (lo <= hi), or remove it.'
    keys = ("x_lo", "x_hi", "z_lo", "z_hi")
    if not isinstance(entry, Mapping) or set(entry) != set(keys):
        raise field_error(where, "domain", f"an object with exactly the keys {list(keys)}", entry, fix)
    arrays = {}
    for key, n in zip(keys, (nx, nx, nz, nz)):
        value = entry[key]
        if (not isinstance(value, list) or len(value) != n or not all(is_number(v) for v in value)
                or not all(math.isfinite(v) for v in value)):
            raise field_error(where, f"domain.{key}", f"a list of {n} finite numbers", value, fix)
        arrays[key] = np.array(value, dtype=float)
        arrays[key].setflags(write=False)
    if np.any(arrays["x_lo"] > arrays["x_hi"]) or np.any(arrays["z_lo"] > arrays["z_hi"]):
        raise field_error(where, "domain", "lo <= hi componentwise", entry, fix)
    return Domain(**arrays)


#: Top-level card fields some variant reads (another method's card must not carry them).
_VARIANT_FIELDS = frozenset(name for v in variants.VARIANTS.values() for name in v.card_fields)


def model_array_shapes(card: Mapping[str, Any], where: str = CARD_FILE) -> dict[str, tuple[int, ...]]:
    """All array names and shapes a card needs (validated first; format fields and SHA-256 optional)."""
    if not isinstance(card, Mapping):
        raise field_error(where, "<card>", "a JSON object", Text(type(card).__name__), _FIX_NEW)
    filled = {"format": FORMAT, "format_version": FORMAT_VERSION, "kklcasadi_version": "", **card}
    return parse_card(filled, where, require_sha=False).array_shapes()


def make_card(system: System | SystemSpec, design: Design, method: str, spec: Any, *, dt: float,
              window: int = 1, training: Optional[Mapping[str, Any]] = None,
              base: Optional[Mapping[str, str]] = None, measurement_std: float = 0.0,
              domain: Optional[Domain] = None, coverage: Optional[LabelReport] = None,
              process_std: Optional[Union[float, Sequence[float]]] = None, search: Optional[Search] = None,
              monitor: Optional[MonitorSpec] = None,
              fit_families: Optional[Mapping[str, Mapping[str, Any]]] = None) -> dict:
    """The card of a model: the one way training, :func:`derive_model` and tests write one.

    Parameters
    ----------
    system : System or SystemSpec
        The plant (its name and sizes are recorded).
    design : Design
        The latent pair ``(A, B)``.
    method : str
        A key of :data:`kklcasadi.model.variants.VARIANTS`.
    spec
        The variant's typed architecture spec: its ``to_card()`` gives the architecture entries and
        the variant's ``card_entries(spec)`` the extra top-level fields.
    dt : float
        Sample period in seconds.
    window : int
        Input-window length in samples (1 for variants that do not read the window).
    training : Mapping, optional
        Free-form training record (JSON-serialisable; numpy values are converted on save).
    base : Mapping, optional
        ``{"path": relative path, "weights_sha256": hex}`` of the model this one was built on.
    measurement_std : float
        The noise level the decoder was fit for.
    domain : Domain, optional
        Where the maps were trained (recorded for the observer's domain monitor).
    coverage : kklcasadi.plant.data.LabelReport, optional
        How the Phase-1 labels were made and how well they cover the box.
    process_std : float or sequence of float (nx,), optional
        The process-noise level of the training data (one per state, or one for all), where the
        method uses one.
    search : Search, optional
        The design search the model was chosen by (``kklcasadi tune``).
    monitor : MonitorSpec, optional
        The decoder-input monitor's card entry (its arrays go into the model's arrays).
    fit_families : Mapping, optional
        The input families the maps were fit on, ``{family: {parameter: (lo, hi)}}``.

    Returns
    -------
    dict
        Ready for :func:`save_model` (which adds the format fields and the SHA-256).
    """
    variant = variants.get(method)
    plant = {"name": system.name, "nx": system.nx, "nu": system.nu, "ny": system.ny}
    if system.fingerprint is not None:
        plant["fingerprint"] = system.fingerprint
    return {"method": method, "system": plant,
            "design": {"A": np.asarray(design.A).tolist(), "B": np.asarray(design.B).tolist()},
            "dt": float(dt), "window": int(window), "architecture": spec.to_card(),
            "base": None if base is None else dict(base),
            "noise": {"measurement_std": float(measurement_std),
                      **({} if process_std is None else {"process_std": _card_levels(process_std)})},
            "training": dict(training or {}), **variant.card_entries(spec),
            **({} if domain is None else {"domain": domain.to_card()}),
            **({} if coverage is None else {"coverage": coverage.to_card()}),
            **({} if search is None else {"search": search.to_card()}),
            **({} if monitor is None else {"monitor": monitor.to_card()}),
            **({} if fit_families is None else {"fit_families": {k: {p: list(b) for p, b in v.items()}
                                                                 for k, v in fit_families.items()}})}
