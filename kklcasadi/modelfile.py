"""Model files: ``weights.npz`` + ``card.json``, read and written without torch.

A model directory holds two files:

``weights.npz``
    Plain float64 arrays (no pickles), named ``<prefix>/<array>``, e.g. ``decoder/W0``.
``card.json``
    What the arrays mean: the system, the observer design ``(A, B)``, the sample period, the
    input-window length, the network architecture, the base model, the noise level and free-form
    training notes, plus the SHA-256 of the weights file.

The array names and shapes follow from the architecture entries of the card; this module is the
single place that derives them (:class:`MLPSpec`, :class:`ObsSpec`, :class:`HyperSpec`,
:func:`model_array_shapes`), so that the torch networks, the exporters and the loader agree. The
format is described for users in ``docs/model-format.md``.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np

FORMAT = "kklcasadi.model"
FORMAT_VERSION = 1
WEIGHTS_FILE = "weights.npz"
CARD_FILE = "card.json"
METHODS = ("autonomous", "curriculum", "obs", "dyn", "inject")
ACTIVATIONS = ("tanh", "relu", "softplus", "identity")

ENCODER = "encoder"
DECODER = "decoder"
OBS_GRU = "context/gru"
OBS_PROJ = "context/proj/W"
OBS_GAIN = "gain"
HYPER = "hyper"
HYPER_BACKBONE_ACTIVATION = "tanh"

_METHOD_ENTRIES = {
    "autonomous": (ENCODER, DECODER),
    "curriculum": (ENCODER, DECODER),
    "inject": (ENCODER, DECODER),
    "obs": (ENCODER, DECODER, "context", "gain"),
    "dyn": (ENCODER, DECODER, "hyper"),
}
_SHA256 = re.compile(r"^[0-9a-f]{64}$")


class _Text(str):
    """A description of what was found, shown without quotes in error messages."""

    def __repr__(self) -> str:
        return str(self)


def _error(where: str, field_name: str, expected: str, found: Any, fix: str) -> ValueError:
    """Build the one error message style of this module.

    Parameters
    ----------
    where : str
        The file or object the problem is in.
    field_name : str
        The field (dotted path) or array name.
    expected, found
        What was expected and what was found (``found`` is shown with ``repr``, so that
        ``"100"`` and ``100`` differ; wrap descriptions in ``_Text``).
    fix : str
        What the user should do about it.
    """
    return ValueError(f"{where}: '{field_name}': expected {expected}, found {found!r}. {fix}")


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_number(value: Any) -> bool:
    return (_is_int(value) or isinstance(value, (float, np.floating))) and not isinstance(
        value, (bool, np.bool_)
    )


def _positive_int(value: Any, where: str, field_name: str, fix: str) -> int:
    if not _is_int(value) or value < 1:
        raise _error(where, field_name, "a positive integer", value, fix)
    return int(value)


def check_activation(name: Any) -> str:
    """Return ``name`` if it is a known activation, else raise.

    Parameters
    ----------
    name : str
        One of :data:`ACTIVATIONS`.

    Raises
    ------
    ValueError
        If ``name`` is not one of :data:`ACTIVATIONS` (the message lists them).
    """
    if name not in ACTIVATIONS:
        raise ValueError(
            f"activation: unknown activation {name!r}; known activations are "
            f"{', '.join(ACTIVATIONS)}."
        )
    return name


@dataclass(frozen=True)
class MLPSpec:
    """Architecture of one MLP: layer sizes ``[d0, ..., dL]`` and the hidden activation.

    The card entry is ``{"sizes": [d0, ..., dL], "activation": "tanh"}``. The arrays under a
    prefix ``P`` are ``P/in_mean`` (d0,), ``P/in_std`` (d0,), ``P/out_mean`` (dL,),
    ``P/out_std`` (dL,), and for ``i = 0..L-1``: ``P/W{i}`` (d_{i+1}, d_i), ``P/b{i}``
    (d_{i+1},).
    """

    sizes: tuple[int, ...]
    activation: str = "tanh"

    def __post_init__(self) -> None:
        sizes = tuple(self.sizes)
        if len(sizes) < 2 or not all(_is_int(d) and d >= 1 for d in sizes):
            raise _error(
                "MLP architecture", "sizes", "at least two positive integers [d_in, ..., d_out]",
                self.sizes, "Give the layer widths, input first.",
            )
        object.__setattr__(self, "sizes", tuple(int(d) for d in sizes))
        check_activation(self.activation)

    @classmethod
    def from_card(cls, entry: Any, where: str = "architecture",
                  field_name: str = "mlp") -> "MLPSpec":
        """Parse a card entry ``{"sizes": [...], "activation": ...}``.

        Parameters
        ----------
        entry : Mapping
            The card entry.
        where, field_name : str
            Used in error messages (the file and the dotted field name).
        """
        fix = 'Write the entry as {"sizes": [d_in, ..., d_out], "activation": "tanh"}.'
        if not isinstance(entry, Mapping):
            raise _error(where, field_name, "an object with 'sizes' and 'activation'", entry, fix)
        if set(entry) != {"sizes", "activation"}:
            raise _error(where, field_name, "exactly the keys ['activation', 'sizes']",
                         sorted(entry), fix)
        sizes = entry["sizes"]
        if (not isinstance(sizes, (list, tuple)) or len(sizes) < 2
                or not all(_is_int(d) and d >= 1 for d in sizes)):
            raise _error(where, f"{field_name}.sizes", "a list of at least two positive integers",
                         sizes, fix)
        if entry["activation"] not in ACTIVATIONS:
            raise _error(where, f"{field_name}.activation", f"one of {list(ACTIVATIONS)}",
                         entry["activation"], fix)
        return cls(tuple(sizes), entry["activation"])

    def to_card(self) -> dict:
        """The card entry of this architecture."""
        return {"sizes": list(self.sizes), "activation": self.activation}

    @property
    def n_in(self) -> int:
        """Input size d0."""
        return self.sizes[0]

    @property
    def n_out(self) -> int:
        """Output size dL."""
        return self.sizes[-1]

    @property
    def layer_shapes(self) -> tuple[tuple[int, int], ...]:
        """Weight shapes ``(d_{i+1}, d_i)`` of the layers, first layer first."""
        return tuple(zip(self.sizes[1:], self.sizes[:-1]))

    def array_shapes(self, prefix: str) -> dict[str, tuple[int, ...]]:
        """Names and shapes of the arrays of this MLP under ``prefix``."""
        shapes = {
            f"{prefix}/in_mean": (self.n_in,),
            f"{prefix}/in_std": (self.n_in,),
            f"{prefix}/out_mean": (self.n_out,),
            f"{prefix}/out_std": (self.n_out,),
        }
        for i, (d_out, d_in) in enumerate(self.layer_shapes):
            shapes[f"{prefix}/W{i}"] = (d_out, d_in)
            shapes[f"{prefix}/b{i}"] = (d_out,)
        return shapes


def gru_array_shapes(prefix: str, nu: int, hidden: int) -> dict[str, tuple[int, ...]]:
    """Names and shapes of a bias-free GRU's arrays: ``P/W_ih`` (3H, nu), ``P/W_hh`` (3H, H)."""
    return {f"{prefix}/W_ih": (3 * hidden, nu), f"{prefix}/W_hh": (3 * hidden, hidden)}


