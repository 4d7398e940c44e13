"""results/ is traceable: every file names the command and commit that made it in its own content, the tree is
results/<study>/<system>/, and the index is what benchmarks/results_index.py writes from the stamps."""

import re
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from kklcasadi import provenance

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
SCRIPT = ROOT / "benchmarks" / "results_index.py"
FILES = sorted(str(p.relative_to(RESULTS)) for p in RESULTS.rglob("*") if p.is_file())


@pytest.fixture(scope="module")
def index():
    sys.path.insert(0, str(SCRIPT.parent))                       # the script imports its sibling pages.py
    try:
        return runpy.run_path(str(SCRIPT))
    finally:
        sys.path.remove(str(SCRIPT.parent))


def test_every_file_names_its_command_and_commit(index):
    untraced = []
    for name in FILES:
        path = RESULTS / name
        stamp = index["stamp_of"](path)               # a weights.npz: its card's, which holds their SHA-256
        if not (stamp.command.strip() and re.fullmatch(r"[0-9a-f]{40}(-dirty)?", stamp.commit)
                and (not stamp.retroactive or "retroactive stamp" in stamp.note)
                and (path.suffix == ".npz" or provenance.read(path) == stamp)):
            untraced.append(name)
    assert untraced == []


def test_the_tree_is_study_system_file(index):
    assert len(FILES) > 250
    for name in FILES:
        parts = Path(name).parts
        assert len(parts) >= 3 and parts[0] in index["STUDIES"] or name == "README.md", name


def test_the_index_is_what_the_script_writes_from_the_stamps(index):
    assert provenance.strip_markdown(index["INDEX"].read_text()) == index["index"](), \
        "results/README.md is stale: run python benchmarks/results_index.py"
    assert provenance.read(index["INDEX"]).command == "python benchmarks/results_index.py"


def test_a_file_without_a_stamp_is_named(index, tmp_path, monkeypatch):
    (tmp_path / "protocol" / "x").mkdir(parents=True)
    (tmp_path / "protocol" / "x" / "t.md").write_text("| a |\n")
    monkeypatch.setitem(index["index"].__globals__, "RESULTS", tmp_path)
    monkeypatch.setitem(index["index"].__globals__, "ROOT", tmp_path.parent)
    with pytest.raises(SystemExit, match=r"protocol/x/t\.md: no provenance stamp"):
        index["index"]()


def test_the_check_flag_says_when_the_index_is_stale(monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(SCRIPT.parent))
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), "--check"])
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    assert done.value.code == 0


def test_a_page_is_replaced_whole_or_not_at_all(monkeypatch, tmp_path, capsys):
    """benchmarks/pages.py: a page is regenerated in place (its command's one output), atomically: a page that
    fails to compute or to write leaves the old one whole and nothing beside it."""
    import os

    monkeypatch.syspath_prepend(str(SCRIPT.parent))
    publish = runpy.run_path(str(SCRIPT.parent / "pages.py"))["publish"]
    assert publish("x.md", lambda: "# x\n", [], folder=tmp_path) == 0
    assert provenance.strip_markdown((tmp_path / "x.md").read_text()) == "# x\n"
    assert publish("x.md", lambda: "# y\n", [], folder=tmp_path) == 0
    old = (tmp_path / "x.md").read_bytes()
    assert provenance.strip_markdown(old.decode()) == "# y\n" and provenance.read(tmp_path / "x.md").command

    def failing(*args):
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        publish("x.md", failing, [], folder=tmp_path)
    monkeypatch.setattr(os, "fsync", failing)
    with pytest.raises(OSError, match="disk full"):
        publish("x.md", lambda: "# z\n", [], folder=tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["x.md"] and (tmp_path / "x.md").read_bytes() == old
    assert publish("x.md", lambda: "# z\n", ["--check"], folder=tmp_path) == 1          # stale: says so


STAMPED = [p for top in ("results", "docs", "models") for p in sorted((ROOT / top).rglob("*"))
           if p.is_file() and p.suffix in (".md", ".json", ".csv", ".png")] + [ROOT / "README.md"]


def _git(*args: str) -> "subprocess.CompletedProcess[str]":
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=60)


def test_every_stamped_commit_is_in_the_history():
    """A stamp's commit can be checked out from a clone: results made on a branch that was rebased before it
    landed name a commit outside main's history unless that commit is merged in (`git merge -s ours COMMIT`
    leaves the tree as it is)."""
    if shutil.which("git") is None or _git("rev-parse", "--show-toplevel").returncode != 0:
        pytest.skip("not a git checkout: the history cannot be read")
    if _git("rev-parse", "--is-shallow-repository").stdout.strip() == "true":
        pytest.skip("a shallow clone holds part of the history only")
    commits: dict[str, list[str]] = {}
    for path in STAMPED:
        for found in re.finditer(rb'"commit"\s*:\s*"([0-9a-f]{40})(?:-dirty)?"', path.read_bytes()):
            commits.setdefault(found.group(1).decode(), []).append(str(path.relative_to(ROOT)))
    assert len(commits) > 20
    outside = {c: files for c, files in commits.items() if _git("merge-base", "--is-ancestor", c, "HEAD").returncode}
    assert outside == {}, "stamps naming commits outside the history (merge them in with git merge -s ours)"
