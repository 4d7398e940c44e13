"""The card's integrity: one SHA-256 over the whole card, which holds the SHA-256 of the weights, so that an edit
of either is refused on load; and a short hash per field, so that the refusal names the field that changed.

``card.json`` carries ``"digest": {"sha256": <64 hex digits>, "fields": {<path>: <8 hex digits>, ...}}``:

``sha256``
    SHA-256 of a fixed tag and the canonical JSON (sorted keys, no blanks, ASCII) of every other field of the
    card, ``weights_sha256`` (the SHA-256 of ``weights.npz``'s bytes) among them: one digest over the card and
    the weights.
``fields``
    For every field down to :data:`FIELD_DEPTH` levels (``dt``, ``system.fingerprint``,
    ``architecture.encoder.activation``), the first 8 hex digits of the SHA-256 of its canonical JSON.

This detects a changed, added or removed field, accidental or not; it is not a signature against someone
who can write the files (they can sign again: ``kklcasadi resign``). Loading never runs code either way.
The card's JSON is read with bounded size and nesting (:func:`read_card_json`) before anything else.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Mapping, Optional

from ..nets.specs import field_error
from ..validation import Text, error

__all__ = ["DIGEST", "MAX_CARD_BYTES", "MAX_CARD_DEPTH", "FIELD_DEPTH", "canonical", "card_digest", "changes",
           "describe", "check_digest", "read_card_json", "json_depth"]

#: The card's integrity entry.
DIGEST = "digest"
#: Bounds checked before a card is parsed: its size (the largest shipped card has 16 kB) and its nesting (5 levels).
MAX_CARD_BYTES = 4 * 2 ** 20
MAX_CARD_DEPTH = 32
#: How deep ``digest.fields`` names the fields it hashes one by one.
FIELD_DEPTH = 3
_TAG = b"kklcasadi.model card digest\n"
_RESIGN = "Restore the card, or check it and accept it with: kklcasadi resign {directory}"


def canonical(value: Any) -> bytes:
    """The canonical JSON of a card value: sorted keys, no blanks, ASCII, no NaN."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode()


def _fields(card: Mapping[str, Any]) -> dict[str, Any]:
    """Every field down to :data:`FIELD_DEPTH` levels by its dotted path (an object deeper down is one field)."""
    out: dict[str, Any] = {}

    def walk(value: Any, path: str, depth: int) -> None:
        if isinstance(value, Mapping) and value and depth < FIELD_DEPTH:
            for key, item in value.items():
                walk(item, f"{path}.{key}", depth + 1)
        else:
            out[path] = value

    for key, value in card.items():
        if key != DIGEST:
            walk(value, str(key), 1)
    return out


def card_digest(card: Mapping[str, Any]) -> dict:
    """The ``digest`` entry of ``card`` (its own ``digest``, if any, left out)."""
    body = {key: value for key, value in card.items() if key != DIGEST}
    return {"sha256": hashlib.sha256(_TAG + canonical(body)).hexdigest(),
            "fields": {path: hashlib.sha256(canonical(value)).hexdigest()[:8] for path, value in _fields(body).items()}}


def _shown(value: Any, limit: int = 80) -> str:
    text = canonical(value).decode()
    return text if len(text) <= limit else text[:limit - 3] + "..."


def changes(card: Mapping[str, Any]) -> list[tuple[str, str, Any]]:
    """What changed in ``card`` since its digest was computed: ``(path, "changed" | "added" | "removed", value now)``
    per field (empty: nothing changed, or the card has no digest to compare with)."""
    entry = card.get(DIGEST)
    recorded = entry.get("fields", {}) if isinstance(entry, Mapping) else {}
    now = card_digest(card)["fields"]
    values = _fields(card)
    return ([(path, "changed", values[path]) for path, short in now.items()
             if path in recorded and recorded[path] != short]
            + [(path, "added", values[path]) for path in now if path not in recorded]
            + [(path, "removed", None) for path in recorded if path not in now])


def describe(change: tuple[str, str, Any]) -> str:
    """One change as text: ``'dt' changed (now 0.1)``."""
    path, kind, value = change
    if kind == "removed":
        return f"'{path}' removed"
    return f"'{path}' {kind} ({'now ' if kind == 'changed' else ''}{_shown(value)})"