@dataclass(frozen=True)
class ObsSpec:
    """Architecture of the HyperKKL_obs injection.

    Card entries: ``"context": {"hidden": H, "proj": n_l}`` and ``"gain": {mlp}`` with gain
    sizes ``[nz + n_l, ..., nz*nu]``; ``nz`` and ``nu`` follow from the gain sizes.
    """

    hidden: int
    proj: int
    gain: MLPSpec

    def __post_init__(self) -> None:
        where = "obs architecture"
        _positive_int(self.hidden, where, "context.hidden", "Give the GRU width.")
        _positive_int(self.proj, where, "context.proj", "Give the projection width.")
        if self.gain.n_in <= self.proj:
            raise _error(where, "gain.sizes[0]", f"nz + proj > proj = {self.proj}",
                         self.gain.n_in, "The gain MLP takes [z; l] as input.")
        if self.gain.n_out % self.nz:
            raise _error(where, "gain.sizes[-1]", f"a multiple of nz = {self.nz} (nz*nu)",
                         self.gain.n_out, "The gain MLP outputs G(z, l) (nz, nu) row-major.")

    @classmethod
    def from_card(cls, architecture: Any, where: str = "architecture") -> "ObsSpec":
        """Parse the ``context`` and ``gain`` entries of an architecture mapping."""
        fix = 'Write "context" as {"hidden": H, "proj": n_l}.'
        if not isinstance(architecture, Mapping):
            raise _error(where, "architecture", "an object", architecture, fix)
        context = architecture.get("context")
        if not isinstance(context, Mapping) or set(context) != {"hidden", "proj"}:
            raise _error(where, "context", "an object with keys ['hidden', 'proj']", context, fix)
        hidden = _positive_int(context["hidden"], where, "context.hidden", fix)
        proj = _positive_int(context["proj"], where, "context.proj", fix)
        gain = MLPSpec.from_card(architecture.get("gain"), where, "gain")
        try:
            return cls(hidden, proj, gain)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc

    def to_card(self) -> dict:
        """The ``context`` and ``gain`` card entries."""
        return {"context": {"hidden": self.hidden, "proj": self.proj}, "gain": self.gain.to_card()}

    @property
    def nz(self) -> int:
        """Latent size, ``gain.sizes[0] - proj``."""
        return self.gain.n_in - self.proj

    @property
    def nu(self) -> int:
        """Input size, ``gain.sizes[-1] / nz``."""
        return self.gain.n_out // self.nz

    def array_shapes(self, prefix: str = "") -> dict[str, tuple[int, ...]]:
        """Names and shapes of the injection's arrays (``prefix`` empty in model files)."""
        shapes = gru_array_shapes(array_name(prefix, OBS_GRU), self.nu, self.hidden)
        shapes[array_name(prefix, OBS_PROJ)] = (self.proj, self.hidden)
        shapes.update(self.gain.array_shapes(array_name(prefix, OBS_GAIN)))
        return shapes


