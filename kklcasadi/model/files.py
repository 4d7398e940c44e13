"""Model files: ``weights.npz`` + ``card.json``, read and written without torch.

A model directory holds two files:

``weights.npz``
    Plain float64 arrays (no pickles), named ``<prefix>/<array>``, e.g. ``decoder/W0``.
``card.json``
    What the arrays mean (:mod:`kklcasadi.model.card`), plus the SHA-256 of the weights file.

:func:`load_model` reads and checks a directory once (the card by :func:`kklcasadi.model.card.parse_card`, the
arrays against it); :func:`save_model` validates the same before it writes. The format is described for users in
``docs/model-format.md``.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from ..nets.specs import check_arrays, check_names, field_error
from ..validation import Text, error
from ..writes import write_dir, write_file
from . import variants
from .card import CARD_FILE, FORMAT, FORMAT_VERSION, ModelSpec, make_card, parse_card
from .digest import DIGEST, card_digest, changes, check_digest, describe, read_card_json
from .monitor import check_radii

__all__ = ["WEIGHTS_FILE", "CARD_FILE", "EXTRA_FILES", "MODEL_FILES", "MAX_NPY_HEADER", "Model", "load_model",
           "save_model", "derive_model", "resign_model"]

WEIGHTS_FILE = "weights.npz"
#: Files a model directory may hold beside the card and the weights, written with them (:func:`save_model`).
EXTRA_FILES = ("history.json", "history.png")
#: The names a model directory's writer owns: replaced or dropped with the model, never carried over
#: (``.train``: training's checkpoints, done with once the model is written).
MODEL_FILES = (WEIGHTS_FILE, CARD_FILE, *EXTRA_FILES, ".train")


@dataclass(frozen=True)
class Model:
    """A loaded model directory.

    Attributes
    ----------
    path : Path
        The model directory.
    card : dict
        The parsed ``card.json`` as read (treat as read-only; use :attr:`spec` for its fields).
    spec : ModelSpec
        The typed, validated card.
    arrays : dict[str, np.ndarray]
        The float64 arrays of ``weights.npz``, read-only, checked against ``spec``.
    base : Model or None
        The base (Phase-1) model named by ``card["base"]``, loaded and checked.
    """

    path: Path
    card: dict
    spec: ModelSpec
    arrays: dict
    base: Optional[Model] = field(default=None, repr=False)

    @property
    def method(self) -> str:
        """The observer variant, a key of :data:`kklcasadi.model.variants.VARIANTS`."""
        return self.spec.method

    @property
    def A(self) -> np.ndarray:
        """Latent dynamics matrix (nz, nz)."""
        return self.spec.A

    @property
    def B(self) -> np.ndarray:
        """Output injection matrix (nz, ny)."""
        return self.spec.B

    @property
    def dt(self) -> float:
        """Sample period in seconds."""
        return self.spec.dt

    @property
    def window(self) -> int:
        """Input-window length in samples."""
        return self.spec.window


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


#: Bytes an array's ``.npy`` header may hold (numpy's own default limit), and the room a zip entry takes beside its
#: data (local header, name, data descriptor): bounds on the weights file checked before it is read.
MAX_NPY_HEADER = 10_000
_ZIP_ENTRY = 1_024
_FIX_WEIGHTS = "Restore the file or save the model again."


def _archive(path: Path) -> dict[str, zipfile.ZipInfo]:
    """The entries of ``weights.npz`` by array name, from its central directory (nothing is decompressed)."""
    try:
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as exc:
        raise error(str(path), "a plain .npz archive", Text(f"an unreadable file ({exc})"), _FIX_WEIGHTS) from None
    entries: dict[str, zipfile.ZipInfo] = {}
    for info in infos:
        name = info.filename[:-len(".npy")]
        if not info.filename.endswith(".npy") or info.is_dir() or name in entries:
            raise error(str(path), "an archive of distinct .npy arrays", Text(f"the entry {info.filename!r}"),
                        _FIX_WEIGHTS)
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise error(str(path), "entries stored or deflated (numpy.savez, savez_compressed)",
                        Text(f"the entry {info.filename!r} compressed by method {info.compress_type}"), _FIX_WEIGHTS)
        entries[name] = info
    return entries


def _file_sha256(path: Path) -> str:
    sha = hashlib.sha256()
    with open(path, "rb") as stream:
        for chunk in iter(lambda: stream.read(2 ** 20), b""):
            sha.update(chunk)
    return sha.hexdigest()


def _expected_bytes(shape: tuple[int, ...]) -> int:
    return 8 * math.prod(shape)


def _read_npz(path: Path, data: bytes, entries: Mapping[str, zipfile.ZipInfo],
              shapes: Mapping[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
    """The arrays of ``weights.npz`` (its bytes ``data``), each checked before it is decompressed or allocated: the
    names the card names, an uncompressed size that its shape fits (a deflate bomb is refused from its
    directory), a bounded ``.npy`` header declaring that shape and float64, no pickled objects."""
    where = str(path)
    check_names(entries, shapes, where, exact=True)
    arrays = {}
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        for name, shape in shapes.items():
            info, size = entries[name], _expected_bytes(shape)
            if not size <= info.file_size <= size + MAX_NPY_HEADER:
                raise field_error(where, name, f"{size} bytes of float64 data of shape {shape} (and a header)",
                                  Text(f"an entry of {info.file_size} bytes uncompressed"), _FIX_WEIGHTS)
            try:
                with archive.open(info) as stream:
                    raw = stream.read(info.file_size)
            except (zipfile.BadZipFile, EOFError, OSError, ValueError, zlib.error) as exc:
                raise field_error(where, name, "a readable archive entry", Text(str(exc)), _FIX_WEIGHTS) from None
            arrays[name] = _npy_array(raw, shape, where, name)
    return arrays


def _npy_array(raw: bytes, shape: tuple[int, ...], where: str, name: str) -> np.ndarray:
    stream = io.BytesIO(raw)
    try:
        version = np.lib.format.read_magic(stream)
        read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in read_header:
            raise ValueError(f"format version {version}")
        found, fortran, dtype = read_header[version](stream, max_header_size=MAX_NPY_HEADER)
    except ValueError as exc:
        raise field_error(where, name, "a .npy array", Text(f"an unreadable header ({exc})"), _FIX_WEIGHTS) from None
    if dtype != np.dtype("<f8") and dtype != np.dtype(">f8"):
        raise field_error(where, name, "dtype float64", Text(str(dtype)), "Save the model with "
                          "kklcasadi.model.files.save_model.")
    if tuple(found) != tuple(shape):
        raise field_error(where, name, f"shape {tuple(shape)}", Text(f"shape {tuple(found)}"),
                          "the weights do not match the architecture: save them again from the trained networks.")
    body = raw[stream.tell():]
    if len(body) != _expected_bytes(shape):
        raise field_error(where, name, f"{_expected_bytes(shape)} bytes of data", Text(f"{len(body)} bytes"),
                          _FIX_WEIGHTS)
    array = np.frombuffer(body, dtype=dtype).reshape(shape, order="F" if fortran else "C").astype(np.float64)
    array.setflags(write=False)
    return array


def _load_base(directory: Path, card: dict, where: str, seen: frozenset) -> Optional[Model]:
    if card["base"] is None:
        return None
    base_dir = (directory / card["base"]["path"]).resolve()
    if base_dir in seen:
        raise field_error(where, "base.path", "a chain of base models without cycles", str(base_dir),
                     "Point base.path at the Phase-1 model.")
    try:
        base = _load(base_dir, seen | {base_dir})
    except ValueError as exc:
        raise ValueError(f"{where}: 'base.path' = {card['base']['path']!r} ({base_dir}) could not "
                         f"be loaded: {exc}") from exc
    if base.card["weights_sha256"] != card["base"]["weights_sha256"]:
        raise field_error(where, "base.weights_sha256", card["base"]["weights_sha256"],
                     base.card["weights_sha256"],
                     f"The base model at {base_dir} changed after this model was trained on it; "
                     "restore it or retrain this model.")
    for key in ("system", "design"):
        if base.card[key] != card[key]:
            raise field_error(where, key, f"the base model's {key} ({base_dir})", card[key],
                         "A model and its base must describe the same plant and design.")
    return base


def _load(directory: Path, seen: frozenset, card: Optional[dict] = None) -> Model:
    """Read and check a model directory; with ``card`` given, that card instead of the file's, its digest unchecked
    (:func:`resign_model`)."""
    card_path, weights_path = directory / CARD_FILE, directory / WEIGHTS_FILE
    for path in (card_path, weights_path):
        if not path.is_file():
            raise ValueError(f"{path}: file not found; expected a model directory with "
                             f"{CARD_FILE} and {WEIGHTS_FILE}. Check the path, or train/save the "
                             "model first.")
    where = str(card_path)
    if card is None:
        card = read_card_json(card_path)
        check_digest(card, where, directory)
    digest = _file_sha256(weights_path)                   # streamed: no size is trusted before the hash matches
    if not isinstance(card, Mapping) or digest != card.get("weights_sha256"):
        parse_card(card, where)                           # a card without a valid weights_sha256 says so first
        raise field_error(where, "weights_sha256", f"the SHA-256 of {weights_path} = {digest}",
                     card["weights_sha256"],
                     "The weights file was modified or swapped, or the card belongs to another "
                     "model; restore the matching pair of files or save the model again.")
    entries = _archive(weights_path)
    spec = parse_card(card, where, n_arrays=len(entries))
    shapes = spec.array_shapes()
    bound = sum(_expected_bytes(shape) + MAX_NPY_HEADER + _ZIP_ENTRY + len(name) for name, shape in shapes.items())
    size = weights_path.stat().st_size
    if size > bound + _ZIP_ENTRY:
        raise error(str(weights_path), f"at most {bound + _ZIP_ENTRY} bytes (the arrays the card names)",
                    Text(f"{size} bytes"), _FIX_WEIGHTS)
    data = weights_path.read_bytes()
    if hashlib.sha256(data).hexdigest() != digest:       # changed since it was hashed
        raise error(str(weights_path), "a file that does not change while it is read", Text("another file"),
                    "Load it again once whatever writes it has finished.")
    arrays = _read_npz(weights_path, data, entries, shapes)
    check_arrays(arrays, shapes, str(weights_path), exact=True)
    if spec.monitor is not None:
        check_radii(arrays, str(weights_path))
    base = _load_base(directory, card, where, seen)
    return Model(path=directory, card=card, spec=spec, arrays=arrays, base=base)


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
        names the file and field, what was expected and received, and what to do.
    """
    directory = Path(directory).resolve()
    return _load(directory, frozenset({directory}))


