"""kklcasadi tune does not lose a study: one ``--out`` holds one study (a second is refused), an empty or corrupt
storage is refused without touching ``trials/``, workers started at the same moment on a new SQLite storage do not
race on its tables, and every storage error is one line."""

import os
import re
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import race

optuna = pytest.importorskip("optuna", reason="the tune extra is not installed: pip install 'kklcasadi[tune]'")
pytest.importorskip("kklcasadi.train", reason="tune trains observers (torch)")

from kklcasadi.evaluation import tune as tn  # noqa: E402
from kklcasadi.evaluation.tune import storage as st  # noqa: E402
from kklcasadi.plant.systems import get  # noqa: E402
from kklcasadi.validation import ArgumentError  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _tune(out, *extra):
    return subprocess.run([sys.executable, "-m", "kklcasadi", "tune", "--system", "duffing", "--trials", "1", "--runs",
                           "32", "--epochs", "2", "--val-trials", "2", "--quiet", "--out", str(out), *extra],
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})


def _trials(out):
    """A study's trials/ as a previous run left it."""
    trial = out / "trials" / "0000"
    trial.mkdir(parents=True)
    (trial / "card.json").write_text("{}")
    return {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("content,received", [(b"", "an empty file"),
                                              (b"not a database at all" * 50, "a file that is not a SQLite database")])
def test_an_empty_or_corrupt_study_db_is_refused_without_touching_trials(tmp_path, content, received):
    out = tmp_path / "out"
    before = _trials(out)
    (out / "study.db").write_bytes(content)
    before[out / "study.db"] = content
    result = _tune(out)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert f"--storage: expected the study's SQLite database, received {out / 'study.db'}, {received}" in result.stderr
    assert {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before


def test_a_storage_that_lost_its_study_is_refused_without_touching_trials(tmp_path):
    out = tmp_path / "out"
    before = _trials(out)
    fresh = f"sqlite:///{tmp_path / 'fresh.db'}"              # a valid, new database: it has no study
    result = _tune(out, "--storage", fresh)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "--storage: expected the study 'duffing-bank' that" in result.stderr and "has no such study" in result.stderr
    assert {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before


def test_a_second_study_in_one_out_is_refused(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / tn.study.BINDING).write_text('{"study": "first", "storage": "sqlite:///x.db"}')
    with pytest.raises(ArgumentError, match=r"out_dir: expected the directory of the study 'first' on sqlite:///x.db "
                                            r".*received the study 'duffing-bank'"):
        tn.tune(get("duffing"), "bank", out, n_trials=1, progress=False)
    result = _tune(out, "--study", "second")
    assert result.returncode == 2 and result.stderr.startswith("error: --out: expected the directory of the study "
                                                               "'first'"), result.stderr


@pytest.mark.parametrize("text, received", [("{", "a parse error"), ('["first"]', "a JSON list")])
def test_an_unreadable_binding_is_one_line(tmp_path, text, received):
    out = tmp_path / "out"
    out.mkdir()
    (out / tn.study.BINDING).write_text(text)
    with pytest.raises(ArgumentError, match=f"^{out / tn.study.BINDING}: expected .*received {received}.* Restore "
                                            r"it, or give the study another --out \(study.json binds"):
        tn.tune(get("duffing"), "bank", out, n_trials=1, progress=False)
    assert (out / tn.study.BINDING).read_text() == text and sorted(p.name for p in out.iterdir()) == ["study.json"]


@pytest.mark.parametrize("url,match", [
    ("postgresql://user@host:notaport/db", r"--storage: expected an SQLAlchemy URL such as .*received postgresql://\.\.\."),
    ("postgresql://kkl@127.0.0.1:1/db", r"--storage: expected a storage Optuna can open and use, received "
                                        r"postgresql://kkl@127.0.0.1:1/db: \(psycopg.OperationalError\) connection"),
    ("nonsense", r"--storage: expected a storage Optuna can open and use, received 'nonsense': Could not parse"),
    ("mysql://u@h/db", r"--storage: expected a storage Optuna can open and use, received mysql://u@h/db: Failed to "
                       r"import DB access module"),
])
def test_storage_errors_are_one_line(tmp_path, url, match):
    if url.startswith("postgresql://kkl"):
        pytest.importorskip("psycopg")
    result = _tune(tmp_path / "out", "--storage", url)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert re.search(match, result.stderr), result.stderr
    assert not (tmp_path / "out" / "trials").exists()


def test_a_locked_study_db_is_one_line(tmp_path, monkeypatch):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    st.open_storage(url, 30)                                       # a valid, new study database
    monkeypatch.setattr(st, "SQLITE_TIMEOUT", 0.3)
    holder = sqlite3.connect(tmp_path / "study.db", isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")                              # another program holds it
    try:
        t0 = time.perf_counter()
        with pytest.raises(ArgumentError) as info:
            storage = st.open_storage(url, 30)
            with st.storage_errors(url):
                optuna.create_study(study_name="s", storage=storage, load_if_exists=True)
        assert time.perf_counter() - t0 < 30
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    assert "\n" not in str(info.value) and "database is locked" in str(info.value)
    assert str(info.value).startswith("storage: expected a storage Optuna can open and use")


def _open(url, barrier, results):
    try:
        barrier.wait()
        storage = st.open_storage(url, 30)
        optuna.create_study(study_name="s", storage=storage, load_if_exists=True)
        results.put("ok")
    except Exception as exc:  # the test reports whatever a worker raised
        results.put(f"{type(exc).__name__}: {exc}")


def test_workers_started_at_the_same_moment_on_a_new_sqlite_storage(tmp_path):
    for attempt in range(6):
        url = f"sqlite:///{tmp_path / f'study{attempt}.db'}"
        assert race(_open, [(url,)] * 3, timeout=120) == ["ok"] * 3