@dataclass(frozen=True)
class HyperSpec:
    """Architecture of the HyperKKL_dyn LoRA hypernetwork.

    Card entry ``"hyper": {"hidden": H, "embed": E, "backbone": [64, 64], "rank": r}``. The
    backbone MLP has sizes ``[H + E, *backbone]`` and tanh activation.
    """

    hidden: int
    embed: int
    backbone: tuple[int, ...]
    rank: int

    def __post_init__(self) -> None:
        where, fix = "hyper architecture", "Give positive integers."
        _positive_int(self.hidden, where, "hyper.hidden", fix)
        _positive_int(self.embed, where, "hyper.embed", fix)
        _positive_int(self.rank, where, "hyper.rank", fix)
        backbone = tuple(self.backbone)
        if not backbone or not all(_is_int(d) and d >= 1 for d in backbone):
            raise _error(where, "hyper.backbone", "a non-empty list of positive integers",
                         self.backbone, fix)
        object.__setattr__(self, "backbone", tuple(int(d) for d in backbone))

    @classmethod
    def from_card(cls, architecture: Any, where: str = "architecture") -> "HyperSpec":
        """Parse the ``hyper`` entry of an architecture mapping."""
        fix = 'Write "hyper" as {"hidden": H, "embed": E, "backbone": [64, 64], "rank": r}.'
        if not isinstance(architecture, Mapping):
            raise _error(where, "architecture", "an object", architecture, fix)
        entry = architecture.get("hyper")
        keys = {"hidden", "embed", "backbone", "rank"}
        if not isinstance(entry, Mapping) or set(entry) != keys:
            raise _error(where, "hyper", f"an object with keys {sorted(keys)}", entry, fix)
        backbone = entry["backbone"]
        if not isinstance(backbone, (list, tuple)):
            raise _error(where, "hyper.backbone", "a list of positive integers", backbone, fix)
        try:
            return cls(entry["hidden"], entry["embed"], tuple(backbone), entry["rank"])
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc

    def to_card(self) -> dict:
        """The ``hyper`` card entry."""
        return {"hyper": {"hidden": self.hidden, "embed": self.embed,
                          "backbone": list(self.backbone), "rank": self.rank}}

    @property
    def backbone_spec(self) -> MLPSpec:
        """The backbone MLP, sizes ``[H + E, *backbone]``, tanh."""
        return MLPSpec((self.hidden + self.embed, *self.backbone), HYPER_BACKBONE_ACTIVATION)

    def array_shapes(self, prefix: str, nu: int,
                     target_shapes: Sequence[tuple[int, int]]) -> dict[str, tuple[int, ...]]:
        """Names and shapes of the hypernetwork's arrays.

        Parameters
        ----------
        prefix : str
            ``"hyper"`` in model files.
        nu : int
            Input size (the GRU's input).
        target_shapes : sequence of (d_out, d_in)
            The modulated layers, see :func:`lora_target_shapes`.
        """
        shapes = gru_array_shapes(f"{prefix}/gru", nu, self.hidden)
        shapes[f"{prefix}/embed"] = (len(target_shapes), self.embed)
        shapes.update(self.backbone_spec.array_shapes(f"{prefix}/backbone"))
        n_features = self.backbone[-1]
        for j, (d_out, d_in) in enumerate(target_shapes):
            shapes[f"{prefix}/head{j}/Wa"] = (d_out * self.rank, n_features)
            shapes[f"{prefix}/head{j}/Wb"] = (d_in * self.rank, n_features)
        shapes[f"{prefix}/scale"] = ()
        return shapes


