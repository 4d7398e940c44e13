"""Provenance stamps: which command, commit, versions and seeds wrote a result file.

A :class:`Stamp` records the command line, the git commit of the package's checkout (``"unknown"``
outside one, the package version beside it), the package version, the seeds, the UTC time and the
python, casadi and torch versions. Every file a result writer makes carries one in its own content:

=========  ======================================================================================
JSON       a top-level ``"provenance"`` object (:func:`json_record`; a list is wrapped as
           ``{"provenance": ..., "records": [...]}``)
Markdown   a first line ``<!-- provenance {...} -->`` (an HTML comment: rendered invisible;
           :func:`markdown`)
CSV        a first line ``# provenance {...}`` before the header row (:func:`csv_comment`; the
           package's CSV reader skips it, as ``pandas.read_csv(..., comment="#")`` and
           ``csv`` after one ``readline()`` do)
PNG        a ``provenance`` text chunk (:func:`png_metadata`, for matplotlib's
           ``savefig(..., metadata=...)``)
=========  ======================================================================================

:func:`read` gets the stamp back from any of them. A *retroactive* stamp (``retroactive=True``)
was written after the fact, from what is known of a file (the command recorded in the docs and the
commit that added it): its ``time`` is that commit's, its versions are unknown.
"""

from __future__ import annotations

import functools
import json
import os
import platform
import shlex
import subprocess
import sys
import zlib
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

from .validation import Text, error
from .version import __version__

__all__ = ["Stamp", "stamp", "commit", "command_line", "json_record", "json_payload", "markdown", "strip_markdown",
           "csv_comment", "png_metadata", "read", "KEY", "UNKNOWN"]

