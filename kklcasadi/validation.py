"""Argument checks shared by every module, with one error style.

Every message reads ``"<argument>: expected <what>, received <value>."``, optionally followed by
what to do about it. Wrong values raise :class:`ArgumentError` (a :class:`ValueError`), wrong types
:class:`ArgumentTypeError` (a :class:`TypeError`); both carry the parts of the message as fields
(``argument``, ``expected``, ``received``, ``hint``), which the command line reads to name its own flag.
"""

from __future__ import annotations

import math
from typing import Any, Collection, Optional

import numpy as np

__all__ = ["error", "ArgumentError", "ArgumentTypeError", "Text",
           "is_int", "is_number", "positive_int", "nonnegative_int", "positive_number",
           "nonnegative_number", "finite_number", "one_of", "finite_array", "index_tuple", "state_stds", "covariance"]


class Text(str):
    """A description of what was received, shown without quotes in error messages."""

    def __repr__(self) -> str:
        return str(self)


class _Fields:
    """The parts of the package's one error message, kept as fields beside the message."""

    def __init__(self, argument: str, expected: str, received: Any, hint: str = "") -> None:
        self.argument, self.expected, self.received, self.hint = argument, expected, received, hint
        super().__init__(f"{argument}: {self.detail}")

    @property
    def detail(self) -> str:
        """The message without its argument: ``"expected <what>, received <value>. <hint>"``."""
        message = f"expected {self.expected}, received {self.received!r}."
        return f"{message} {self.hint}" if self.hint else message

    def __reduce__(self) -> tuple:                 # picklable across processes, fields and all
        return type(self), (self.argument, self.expected, self.received, self.hint)


class ArgumentError(_Fields, ValueError):
    """A bad value: ``argument`` (a name, or ``"<file>: '<field>'"``), what was ``expected``, what was
    ``received`` (shown with ``repr``) and a ``hint`` (what to do; may be empty)."""


class ArgumentTypeError(_Fields, TypeError):
    """A value of the wrong type, with the fields of :class:`ArgumentError`."""


def error(argument: str, expected: str, received: Any, fix: str = "", *,
          kind: type[Exception] = ValueError) -> Exception:
    """Build the package's one error message.

    Parameters
    ----------
    argument : str
        What is wrong: an argument name, or ``"<file>: '<field>'"``.
    expected : str
        What was expected.
    received
        What was received, shown with ``repr`` (so ``"100"`` and ``100`` differ; wrap a
        description in :class:`Text` to show it as is).
    fix : str, optional
        What the user should do about it.
    kind : type
        ``ValueError`` (an :class:`ArgumentError` is returned) or ``TypeError`` (an
        :class:`ArgumentTypeError`).

    Returns
    -------
    ArgumentError or ArgumentTypeError
        To be raised by the caller.
    """
    if kind not in (ValueError, TypeError):
        raise ArgumentTypeError("kind", "ValueError or TypeError", Text(getattr(kind, "__name__", repr(kind))))
    return (ArgumentTypeError if kind is TypeError else ArgumentError)(argument, expected, received, fix)