def lora_target_shapes(encoder: MLPSpec, decoder: MLPSpec) -> tuple[tuple[int, int], ...]:
    """The layers HyperKKL_dyn modulates: all encoder layers, then all decoder layers.

    Returns
    -------
    tuple of (d_out, d_in)
        Target ``j`` has weight shape ``(d_out_j, d_in_j)``.
    """
    return encoder.layer_shapes + decoder.layer_shapes


def array_name(prefix: str, name: str) -> str:
    """``"prefix/name"``, or ``name`` when ``prefix`` is empty."""
    return f"{prefix}/{name}" if prefix else name


def check_arrays(arrays: Any, shapes: Mapping[str, tuple[int, ...]], where: str,
                 *, exact: bool = False) -> None:
    """Check that ``arrays`` holds finite real arrays of the expected shapes.

    Parameters
    ----------
    arrays : Mapping[str, array_like]
        The arrays, by name.
    shapes : Mapping[str, tuple of int]
        Expected names and shapes.
    where : str
        Used in error messages (a file, or an argument name).
    exact : bool
        Also reject arrays that ``shapes`` does not name.

    Raises
    ------
    TypeError
        If ``arrays`` is not a mapping.
    ValueError
        Missing, misshaped, non-numeric or non-finite arrays, and unexpected ones if ``exact``.
    """
    if not isinstance(arrays, Mapping):
        raise TypeError(f"{where}: expected a mapping of array name -> array, "
                        f"found {type(arrays).__name__}.")
    missing = [name for name in shapes if name not in arrays]
    if missing:
        raise _error(where, missing[0], f"an array of shape {shapes[missing[0]]}", _Text("missing"),
                     f"{len(missing)} array(s) missing ({', '.join(missing[:5])}"
                     f"{', ...' if len(missing) > 5 else ''}); the weights do not match the "
                     "architecture: save them again from the trained networks.")
    if exact:
        extra = sorted(set(arrays) - set(shapes))
        if extra:
            raise _error(where, extra[0], "only the arrays the architecture names",
                         _Text("an extra array"),
                         f"Unexpected arrays {extra[:5]}; remove them or fix the architecture.")
    for name, shape in shapes.items():
        value = np.asarray(arrays[name])
        if value.dtype.kind not in "fiu":
            raise _error(where, name, "a real numeric array", _Text(f"dtype {value.dtype}"),
                         "Store float64 arrays.")
        if value.shape != tuple(shape):
            raise _error(where, name, f"shape {tuple(shape)}", _Text(f"shape {value.shape}"),
                         "The weights do not match the architecture; save them again from the "
                         "trained networks, or fix the architecture entry.")
        if not np.all(np.isfinite(value)):
            raise _error(where, name, "finite values", _Text("NaN or inf"),
                         "Training diverged or the file is damaged; retrain or restore the model.")
    for name in shapes:
        if name.endswith(("/in_std", "/out_std")) and not np.all(np.asarray(arrays[name]) > 0):
            raise _error(where, name, "positive standard deviations",
                         float(np.min(arrays[name])),
                         "Normalisation scales must be > 0; clamp them when computing them.")


