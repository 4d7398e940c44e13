"""Property tests of the log reader (issue 47): random mutations of a valid log are either read unchanged in
meaning or refused with a one-line ValueError, never a traceback and never a silent change.

Three families: mutations that keep the meaning (columns reordered, other columns added, blanks, quotes, a
byte-order mark, CRLF, blank and comment lines, other spellings of the same numbers) must give the same log;
mutations that break a field the model reads (a character no plain decimal number holds, a non-finite word,
a field dropped or added, a time moved back) must be refused in one line naming where; any mutation of the
bytes at all must give a log or a one-line ValueError."""

import math

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from kklcasadi.plant.logs import read_log  # noqa: E402

DT = 0.01
PROPERTY = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@st.composite
def logs(draw):
    """A valid log: (header, rows of strings, the float table of time, y, u)."""
    n = draw(st.integers(3, 25))
    steps = draw(st.lists(st.floats(0.98, 1.02), min_size=n - 1, max_size=n - 1))
    t = np.concatenate([[draw(st.floats(-10, 10))], np.zeros(n - 1)])
    t[1:] = t[0] + np.cumsum(np.array(steps) * DT)
    y = np.array(draw(st.lists(finite, min_size=n, max_size=n)))
    u = np.array(draw(st.lists(finite, min_size=n, max_size=n)))
    table = np.column_stack([t, y, u])
    return ["time", "y", "u"], [[repr(float(v)) for v in row] for row in table], table


def text_of(header, rows, newline="\n"):
    return newline.join(",".join(row) for row in [header, *rows]) + newline


def read(path):
    log = read_log(path, time_col="time", y_cols=("y",), u_cols=("u",), dt=DT)
    return log.t, log.y, log.u


def spellings(value):
    """Other ways to write the same float."""
    forms = [repr(value), f"{value:.17g}", f"{value:.17e}", f"{value:.17E}", f'"{value!r}"', f" {value!r}\t"]
    if math.copysign(1.0, value) > 0:                                 # not -0.0
        forms.append(f"+{value!r}")
    return forms


@PROPERTY
@given(data=logs(), choices=st.data())
def test_meaning_preserving_mutations_read_the_same(tmp_path, data, choices):
    header, rows, _ = data
    path = tmp_path / "log.csv"
    path.write_text(text_of(header, rows), encoding="utf-8")
    expected = read(path)
    order = choices.draw(st.permutations(range(3)))
    extra = choices.draw(st.lists(st.text(st.characters(min_codepoint=32, max_codepoint=0x2FF,
                                                          blacklist_characters=',"'), max_size=8), max_size=3))
    names = [header[i] for i in order] + [f"extra{i}" for i in range(len(extra))]
    body = []
    for row in rows:
        fields = [choices.draw(st.sampled_from(spellings(float(row[i])))) for i in order]
        body.append(fields + [f'"{e}"' for e in extra])
    lines = [",".join(names)] + [",".join(row) for row in body]
    for _ in range(choices.draw(st.integers(0, 3))):                # blank and comment lines, anywhere
        lines.insert(choices.draw(st.integers(0, len(lines))), choices.draw(st.sampled_from(["", "# note, 1,2", "#"])))
    newline = choices.draw(st.sampled_from(["\n", "\r\n"]))
    text = ("\ufeff" if choices.draw(st.booleans()) else "") + newline.join(lines) + newline
    path.write_text(text, encoding="utf-8", newline="")
    for got, want in zip(read(path), expected):
        np.testing.assert_array_equal(got, want)


#: Characters no plain decimal number holds wherever they go (no digit, sign, point or exponent).
POISON = ["_", "x", "\u0661", "\u0966", "\uff11", "\u2212", "\u00a0", "a", ";", "'", "%", "\\", "/", "\x00"]


@PROPERTY
@given(data=logs(), choices=st.data())
def test_a_broken_field_is_refused_in_one_line(tmp_path, data, choices):
    header, rows, table = data
    k = choices.draw(st.integers(0, len(rows) - 1))
    c = choices.draw(st.integers(0, 2))
    kind = choices.draw(st.sampled_from(["poison", "non-finite", "drop", "add", "time back"]))
    rows = [list(row) for row in rows]
    if kind == "poison":
        field = rows[k][c]
        at = choices.draw(st.integers(0, len(field)))
        rows[k][c] = field[:at] + choices.draw(st.sampled_from(POISON)) + field[at:]
        pattern = rf"row {k} \(line {k + 2}\), column '{header[c]}': expected a plain decimal number"
    elif kind == "non-finite":
        rows[k][c] = choices.draw(st.sampled_from(["nan", "NaN", "inf", "-Infinity", "+inf", "1e999", "-1e400"]))
        pattern = rf"row {k} \(line {k + 2}\), column '{header[c]}': expected a finite number"
    elif kind == "drop":
        del rows[k][c]
        pattern = rf"row {k} \(line {k + 2}\): expected 3 fields \(one per header column\), received 2"
    elif kind == "add":
        rows[k].insert(c, repr(float(table[k, c])))
        pattern = rf"row {k} \(line {k + 2}\): expected 3 fields \(one per header column\), received 4"
    else:
        k = max(k, 1)
        rows[k][0] = repr(float(table[k - 1, 0]) - choices.draw(st.sampled_from([0.0, 1e-3, 5.0])))
        pattern = rf"row {k} \(line {k + 2}\), column 'time': expected a time after row {k - 1}'s"
    path = tmp_path / "log.csv"
    path.write_text(text_of(header, rows), encoding="utf-8")
    with pytest.raises(ValueError, match=pattern) as caught:
        read(path)
    assert "\n" not in str(caught.value)


HOSTILE = list("0123456789.,-+eE \t\r\n#\"'_x") + ["\ufeff", "\u0661", "\x00", "nan", "inf", "\u00e9"]


@PROPERTY
@given(data=logs(), edits=st.lists(st.tuples(st.sampled_from(["insert", "delete", "replace"]), st.floats(0, 1),
                                             st.sampled_from(HOSTILE)), min_size=1, max_size=6),
       raw=st.booleans(), garbage=st.binary(max_size=8))
def test_any_mutation_is_a_log_or_one_line(tmp_path, data, edits, raw, garbage):
    header, rows, _ = data
    text = text_of(header, rows)
    for kind, where, piece in edits:
        at = min(int(where * len(text)), len(text) - 1)
        text = (text[:at] + piece + text[at:] if kind == "insert" else text[:at] + text[at + 1:] if kind == "delete"
                else text[:at] + piece + text[at + 1:])
    content = text.encode("utf-8")
    if raw:                                                       # and bytes that need not be UTF-8
        at = len(content) // 2
        content = content[:at] + garbage + content[at:]
    path = tmp_path / "log.csv"
    path.write_bytes(content)
    try:
        t, y, u = read(path)
    except ValueError as exc:
        message = str(exc)
        assert "\n" not in message and "\r" not in message and len(message) < 2000, message
        return
    assert t.size >= 2 and np.all(np.isfinite(y)) and np.all(np.isfinite(u)) and np.all(np.diff(t) > 0)
    assert math.isclose(t[1] - t[0], DT, rel_tol=1e-9)