def is_int(value: Any) -> bool:
    """Whether ``value`` is a Python or numpy integer (not a bool)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def is_number(value: Any) -> bool:
    """Whether ``value`` is a real Python or numpy number (not a bool)."""
    return is_int(value) or (isinstance(value, (float, np.floating)) and not isinstance(value, np.bool_))


def _integer(value: Any, argument: str, lowest: int, expected: str, fix: str) -> int:
    if not is_int(value):
        raise error(argument, expected, Text(type(value).__name__ if not is_number(value) else repr(value)),
                    fix, kind=TypeError)
    if value < lowest:
        raise error(argument, expected, value, fix)
    return int(value)


def positive_int(value: Any, argument: str, fix: str = "") -> int:
    """Return ``value`` as an int >= 1, else raise (TypeError for a non-integer)."""
    return _integer(value, argument, 1, "a positive int", fix)


def nonnegative_int(value: Any, argument: str, fix: str = "") -> int:
    """Return ``value`` as an int >= 0, else raise (TypeError for a non-integer)."""
    return _integer(value, argument, 0, "an int >= 0", fix)


def _real(value: Any, argument: str, expected: str, fix: str) -> float:
    if not is_number(value):
        raise error(argument, expected, Text(type(value).__name__), fix, kind=TypeError)
    if not math.isfinite(value):
        raise error(argument, expected, value, fix)
    return float(value)


def finite_number(value: Any, argument: str, fix: str = "") -> float:
    """Return ``value`` as a finite float, else raise."""
    return _real(value, argument, "a finite number", fix)


def positive_number(value: Any, argument: str, fix: str = "") -> float:
    """Return ``value`` as a finite float > 0, else raise."""
    out = _real(value, argument, "a finite number > 0", fix)
    if out <= 0:
        raise error(argument, "a finite number > 0", value, fix)
    return out


def nonnegative_number(value: Any, argument: str, fix: str = "") -> float:
    """Return ``value`` as a finite float >= 0, else raise."""
    out = _real(value, argument, "a finite number >= 0", fix)
    if out < 0:
        raise error(argument, "a finite number >= 0", value, fix)
    return out


def one_of(value: Any, argument: str, choices: Collection[Any], fix: str = "") -> Any:
    """Return ``value`` if it is one of ``choices``, else raise a ValueError listing them."""
    if value not in choices:
        raise error(argument, f"one of {list(choices)}", value, fix)
    return value


def finite_array(value: Any, argument: str, shape: Optional[tuple[int, ...]] = None) -> np.ndarray:
    """Return ``value`` as a float64 array (of ``shape`` if given) with finite entries, else raise."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise error(argument, "an array of real numbers", Text(type(value).__name__), kind=TypeError) from exc
    if shape is not None and array.shape != tuple(shape):
        raise error(argument, f"shape {tuple(shape)}", Text(f"shape {array.shape}"))
    if not np.all(np.isfinite(array)):
        raise error(argument, "finite values", Text("NaN or inf"))
    return array


def state_stds(value: Any, nx: int, argument: str = "process_std") -> float | np.ndarray:
    """A noise std for every state (a float) or one per state (an array (nx,)), all finite and >= 0, else raise."""
    if np.ndim(value) == 0:
        return nonnegative_number(value, argument)
    std = finite_array(value, argument)
    if std.shape != (nx,) or np.any(std < 0):
        raise error(argument, f"a number >= 0 or nx = {nx} of them (one per state)", std.tolist())
    return std


def covariance(value: Any, n: int, argument: str, *, definite: bool = False) -> np.ndarray:
    """Return ``value`` as a finite symmetric (n, n) float64 matrix, positive semi-definite (positive
    definite with ``definite``), else raise naming ``argument``."""
    m = finite_array(np.atleast_2d(np.asarray(value, dtype=float)), argument)
    if m.shape != (n, n):
        raise error(argument, f"shape {(n, n)}", Text(f"shape {m.shape}"))
    kind = "definite" if definite else "semi-definite"
    if not np.allclose(m, m.T):
        raise error(argument, f"a symmetric positive {kind} matrix", m.tolist())
    smallest = np.min(np.linalg.eigvalsh(0.5 * (m + m.T)))
    if smallest < 0 or (definite and smallest <= 0):
        raise error(argument, f"a symmetric positive {kind} matrix", m.tolist())
    return m


def index_tuple(value: Any, argument: str, n: int) -> tuple[int, ...]:
    """Return ``value`` (a sequence of distinct indices into ``n`` entries) as a sorted tuple of ints.

    Raises
    ------
    TypeError
        ``value`` is a string or not a sequence, or an entry is not an int (bools are not ints).
    ValueError
        An entry is outside ``[0, n)`` or repeated.
    """
    expected = f"a sequence of distinct indices in [0, {n})"
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple, range, np.ndarray)):
        raise error(argument, expected, Text(type(value).__name__), kind=TypeError)
    entries = list(np.asarray(value).ravel()) if isinstance(value, np.ndarray) else list(value)
    for entry in entries:
        if not is_int(entry):
            raise error(argument, expected, Text(f"an entry {entry!r} of type {type(entry).__name__}"),
                        kind=TypeError)
    out = [int(entry) for entry in entries]
    bad = [i for i in out if not 0 <= i < n]
    if bad:
        raise error(argument, expected, Text(f"{out} (out of range: {bad})"))
    if len(set(out)) != len(out):
        raise error(argument, expected, Text(f"{out} (repeated entries)"))
    return tuple(sorted(out))