def model_array_shapes(card: Mapping[str, Any],
                       where: str = CARD_FILE) -> dict[str, tuple[int, ...]]:
    """All array names and shapes a (validated) card's architecture needs.

    Parameters
    ----------
    card : Mapping
        A card that passed :func:`validate_card`.
    where : str
        Used in error messages.

    Raises
    ------
    ValueError
        If the architecture entries do not fit the system and design sizes.
    """
    system, arch = card["system"], card["architecture"]
    nx, nu = system["nx"], system["nu"]
    nz = len(card["design"]["A"])
    encoder = MLPSpec.from_card(arch[ENCODER], where, "architecture.encoder")
    decoder = MLPSpec.from_card(arch[DECODER], where, "architecture.decoder")
    for name, spec, n_in, n_out in ((ENCODER, encoder, nx, nz), (DECODER, decoder, nz, nx)):
        if (spec.n_in, spec.n_out) != (n_in, n_out):
            raise _error(where, f"architecture.{name}.sizes",
                         f"[{n_in}, ..., {n_out}] (nx={nx}, nz={nz})", list(spec.sizes),
                         "The encoder maps x to z and the decoder z to x; fix the sizes or the "
                         "system/design entries.")
    shapes = {**encoder.array_shapes(ENCODER), **decoder.array_shapes(DECODER)}
    if card["method"] == "obs":
        obs = ObsSpec.from_card(arch, where)
        if (obs.nz, obs.gain.n_out) != (nz, nz * nu):
            raise _error(where, "architecture.gain.sizes",
                         f"[nz + proj = {nz + obs.proj}, ..., nz*nu = {nz * nu}]",
                         list(obs.gain.sizes), "Size the gain MLP from the design and the system.")
        shapes.update(obs.array_shapes())
    elif card["method"] == "dyn":
        hyper = HyperSpec.from_card(arch, where)
        shapes.update(hyper.array_shapes(HYPER, nu, lora_target_shapes(encoder, decoder)))
    return shapes


def _matrix(value: Any, where: str, field_name: str, n_cols: Optional[int], fix: str) -> np.ndarray:
    ok = (isinstance(value, list) and value and all(isinstance(row, list) and row for row in value)
          and all(_is_number(v) for row in value for v in row)
          and len({len(row) for row in value}) == 1)
    if not ok:
        raise _error(where, field_name, "a non-empty list of equal-length lists of numbers",
                     value, fix)
    matrix = np.array(value, dtype=np.float64)
    if not np.all(np.isfinite(matrix)):
        raise _error(where, field_name, "finite numbers", value, fix)
    if n_cols is not None and matrix.shape[1] != n_cols:
        raise _error(where, field_name, f"{n_cols} columns", matrix.shape[1], fix)
    return matrix