def save_model(directory: str | os.PathLike, arrays: Mapping[str, Any], card: Mapping[str, Any],
               *, overwrite: bool = False, extra: Optional[Mapping[str, bytes]] = None) -> Path:
    """Validate and write ``weights.npz`` and ``card.json`` into ``directory``.

    The card's ``format``, ``format_version``, ``kklcasadi_version`` and ``weights_sha256`` are
    filled in here. The files are written into a temporary directory beside ``directory`` and published
    with one rename (:func:`kklcasadi.writes.write_dir`): at every moment the old model or the new one is
    whole, and of two saves of one new model without ``overwrite`` exactly one wins.

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
        Replace an existing model in ``directory`` (its other files, those of :data:`MODEL_FILES` aside,
        stay).
    extra : Mapping[str, bytes], optional
        Files written with the model in the same step, among :data:`EXTRA_FILES` (the training
        history).

    Returns
    -------
    Path
        The model directory.

    Raises
    ------
    FileExistsError
        If ``directory`` already holds a model (or another save publishes one first) and ``overwrite``
        is False.
    ValueError
        If the card or the arrays are invalid (as :func:`load_model` would report).
    """
    from ..version import __version__

    directory = Path(directory).resolve()
    if not isinstance(card, Mapping):
        raise field_error("save_model", "card", "a mapping", Text(type(card).__name__), "")
    card = {**card, "format": FORMAT, "format_version": FORMAT_VERSION,
            "kklcasadi_version": __version__}
    card.pop("weights_sha256", None)
    card.pop(DIGEST, None)
    card = json.loads(_to_json(card))
    where = f"card for {directory / CARD_FILE}"
    if not isinstance(arrays, Mapping):
        raise error("arrays", "a mapping of array name -> array", Text(type(arrays).__name__), kind=TypeError)
    spec = parse_card(card, where, require_sha=False, n_arrays=len(arrays))
    check_arrays(arrays, spec.array_shapes(), "arrays", exact=True)
    arrays = {name: np.array(value, dtype=np.float64) for name, value in arrays.items()}
    if spec.monitor is not None:
        check_radii(arrays, "arrays")

    if (directory / CARD_FILE).exists() and not overwrite:
        raise FileExistsError(f"{directory / CARD_FILE}: a model already exists here; pass overwrite=True "
                              "to replace it, or choose another directory.")
    _load_base(directory, card, where, frozenset({directory}))

    data = _npz_bytes(arrays)
    card["weights_sha256"] = hashlib.sha256(data).hexdigest()
    card[DIGEST] = card_digest(card)
    extra = dict(extra or {})
    for name in extra:
        if name not in EXTRA_FILES:
            raise error("extra", f"files among {list(EXTRA_FILES)}", name)
    write_dir(directory, {WEIGHTS_FILE: data, CARD_FILE: _to_json(card), **extra}, overwrite=overwrite,
              owned=MODEL_FILES, argument=str(directory))
    return directory


