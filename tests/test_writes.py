"""Writes that cannot be half done or collide (kklcasadi.writes): a new target is an exclusive create (of two
writers exactly one wins), a replaced directory is swapped in one step with the files that are not the
writer's carried over, and the C files and model files go through it."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import one_winner, race

from kklcasadi import writes
from kklcasadi.model.files import CARD_FILE, WEIGHTS_FILE, load_model, save_model

ROOT = Path(__file__).resolve().parents[1]


def test_write_file_is_exclusive_unless_overwriting(tmp_path):
    path = writes.write_file(tmp_path / "a" / "x.txt", "one")
    assert path.read_text() == "one"
    with pytest.raises(FileExistsError, match="x.txt exists; pass overwrite"):
        writes.write_file(path, "two")
    assert path.read_text() == "one"
    writes.write_file(path, b"three", overwrite=True)
    assert path.read_text() == "three" and sorted(os.listdir(path.parent)) == ["x.txt"]
    with pytest.raises(ValueError, match="--out: expected a file path, received .* It is a directory"):
        writes.write_file(tmp_path, "x", argument="--out")


def test_refuse_existing_names_the_argument_of_the_first_output_that_exists(tmp_path):
    (tmp_path / "page.md").write_text("old")
    (tmp_path / "models").mkdir()
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    writes.refuse_existing({tmp_path / "new.json": "--results", tmp_path / "sub" / "x": "--out"})   # nothing there
    for path, flag in (("page.md", "--page"), ("models", "--out"), ("dangling", "--results")):
        with pytest.raises(FileExistsError, match=f"^{flag}: .*{path} exists and this command does not overwrite; "
                           f"move it away, or choose another {flag}.$"):
            writes.refuse_existing({tmp_path / "new.json": "--results", tmp_path / path: flag})
    assert (tmp_path / "page.md").read_text() == "old" and not (tmp_path / "sub").exists()


def test_write_files_writes_one_directory_at_a_time_and_never_over_a_file(tmp_path):
    files = {tmp_path / "results" / "r.json": "{}\n", tmp_path / "docs" / "r.md": "# r\n",
             tmp_path / "results" / "r.png": b"\x89PNG"}
    assert writes.write_files(files, argument="--results") == list(files)
    assert [path.read_bytes() for path in files] == [b"{}\n", b"# r\n", b"\x89PNG"]
    (tmp_path / "docs" / "r.md").write_text("kept")
    again = {tmp_path / "results" / "s.json": "{}\n", tmp_path / "docs" / "r.md": "new"}
    with pytest.raises(FileExistsError, match="^--page: .*r.md exists"):
        writes.write_files(again, argument="--page")
    assert (tmp_path / "docs" / "r.md").read_text() == "kept" and (tmp_path / "results" / "s.json").exists()
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["docs", "r.json", "r.md", "r.png", "results", "s.json"]


def test_write_dir_publishes_a_new_directory_with_one_rename(tmp_path, monkeypatch):
    renames = []
    real = os.rename
    monkeypatch.setattr(writes.os, "rename", lambda a, b: (renames.append((a, b)), real(a, b))[1])
    target = writes.write_dir(tmp_path / "new", {"a.c": "A", "a.h": "H"})
    assert len(renames) == 1 and Path(renames[0][1]) == target
    assert sorted(os.listdir(target)) == ["a.c", "a.h"] and sorted(os.listdir(tmp_path)) == ["new"]


def test_write_dir_swaps_an_existing_directory_and_carries_the_other_files(tmp_path):
    target = tmp_path / "c"
    writes.write_dir(target, {"a.c": "old", "a.h": "old"})
    (target / "a").write_text("binary the user built")
    os.symlink("a", target / "link")
    inode = target.stat().st_ino
    with pytest.raises(FileExistsError, match="a.c exists; pass overwrite"):
        writes.write_dir(target, {"a.c": "new", "a.h": "new"})
    writes.write_dir(target, {"a.c": "new", "a.h": "new"}, overwrite=True)
    assert target.stat().st_ino != inode                                      # swapped, not rewritten in place
    assert {p.name: p.read_text() for p in target.iterdir() if not p.is_symlink()} == \
        {"a.c": "new", "a.h": "new", "a": "binary the user built"}
    assert os.readlink(target / "link") == "a" and sorted(os.listdir(tmp_path)) == ["c"]
    writes.write_dir(target, {"b.c": "other name"})                         # other names: no overwrite needed
    assert (target / "a.c").read_text() == "new" and (target / "b.c").read_text() == "other name"


def test_staged_publishes_what_the_block_wrote_as_one_or_nothing(tmp_path, monkeypatch):
    target = tmp_path / "report"
    writes.write_dir(target, {"table.md": "old", "plot.png": "old", "notes.txt": "the user's"})
    inode = target.stat().st_ino
    with pytest.raises(RuntimeError, match="the plot failed"):
        with writes.staged(target, overwrite=True) as stage:
            (stage / "table.md").write_text("new")
            raise RuntimeError("the plot failed")
    assert {p.name: p.read_text() for p in target.iterdir()} == \
        {"table.md": "old", "plot.png": "old", "notes.txt": "the user's"}           # nothing of the failed report
    published = []
    write_dir = writes.write_dir
    monkeypatch.setattr(writes, "write_dir", lambda *a, **k: (published.append(a[1]), write_dir(*a, **k))[1])
    with writes.staged(target, overwrite=True) as stage:
        (stage / "table.md").write_text("new")
        (stage / "plot.png").write_bytes(b"new")
        assert (target / "table.md").read_text() == "old" and target not in stage.parents     # not yet published
    assert published == [{"plot.png": b"new", "table.md": b"new"}]                  # one write_dir: one rename
    assert target.stat().st_ino != inode
    assert {p.name: p.read_text() for p in target.iterdir()} == \
        {"table.md": "new", "plot.png": "new", "notes.txt": "the user's"}
    assert sorted(os.listdir(tmp_path)) == ["report"] and not stage.exists()
    with pytest.raises(FileExistsError, match="--out: .*table.md exists"):
        with writes.staged(target, argument="--out") as stage:
            (stage / "table.md").write_text("newer")
    assert (target / "table.md").read_text() == "new"


def test_write_dir_drops_the_writers_own_old_files(tmp_path):
    target = tmp_path / "m"
    writes.write_dir(target, {"card.json": "1", "history.png": "old"})
    (target / ".train").mkdir()
    (target / ".train" / "x.ckpt.npz").write_text("checkpoint")
    writes.write_dir(target, {"card.json": "2"}, overwrite=True, owned=("history.png", ".train"))
    assert sorted(os.listdir(target)) == ["card.json"] and sorted(os.listdir(tmp_path)) == ["m"]


def test_a_directory_that_holds_another_directory_is_written_file_by_file(tmp_path):
    target = tmp_path / "shared"
    (target / "sub").mkdir(parents=True)
    (target / "sub" / "keep.txt").write_text("keep")
    inode = target.stat().st_ino
    writes.write_dir(target, {"a.c": "A"})
    assert target.stat().st_ino == inode and (target / "sub" / "keep.txt").read_text() == "keep"
    assert (target / "a.c").read_text() == "A" and sorted(os.listdir(tmp_path)) == ["shared"]


def test_write_dir_refuses_names_with_paths_and_a_file_target(tmp_path):
    with pytest.raises(ValueError, match="files: expected plain file names, received '../x'"):
        writes.write_dir(tmp_path / "d", {"../x": "x"})
    (tmp_path / "f").write_text("")
    with pytest.raises(ValueError, match="--c: expected a directory"):
        writes.write_dir(tmp_path / "f", {"a": "x"}, argument="--c")


def _save(path, seed, barrier, results):
    card = load_model(ROOT / "models" / "duffing" / "autonomous")
    arrays = {name: np.asarray(a) + seed for name, a in card.arrays.items()}
    barrier.wait()
    try:
        save_model(path, arrays, {k: v for k, v in card.card.items()})
        results.put((seed, "wrote"))
    except FileExistsError as exc:
        results.put((seed, str(exc)))


def test_two_saves_of_one_new_model_exactly_one_wins(tmp_path):
    shipped = load_model(ROOT / "models" / "duffing" / "autonomous")
    for attempt in range(5):
        path = tmp_path / f"model{attempt}"
        winner = one_winner(race(_save, [(path, 1), (path, 2)], timeout=120), "exists", "another writer")
        model = load_model(path)                                              # the winner's model, whole
        name = next(iter(model.arrays))
        assert np.array_equal(model.arrays[name], shipped.arrays[name] + winner)
        assert sorted(os.listdir(path)) == [CARD_FILE, WEIGHTS_FILE]


def _command(*args, cwd=None):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "kklcasadi", *args], capture_output=True, text=True, env=env,
                          cwd=cwd)


def test_the_command_line_does_not_write_into_a_shipped_model(tmp_path):
    shipped = ROOT / "models" / "duffing" / "autonomous"
    before = {p.name: p.read_bytes() for p in shipped.iterdir()}
    for args in (["export", str(shipped), "--c", str(shipped), "--overwrite"],
                 ["export", str(shipped), "--casadi", str(shipped / "step.casadi")],
                 ["train", "--system", "duffing", "--method", "autonomous", "--epochs", "1", "--out", str(shipped),
                  "--overwrite"],
                 ["demo", "--out", str(shipped / "demo.png")]):
        result = _command(*args)
        assert result.returncode == 2, result.stderr
        assert result.stderr.count("\n") == 1 and "ships with kklcasadi, read-only" in result.stderr
    assert {p.name: p.read_bytes() for p in shipped.iterdir()} == before


def test_an_out_that_is_a_directory_is_one_line(tmp_path):
    for args in (["demo", "--out", str(tmp_path)],
                 ["certificate", str(ROOT / "models" / "duffing" / "autonomous"), "--out", str(tmp_path)],
                 ["export", str(ROOT / "models" / "duffing" / "autonomous"), "--casadi", str(tmp_path)]):
        result = _command(*args)
        assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
        assert "--out" in result.stderr or "--casadi" in result.stderr
        assert "expected a file path, received a directory" in result.stderr