def validate_card(card: Any, where: str = CARD_FILE, *, require_sha: bool = True) -> None:
    """Check a card's required fields, their types, and the consistency of its sizes.

    Parameters
    ----------
    card : Mapping
        The parsed ``card.json``.
    where : str
        Used in error messages (the card's path).
    require_sha : bool
        Whether ``weights_sha256`` must be present (False while saving: it is computed then).

    Raises
    ------
    ValueError
        Naming the field, what was expected, what was found and what to do.
    """
    fix_new = "Save the model again with kklcasadi.modelfile.save_model."
    if not isinstance(card, Mapping):
        raise _error(where, "<card>", "a JSON object", _Text(type(card).__name__), fix_new)
    required = ["format", "format_version", "kklcasadi_version", "method", "system", "design",
                "dt", "window", "architecture", "base", "noise", "training"]
    if require_sha:
        required.append("weights_sha256")
    for key in required:
        if key not in card:
            raise _error(where, key, "a required field", _Text("missing"), fix_new)
    if card["format"] != FORMAT:
        raise _error(where, "format", repr(FORMAT), card["format"],
                     "This is not a kklcasadi model card.")
    if not _is_int(card["format_version"]) or card["format_version"] != FORMAT_VERSION:
        raise _error(where, "format_version", FORMAT_VERSION, card["format_version"],
                     "Read it with the kklcasadi version that wrote it, or save it again.")
    if not isinstance(card["kklcasadi_version"], str):
        raise _error(where, "kklcasadi_version", "a string", card["kklcasadi_version"], fix_new)
    if card["method"] not in METHODS:
        raise _error(where, "method", f"one of {list(METHODS)}", card["method"], fix_new)

    system = card["system"]
    fix_sys = 'Write "system" as {"name": str, "nx": int, "nu": int, "ny": int}.'
    if not isinstance(system, Mapping) or not {"name", "nx", "nu", "ny"} <= set(system):
        raise _error(where, "system", "an object with name, nx, nu, ny", system, fix_sys)
    if not isinstance(system["name"], str):
        raise _error(where, "system.name", "a string", system["name"], fix_sys)
    for key in ("nx", "nu", "ny"):
        _positive_int(system[key], where, f"system.{key}", fix_sys)

    design = card["design"]
    fix_design = 'Write "design" as {"A": nz x nz list of lists, "B": nz x ny list of lists}.'
    if not isinstance(design, Mapping) or not {"A", "B"} <= set(design):
        raise _error(where, "design", "an object with A and B", design, fix_design)
    a = _matrix(design["A"], where, "design.A", None, fix_design)
    if a.shape[0] != a.shape[1]:
        raise _error(where, "design.A", "a square matrix", _Text(f"shape {a.shape}"), fix_design)
    b = _matrix(design["B"], where, "design.B", system["ny"], fix_design)
    if b.shape[0] != a.shape[0]:
        raise _error(where, "design.B", f"{a.shape[0]} rows (nz, from A)", b.shape[0], fix_design)

    if not _is_number(card["dt"]) or not math.isfinite(card["dt"]) or card["dt"] <= 0:
        raise _error(where, "dt", "a positive number (seconds)", card["dt"], fix_new)
    _positive_int(card["window"], where, "window", fix_new)

    arch = card["architecture"]
    entries = _METHOD_ENTRIES[card["method"]]
    if not isinstance(arch, Mapping) or set(arch) != set(entries):
        found = sorted(arch) if isinstance(arch, Mapping) else arch
        raise _error(where, "architecture", f"an object with exactly the keys {sorted(entries)} "
                     f"for method {card['method']!r}", found, fix_new)

    base = card["base"]
    if base is not None:
        fix_base = 'Write "base" as null or {"path": "../autonomous", "weights_sha256": "<hex>"}.'
        if (not isinstance(base, Mapping) or set(base) != {"path", "weights_sha256"}
                or not isinstance(base["path"], str)):
            raise _error(where, "base", "null or an object with path and weights_sha256", base,
                         fix_base)
        if not isinstance(base["weights_sha256"], str) or not _SHA256.match(base["weights_sha256"]):
            raise _error(where, "base.weights_sha256", "64 lowercase hex digits",
                         base["weights_sha256"], fix_base)

    noise = card["noise"]
    if (not isinstance(noise, Mapping) or "measurement_std" not in noise
            or not _is_number(noise["measurement_std"])
            or not math.isfinite(noise["measurement_std"]) or noise["measurement_std"] < 0):
        raise _error(where, "noise.measurement_std", "a number >= 0", noise,
                     'Write "noise" as {"measurement_std": 0.0}.')
    if not isinstance(card["training"], Mapping):
        raise _error(where, "training", "an object", card["training"],
                     "Use {} if there is nothing to record.")
    if require_sha and (not isinstance(card["weights_sha256"], str)
                        or not _SHA256.match(card["weights_sha256"])):
        raise _error(where, "weights_sha256", "64 lowercase hex digits", card["weights_sha256"],
                     fix_new)
    model_array_shapes(card, where)