#: The key (JSON), the comment word (markdown, CSV) and the text chunk's keyword (PNG) of a stamp.
KEY = "provenance"
#: The commit outside a git checkout of the package, and the versions a retroactive stamp cannot know.
UNKNOWN = "unknown"
_MD_OPEN, _MD_CLOSE = f"<!-- {KEY} ", " -->"
_CSV_OPEN = f"# {KEY} "
_ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Stamp:
    """Where a result file came from.

    Attributes
    ----------
    command : str
        The command line that wrote it, as typed (``"kklcasadi evaluate models/vdp/bank --ekf"``,
        ``"python benchmarks/summarize.py"``).
    commit : str
        ``git rev-parse HEAD`` of the package's checkout, with ``-dirty`` when tracked files had
        changes; ``"unknown"`` outside a checkout (``version`` then says which release).
    version : str
        The package version.
    seeds : dict {str: int}
        The seeds of what the command drew, by role (``{"trials": 2026}``); empty when it drew nothing.
    time : str
        UTC time, ISO 8601 to the second.
    python, casadi, torch : str
        Versions (``"not installed"`` for a missing torch; ``"unknown"`` in a retroactive stamp).
    retroactive : bool
        Written after the fact from what is known of the file (see ``note``), not by its command.
    note : str
        Free text: how a retroactive stamp was made, what else the command depended on.
    """

    command: str
    commit: str
    version: str = __version__
    seeds: Mapping[str, Any] = field(default_factory=dict)
    time: str = ""
    python: str = UNKNOWN
    casadi: str = UNKNOWN
    torch: str = UNKNOWN
    retroactive: bool = False
    note: str = ""

    def __post_init__(self) -> None:
        for name in ("command", "commit", "version"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value.strip():
                raise error(name, "a non-empty string", value)
        if not isinstance(self.seeds, Mapping) or not all(isinstance(k, str) for k in self.seeds):
            raise error("seeds", "a mapping {role: seed}", Text(repr(self.seeds)), kind=TypeError)
        object.__setattr__(self, "seeds", dict(self.seeds))

    def to_json(self) -> dict:
        """The stamp as a plain dict (JSON-ready; ``retroactive`` and ``note`` only when set)."""
        out = asdict(self)
        if not self.retroactive:
            del out["retroactive"]
        if not self.note:
            del out["note"]
        return out

    @classmethod
    def from_json(cls, data: Any, where: str = KEY) -> Stamp:
        """Read :meth:`to_json`'s dict back; ``where`` names the source in errors."""
        if not isinstance(data, Mapping):
            raise error(where, "a provenance object", Text(type(data).__name__), kind=TypeError)
        known = {f for f in cls.__dataclass_fields__}
        unknown = sorted(set(data) - known)
        if unknown:
            raise error(where, f"fields among {sorted(known)}", Text(f"unknown fields {unknown}"))
        missing = sorted({"command", "commit"} - set(data))
        if missing:
            raise error(where, "a stamp naming its command and commit", Text(f"no {', '.join(missing)}"))
        return cls(**data)

    def text(self) -> str:
        """The stamp as one line of compact JSON (the payload of the markdown and CSV comments)."""
        return json.dumps(self.to_json(), separators=(",", ":"), sort_keys=False)


def command_line(argv: Optional[Sequence[str]] = None) -> str:
    """The command line of this process as a user would type it.

    ``argv`` defaults to :data:`sys.argv`. A console script keeps its name (``kklcasadi ...``), a
    module run as ``python -m`` its module, a script ``python PATH`` with ``PATH`` relative to the
    current directory where it lies under it.
    """
    argv = list(sys.argv if argv is None else argv)
    if not argv:
        return "python"
    program, rest = argv[0], argv[1:]
    path = Path(program)
    if path.name == "__main__.py":
        head = ["python", "-m", path.parent.name]
    elif path.suffix == ".py":
        inside = path.is_absolute() and path.resolve().is_relative_to(Path.cwd().resolve())
        head = ["python", os.path.relpath(path.resolve()) if inside else program]
    else:
        head = [path.name]
    return shlex.join([*head, *map(str, rest)])


def _git(*args: str) -> Optional[str]:
    """``git -C <checkout> ARGS`` output, or None where git is missing, fails or hangs."""
    try:
        done = subprocess.run(["git", "-C", str(_ROOT), *args], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired):             # no git on this machine: the commit is unknown
        return None
    return done.stdout.strip() if done.returncode == 0 else None


@functools.cache
def commit() -> str:
    """The commit of the checkout the package runs from (``HASH`` or ``HASH-dirty``), else ``"unknown"``.

    Only a checkout whose top level holds this very package counts: an installed copy inside some
    other repository (a virtual environment in a clone) is ``"unknown"``.
    """
    top = _git("rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != _ROOT:
        return UNKNOWN
    head = _git("rev-parse", "HEAD")
    if not head:
        return UNKNOWN
    changes = _git("status", "--porcelain", "--untracked-files=no")
    return head + ("-dirty" if changes else "")


def _installed(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:                   # torch is optional: say so in the stamp
        return "not installed"


def stamp(*, seeds: Optional[Mapping[str, Any]] = None, command: Optional[str] = None, note: str = "") -> Stamp:
    """A stamp of this process: its command line (or ``command``), commit, versions, ``seeds`` and time.

    Parameters
    ----------
    seeds : mapping {str: int}, optional
        The seeds of what is written, by role (``{"trials": 2026, "training": 11}``).
    command : str, optional
        The command line to record (default :func:`command_line` of :data:`sys.argv`; the CLI passes
        the ``kklcasadi ...`` line it parsed).
    note : str
        Anything else a reader needs to redo the file.
    """
    return Stamp(command=command or command_line(), commit=commit(), version=__version__, seeds=dict(seeds or {}),
                 time=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                 python=platform.python_version(), casadi=_installed("casadi"), torch=_installed("torch"),
                 note=note)


def json_record(record: Any, stamp: Stamp) -> dict:
    """``record`` with the stamp first: a dict gains a ``"provenance"`` key, a list becomes ``{"provenance":
    ..., "records": [...]}`` (what :func:`json_payload` gives back)."""
    if isinstance(record, Mapping):
        if KEY in record:
            raise error("record", f"a record without a {KEY!r} key", Text(f"one with {KEY!r} already"))
        return {KEY: stamp.to_json(), **record}
    if isinstance(record, (list, tuple)):
        return {KEY: stamp.to_json(), "records": list(record)}
    raise error("record", "a dict or a list", Text(type(record).__name__), kind=TypeError)


def json_payload(data: Any) -> Any:
    """The record of a stamped JSON object without its stamp (a wrapped list comes back as the list);
    an unstamped record as it is."""
    if isinstance(data, Mapping) and KEY in data:
        rest = {k: v for k, v in data.items() if k != KEY}
        return rest["records"] if set(rest) == {"records"} else rest
    return data


def markdown(text: str, stamp: Stamp) -> str:
    """``text`` under a first-line HTML comment holding the stamp."""
    return f"{_MD_OPEN}{stamp.text()}{_MD_CLOSE}\n{text}"


def strip_markdown(text: str) -> str:
    """``text`` without its stamp line (to compare a generated page with a fresh generation)."""
    first, _, rest = text.partition("\n")
    return rest if first.startswith(_MD_OPEN) and first.endswith(_MD_CLOSE) else text


def csv_comment(stamp: Stamp) -> str:
    """The first line of a stamped CSV file, newline included: ``# provenance {...}``."""
    return f"{_CSV_OPEN}{stamp.text()}\n"


def png_metadata(stamp: Stamp) -> dict:
    """``savefig(path, metadata=png_metadata(stamp))``: the stamp as a PNG text chunk, and the software."""
    return {KEY: stamp.text(), "Software": f"kklcasadi {stamp.version}"}


def _png_text(path: Path) -> dict:
    """The tEXt/zTXt/iTXt chunks of a PNG file, ``{keyword: text}``."""
    data = path.read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise error(str(path), "a PNG file", Text("another format"))
    chunks, at = {}, 8
    while at + 8 <= len(data):
        size = int.from_bytes(data[at:at + 4], "big")
        kind, body = data[at + 4:at + 8], data[at + 8:at + 8 + size]
        at += 12 + size
        if kind == b"tEXt":
            key, _, value = body.partition(b"\0")
            chunks[key.decode("latin-1")] = value.decode("latin-1")
        elif kind == b"zTXt":
            key, _, value = body.partition(b"\0")
            chunks[key.decode("latin-1")] = zlib.decompress(value[1:]).decode("latin-1")
        elif kind == b"iTXt":
            key, _, rest = body.partition(b"\0")
            compressed, rest = rest[0], rest[2:]
            _language, _, rest = rest.partition(b"\0")
            _translated, _, value = rest.partition(b"\0")
            chunks[key.decode("latin-1")] = (zlib.decompress(value) if compressed else value).decode("utf-8")
        elif kind == b"IEND":
            break
    return chunks


def read(path: str | os.PathLike) -> Optional[Stamp]:
    """The stamp a file carries (JSON, markdown, CSV, PNG, or any text file with a markdown or CSV
    stamp line first), or None where it carries none.

    Raises
    ------
    ValueError
        A stamp that is there but malformed (names the file).
    """
    path = Path(path)
    where = f"{path}: {KEY}"
    if path.suffix == ".png":
        payload = _png_text(path).get(KEY)
        return None if payload is None else Stamp.from_json(_loads(payload, where), where)
    if path.suffix == ".json":
        data = _loads(path.read_text(), str(path))
        return Stamp.from_json(data[KEY], where) if isinstance(data, Mapping) and KEY in data else None
    with open(path, encoding="utf-8", errors="replace") as stream:
        first = stream.readline().rstrip("\n")
    if first.startswith(_MD_OPEN) and first.endswith(_MD_CLOSE):
        return Stamp.from_json(_loads(first[len(_MD_OPEN):-len(_MD_CLOSE)], where), where)
    if first.startswith(_CSV_OPEN):
        return Stamp.from_json(_loads(first[len(_CSV_OPEN):], where), where)
    return None


def _loads(text: str, where: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(where, "valid JSON", Text(f"{exc.msg} at character {exc.pos}")) from None