def check_digest(card: Any, where: str, directory: Path) -> None:
    """Refuse a card whose digest is missing, malformed or does not match its fields, naming what changed.

    Raises
    ------
    ArgumentError
        ``where: 'FIELD': expected ..., received ...`` and how to restore or accept the card.
    """
    fix = _RESIGN.format(directory=directory)
    if not isinstance(card, Mapping):
        raise field_error(where, "<card>", "a JSON object", Text(type(card).__name__), fix)
    entry = card.get(DIGEST)
    if entry is None:
        raise field_error(where, DIGEST, "the card's digest (cards written before format_version 2 have none)",
                          Text("missing"), fix)
    if (not isinstance(entry, Mapping) or set(entry) != {"sha256", "fields"} or not isinstance(entry["sha256"], str)
            or not isinstance(entry["fields"], Mapping)
            or not all(isinstance(v, str) for v in entry["fields"].values())):
        raise field_error(where, DIGEST, 'an object {"sha256": hex, "fields": {path: hex}}', Text("another value"),
                          fix)
    try:
        computed = card_digest(card)
    except (TypeError, ValueError) as exc:                 # values JSON cannot hold: not a card read from a file
        raise field_error(where, "<card>", "JSON values", Text(str(exc)), fix) from exc
    expected = computed["sha256"]
    if entry["sha256"] == expected:
        if dict(entry["fields"]) != computed["fields"]:   # the fields' digests are part of the card: damaged there
            raise field_error(where, f"{DIGEST}.fields", "the digests of the card's fields it was written with",
                              Text("other digests"), fix)
        return
    found = changes(card)
    if not found:
        raise field_error(where, f"{DIGEST}.sha256", f"the SHA-256 of the card ({expected})", entry["sha256"], fix)
    path, kind, value = found[0]
    more = f"; {len(found) - 1} more change(s)" if len(found) > 1 else ""
    expected_text = {"changed": "the value the model was written with", "added": "no such field (the model was "
                     "written without it)", "removed": "the field the model was written with"}[kind]
    received = Text(("missing" if kind == "removed" else _shown(value)) + more)
    raise field_error(where, path, expected_text, received, fix)


def json_depth(text: str) -> int:
    """The deepest nesting of objects and arrays in a JSON text (strings skipped), without parsing it."""
    depth = deepest = 0
    in_string = escaped = False
    for char in text:
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth -= 1
    return deepest


def read_card_json(path: Path, *, limit: Optional[int] = None,
                   fix: str = "Restore the file or save the model again.") -> Any:
    """``card.json``, checked before it is parsed: a regular file of at most :data:`MAX_CARD_BYTES` bytes (or
    ``limit``), UTF-8, nested at most :data:`MAX_CARD_DEPTH` levels, strict JSON (no NaN or Infinity).

    Raises
    ------
    ArgumentError
        Naming the file, the bound or the parse error, and what to do (``fix``).
    """
    limit = MAX_CARD_BYTES if limit is None else limit
    size = path.stat().st_size
    if size > limit:
        raise error(str(path), f"a card of at most {limit} bytes", Text(f"{size} bytes"), fix)
    with open(path, "rb") as stream:
        raw = stream.read(limit + 1)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(str(path), "UTF-8 text", Text(f"undecodable bytes ({exc.reason} at byte {exc.start})"),
                    fix) from None
    depth = json_depth(text)
    if depth > MAX_CARD_DEPTH:
        raise error(str(path), f"JSON nested at most {MAX_CARD_DEPTH} levels deep", Text(f"{depth} levels"), fix)

    def reject_constant(name: str) -> Any:
        raise ValueError(f"non-standard JSON constant {name}")

    try:
        return json.loads(text, parse_constant=reject_constant)
    except ValueError as exc:
        raise error(str(path), "strict JSON", Text(f"a parse error ({exc})"), fix) from None


def read_json_object(path: Path, fix: str) -> dict:
    """A JSON object the package wrote beside its files (a training's run record, a study's binding), read as
    :func:`read_card_json` reads a card.

    Raises
    ------
    ArgumentError
        In one line naming the file and ``fix`` where it is not a readable JSON object.
    """
    data = read_card_json(path, fix=fix)
    if not isinstance(data, dict):
        raise error(str(path), "a JSON object", Text(f"a JSON {type(data).__name__}"), fix)
    return data
