"""The package is typed (it ships ``py.typed``) and type-checked: mypy on ``kklcasadi`` (the settings of
pyproject.toml) finds no error that ``tests/mypy_baseline.txt`` does not list, and that list only shrinks (an
error fixed must leave it).

The baseline lists each error as ``path: error: message  [code]`` with its count, without line numbers (they
move with every edit). Write it again after fixing errors (and only then):

    python tests/test_types.py
"""

from __future__ import annotations

import configparser
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BASELINE = Path(__file__).with_name("mypy_baseline.txt")
#: ``path:line: error: message  [code]`` (mypy's default output; notes and the summary are other lines)
_ERROR = re.compile(r"^(?P<path>[^:\s]+\.py):\d+: error: (?P<message>.*)$")


def _errors(output: str) -> Counter:
    """mypy's errors in ``output``, keyed ``path: error: message`` (line numbers dropped), with their counts."""
    found = Counter()
    for line in output.splitlines():
        match = _ERROR.match(line.strip())
        if match:
            found[f"{match['path']}: error: {match['message']}"] += 1
    return found


def _mypy() -> Counter:
    result = subprocess.run([sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml")],
                            cwd=ROOT, capture_output=True, text=True)
    if result.returncode not in (0, 1) or not (_errors(result.stdout) or "Success" in result.stdout):
        raise RuntimeError(f"mypy did not run (exit {result.returncode}): {result.stderr or result.stdout}")
    return _errors(result.stdout)


def _read_baseline() -> Counter:
    counts = Counter()
    for line in BASELINE.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            count, _, key = line.partition(" ")
            counts[key] = int(count)
    return counts


def _write_baseline(errors: Counter) -> None:
    lines = [f"{count} {key}" for key, count in sorted(errors.items())]
    BASELINE.write_text("# mypy's errors on kklcasadi (count, then path: error: message), written by "
                        "`python tests/test_types.py`; it only shrinks\n" + "\n".join(lines) + "\n")


def test_the_package_ships_its_annotations():
    assert (ROOT / "kklcasadi" / "py.typed").is_file()
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    assert "py.typed" in [p.strip() for p in config["options.package_data"]["kklcasadi"].split(",")]
    assert "mypy" in config["options.extras_require"]["test"]


def test_the_baseline_is_read_as_written(tmp_path, monkeypatch):
    errors = Counter({"kklcasadi/a.py: error: Item \"None\" has no attribute \"x\"  [union-attr]": 2})
    monkeypatch.setattr(sys.modules[__name__], "BASELINE", tmp_path / "baseline.txt")
    _write_baseline(errors)
    assert _read_baseline() == errors
    output = "kklcasadi/a.py:3: error: Item \"None\" has no attribute \"x\"  [union-attr]\n" \
             "kklcasadi/a.py:9: note: see here\nFound 1 error in 1 file (checked 1 source file)\n"
    assert _errors(output) == Counter({"kklcasadi/a.py: error: Item \"None\" has no attribute \"x\"  [union-attr]": 1})


def test_mypy_finds_no_error_beyond_the_baseline():
    pytest.importorskip("mypy", reason="mypy is in the test extra: pip install -e '.[test]'")
    current, baseline = _mypy(), _read_baseline()
    new = current - baseline
    assert not new, ("type errors beyond tests/mypy_baseline.txt (fix them; the baseline only shrinks):\n"
                     + "\n".join(f"{count} x {key}" for key, count in sorted(new.items())))
    fixed = baseline - current
    assert not fixed, ("errors of tests/mypy_baseline.txt that mypy no longer finds: write the baseline again "
                       "(python tests/test_types.py):\n" + "\n".join(sorted(fixed)))


if __name__ == "__main__":
    _write_baseline(_mypy())
    print(f"wrote {BASELINE}: {sum(_read_baseline().values())} errors")