@dataclass(frozen=True)
class Model:
    """A loaded model directory.

    Attributes
    ----------
    path : Path
        The model directory.
    card : dict
        The parsed ``card.json`` (treat as read-only).
    arrays : dict[str, np.ndarray]
        The float64 arrays of ``weights.npz``, read-only.
    base : Model or None
        The base (Phase-1) model named by ``card["base"]``, loaded and checked.
    """

    path: Path
    card: dict
    arrays: dict
    base: Optional["Model"] = field(default=None, repr=False)

    @property
    def method(self) -> str:
        """The observer variant, one of :data:`METHODS`."""
        return self.card["method"]

    @property
    def A(self) -> np.ndarray:
        """Latent dynamics matrix (nz, nz)."""
        return np.array(self.card["design"]["A"], dtype=np.float64)

    @property
    def B(self) -> np.ndarray:
        """Output injection matrix (nz, ny)."""
        return np.array(self.card["design"]["B"], dtype=np.float64)

    @property
    def dt(self) -> float:
        """Sample period in seconds."""
        return float(self.card["dt"])

    @property
    def window(self) -> int:
        """Input-window length in samples."""
        return int(self.card["window"])


def _npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    raise TypeError(f"card: a value of type {type(value).__name__} is not JSON-serialisable; "
                    "store numbers, strings, lists and dicts (numpy values are converted).")


def _to_json(card: Mapping[str, Any]) -> str:
    try:
        return json.dumps(card, indent=2, allow_nan=False, default=_json_default) + "\n"
    except ValueError as exc:
        raise ValueError(f"card: {exc}; NaN and inf cannot be stored in card.json, record them "
                         "as strings or leave them out.") from exc


def _read_json(path: Path) -> Any:
    def reject_constant(name: str) -> Any:
        raise ValueError(f"non-standard JSON constant {name}")

    try:
        return json.loads(path.read_text(encoding="utf-8"), parse_constant=reject_constant)
    except (UnicodeDecodeError, ValueError) as exc:
        raise ValueError(f"{path}: could not parse the card as strict JSON ({exc}). Restore the "
                         "file or save the model again.") from exc


def _read_npz(path: Path, data: bytes) -> dict[str, np.ndarray]:
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise ValueError(f"{path}: could not read the weights as a plain .npz archive ({exc}). "
                         "Restore the file or save the model again.") from exc
    for name, value in arrays.items():
        if value.dtype != np.float64:
            raise _error(str(path), name, "dtype float64", _Text(str(value.dtype)),
                         "Save the model with kklcasadi.modelfile.save_model.")
        value.setflags(write=False)
    return arrays


def _load_base(directory: Path, card: dict, where: str, seen: frozenset) -> Optional[Model]:
    if card["base"] is None:
        return None
    base_dir = (directory / card["base"]["path"]).resolve()
    if base_dir in seen:
        raise _error(where, "base.path", "a chain of base models without cycles", str(base_dir),
                     "Point base.path at the Phase-1 model.")
    try:
        base = _load(base_dir, seen | {base_dir})
    except ValueError as exc:
        raise ValueError(f"{where}: 'base.path' = {card['base']['path']!r} ({base_dir}) could not "
                         f"be loaded: {exc}") from exc
    if base.card["weights_sha256"] != card["base"]["weights_sha256"]:
        raise _error(where, "base.weights_sha256", card["base"]["weights_sha256"],
                     base.card["weights_sha256"],
                     f"The base model at {base_dir} changed after this model was trained on it; "
                     "restore it or retrain this model.")
    for key in ("system", "design"):
        if base.card[key] != card[key]:
            raise _error(where, key, f"the base model's {key} ({base_dir})", card[key],
                         "A model and its base must describe the same plant and design.")
    return base


def _load(directory: Path, seen: frozenset) -> Model:
    card_path, weights_path = directory / CARD_FILE, directory / WEIGHTS_FILE
    for path in (card_path, weights_path):
        if not path.is_file():
            raise ValueError(f"{path}: file not found; expected a model directory with "
                             f"{CARD_FILE} and {WEIGHTS_FILE}. Check the path, or train/save the "
                             "model first.")
    where = str(card_path)
    card = _read_json(card_path)
    validate_card(card, where)
    data = weights_path.read_bytes()
    digest = hashlib.sha256(data).hexdigest()
    if digest != card["weights_sha256"]:
        raise _error(where, "weights_sha256", f"the SHA-256 of {weights_path} = {digest}",
                     card["weights_sha256"],
                     "The weights file was modified or swapped, or the card belongs to another "
                     "model; restore the matching pair of files or save the model again.")
    arrays = _read_npz(weights_path, data)
    check_arrays(arrays, model_array_shapes(card, where), str(weights_path), exact=True)
    base = _load_base(directory, card, where, seen)
    return Model(path=directory, card=card, arrays=arrays, base=base)