def derive_model(base: str | os.PathLike, out_dir: str | os.PathLike, method: str = "inject", *,
                 overwrite: bool = False) -> Path:
    """Write a model that its variant makes from a base model without training (e.g. ``inject``).

    The new card has the base model's system, design, sample period, noise levels, domain and label coverage,
    window 1, and the arrays and architecture the variant keeps
    (:meth:`kklcasadi.model.variants.Variant.derive`). The model is self-contained: its ``base`` is null
    and ``training.derived_from`` records the base (path relative to the new model, SHA-256 and
    method), so it loads and deploys without the base directory.

    Parameters
    ----------
    base : str or path-like
        A model directory whose method is in the variant's ``derives_from``.
    out_dir : str or path-like
        Where to write the new model (e.g. ``models/duffing/inject``).
    method : str
        The variant to make (default ``"inject"``).
    overwrite : bool
        Replace an existing model in ``out_dir``.

    Returns
    -------
    Path
        The new model directory.
    """
    from ..plant.design import Design

    variant = variants.get(method)
    source = load_model(base)
    if source.method not in variant.derives_from:
        raise field_error(str(source.path / CARD_FILE), "method",
                          f"one of {list(variant.derives_from)} (a model {method!r} is made from)",
                          source.method, "Point base at a Phase-1 model.")
    out = Path(out_dir).resolve()
    spec, arrays, training = variant.derive(source.method, source.spec.architecture, source.arrays)
    training = {**training, "derived_from": {"path": os.path.relpath(source.path, out),
                                             "weights_sha256": source.card["weights_sha256"], "method": source.method}}
    card = make_card(source.spec.system, Design(source.A, source.B), method, spec, dt=source.dt,
                     window=1, training=training, measurement_std=source.spec.measurement_std,
                     domain=source.spec.domain, coverage=source.spec.coverage, process_std=source.spec.process_std)
    return save_model(out, arrays, card, overwrite=overwrite)