def load_model(directory: str | os.PathLike) -> Model:
    """Load and validate a model directory.

    Parameters
    ----------
    directory : str or path-like
        Holds ``weights.npz`` and ``card.json``.

    Returns
    -------
    Model
        With ``base`` loaded when the card names one.

    Raises
    ------
    ValueError
        Missing files, unparsable JSON or npz, missing or mistyped card fields, an unknown method
        or format version, a weights file whose SHA-256 does not match the card, arrays missing,
        misshaped or non-finite, or a base model that cannot be loaded or changed. The message
        names the file and field, what was expected and found, and what to do.
    """
    directory = Path(directory).resolve()
    return _load(directory, frozenset({directory}))


def _write_temp(directory: Path, data: bytes, suffix: str) -> Path:
    handle, name = tempfile.mkstemp(dir=directory, prefix=".tmp-", suffix=suffix)
    with os.fdopen(handle, "wb") as stream:
        stream.write(data)
        stream.flush()
        os.fsync(stream.fileno())
    return Path(name)


def save_model(directory: str | os.PathLike, arrays: Mapping[str, Any], card: Mapping[str, Any],
               *, overwrite: bool = False) -> Path:
    """Validate and write ``weights.npz`` and ``card.json`` into ``directory``.

    The card's ``format``, ``format_version``, ``kklcasadi_version`` and ``weights_sha256`` are
    filled in here. Both files are written to temporary files in ``directory`` first and then moved
    into place with :func:`os.replace`, so a failed write leaves existing files as they were.

    Parameters
    ----------
    directory : str or path-like
        The model directory; created if needed.
    arrays : Mapping[str, array_like]
        Exactly the arrays the card's architecture names (see ``docs/model-format.md``); stored
        as float64.
    card : Mapping
        The card fields (see the module docstring); ``base.path`` is relative to ``directory``.
    overwrite : bool
        Replace an existing model in ``directory``.

    Returns
    -------
    Path
        The model directory.

    Raises
    ------
    FileExistsError
        If ``directory`` already holds a model and ``overwrite`` is False.
    ValueError
        If the card or the arrays are invalid (as :func:`load_model` would report).
    """
    from kklcasadi import __version__

    directory = Path(directory).resolve()
    if not isinstance(card, Mapping):
        raise TypeError(f"card: expected a mapping, found {type(card).__name__}.")
    card = {**card, "format": FORMAT, "format_version": FORMAT_VERSION,
            "kklcasadi_version": __version__}
    card.pop("weights_sha256", None)
    card = json.loads(_to_json(card))
    where = f"card for {directory / CARD_FILE}"
    validate_card(card, where, require_sha=False)
    check_arrays(arrays, model_array_shapes(card, where), "arrays", exact=True)
    arrays = {name: np.array(value, dtype=np.float64) for name, value in arrays.items()}

    existing = [p for p in (directory / CARD_FILE, directory / WEIGHTS_FILE) if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{existing[0]}: a model already exists here; pass overwrite=True "
                              "to replace it, or choose another directory.")
    directory.mkdir(parents=True, exist_ok=True)
    _load_base(directory, card, where, frozenset({directory}))

    data = _npz_bytes(arrays)
    card["weights_sha256"] = hashlib.sha256(data).hexdigest()
    text = _to_json(card)
    temps: list[Path] = []
    try:
        temps.append(_write_temp(directory, data, ".npz"))
        temps.append(_write_temp(directory, text.encode("utf-8"), ".json"))
        os.replace(temps[0], directory / WEIGHTS_FILE)
        os.replace(temps[1], directory / CARD_FILE)
    finally:
        for temp in temps:
            temp.unlink(missing_ok=True)
    return directory