def resign_model(directory: str | os.PathLike) -> list[str]:
    """Check a model whose card was edited by hand (or written before cards carried a digest) and sign its card.

    Everything :func:`load_model` checks is checked (the card's fields against its method, the weights against
    the card's SHA-256 and architecture, the base model) except the card's digest, which is then written anew; the
    weights are not touched.

    Parameters
    ----------
    directory : str or path-like
        The model directory.

    Returns
    -------
    list of str
        What changed since the card was last signed, one entry per field (``'dt' changed (now 0.1)``); for a card
        without a digest, its format version; empty where nothing changed (and nothing was written).

    Raises
    ------
    ValueError
        The model does not load once signed (the message names the file and field, as :func:`load_model`).
    """
    directory = Path(directory).resolve()
    card_path = directory / CARD_FILE
    if not card_path.is_file():
        raise ValueError(f"{card_path}: file not found; expected a model directory with {CARD_FILE} and "
                         f"{WEIGHTS_FILE}.")
    card = read_card_json(card_path)
    if not isinstance(card, Mapping):
        raise field_error(str(card_path), "<card>", "a JSON object", Text(type(card).__name__), "Restore the card.")
    signed = isinstance(card.get(DIGEST), Mapping)
    found = [describe(change) for change in changes(card)] if signed else []
    body = {key: value for key, value in card.items() if key != DIGEST}
    if body.get("format_version") == 1:                    # written before cards carried their digest
        body["format_version"] = FORMAT_VERSION
        found.append(f"'format_version' 1 -> {FORMAT_VERSION} (the card had no digest)")
    _load(directory, frozenset({directory}), card=body)
    body[DIGEST] = card_digest(body)
    if body == card:
        return []
    write_file(card_path, _to_json(body), overwrite=True, argument=str(card_path))
    return found or ["the digest (its fields unchanged)"]
