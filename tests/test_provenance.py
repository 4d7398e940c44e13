"""Provenance stamps: what they record, each file format's round trip, and the commit in and out of a checkout."""

import json
import subprocess
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest

from kklcasadi import provenance
from kklcasadi.plant import logs
from kklcasadi.version import __version__

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def stamp():
    return provenance.stamp(seeds={"trials": 2026, "training": 11}, command="kklcasadi evaluate models/vdp/bank --ekf")


def test_a_stamp_records_the_command_commit_versions_seeds_and_time(stamp):
    import casadi

    assert stamp.command == "kklcasadi evaluate models/vdp/bank --ekf" and stamp.seeds == {"trials": 2026,
                                                                                             "training": 11}
    assert stamp.version == __version__ and stamp.casadi == casadi.__version__ and not stamp.retroactive
    age = datetime.now(timezone.utc) - datetime.fromisoformat(stamp.time)
    assert 0 <= age.total_seconds() < 60 and stamp.time.endswith("+00:00")
    assert provenance.Stamp.from_json(json.loads(json.dumps(stamp.to_json()))) == stamp


def test_the_commit_is_the_checkouts_head_with_its_changes_marked():
    git = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    if git.returncode != 0:
        pytest.skip("the package does not run from a git checkout here")
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True, check=True).stdout.strip()
    assert provenance.commit() == git.stdout.strip() + ("-dirty" if dirty else "")


def test_outside_a_checkout_of_the_package_the_commit_is_unknown(tmp_path, monkeypatch):
    provenance.commit.cache_clear()
    try:
        monkeypatch.setattr(provenance, "_ROOT", tmp_path)                 # not a repository at all
        assert provenance.commit() == "unknown"
        provenance.commit.cache_clear()
        subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)    # a copy inside another repository
        monkeypatch.setattr(provenance, "_ROOT", tmp_path / "site-packages")
        (tmp_path / "site-packages").mkdir()
        assert provenance.commit() == "unknown"
        stamp = provenance.stamp(command="x")
        assert stamp.commit == "unknown" and stamp.version == __version__
    finally:
        provenance.commit.cache_clear()


@pytest.mark.parametrize("argv, expected", [
    (["/venv/bin/kklcasadi", "evaluate", "models/vdp/bank", "--labels", "a b"],
     "kklcasadi evaluate models/vdp/bank --labels 'a b'"),
    (["/x/kklcasadi/__main__.py", "demo"], "python -m kklcasadi demo"),
    (["benchmarks/summarize.py", "--out", "docs/results"], "python benchmarks/summarize.py --out docs/results"),
    ([], "python"),
])
def test_the_command_line_reads_as_typed(argv, expected):
    assert provenance.command_line(argv) == expected


def test_an_absolute_script_path_under_the_current_folder_is_shown_relative(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert provenance.command_line([str(tmp_path / "b" / "s.py"), "1"]) == "python b/s.py 1"
    assert provenance.command_line(["/elsewhere/s.py"]) == "python /elsewhere/s.py"


def test_json_markdown_csv_and_png_round_trip(stamp, tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (tmp_path / "a.json").write_text(json.dumps(provenance.json_record({"x": 1}, stamp)))
    (tmp_path / "b.json").write_text(json.dumps(provenance.json_record([{"x": 1}, {"x": 2}], stamp)))
    (tmp_path / "c.md").write_text(provenance.markdown("| a |\n|---|\n", stamp))
    (tmp_path / "d.csv").write_text(provenance.csv_comment(stamp) + "time,y\n0,1\n0.1,2\n")
    fig, ax = plt.subplots()
    ax.plot([0, 1])
    fig.savefig(tmp_path / "e.png", metadata=provenance.png_metadata(stamp))
    plt.close(fig)
    for name in ("a.json", "b.json", "c.md", "d.csv", "e.png"):
        assert provenance.read(tmp_path / name) == stamp, name
    assert provenance.json_payload(json.loads((tmp_path / "a.json").read_text())) == {"x": 1}
    assert provenance.json_payload(json.loads((tmp_path / "b.json").read_text())) == [{"x": 1}, {"x": 2}]
    assert provenance.json_payload([1, 2]) == [1, 2]                          # an unstamped record as it is
    assert provenance.strip_markdown((tmp_path / "c.md").read_text()) == "| a |\n|---|\n"
    assert provenance.strip_markdown("| a |\n") == "| a |\n"
    rows = np.loadtxt(tmp_path / "d.csv", delimiter=",", comments="#", skiprows=2)      # numpy: the stamp and header
    assert rows[:, 1].tolist() == [1.0, 2.0]


def test_files_without_a_stamp_read_none(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (tmp_path / "a.json").write_text("[1, 2]")
    (tmp_path / "b.md").write_text("# title\n")
    fig = plt.figure()
    fig.savefig(tmp_path / "c.png")
    plt.close(fig)
    assert [provenance.read(tmp_path / n) for n in ("a.json", "b.md", "c.png")] == [None, None, None]


def test_a_retroactive_stamp_says_so(tmp_path):
    stamp = provenance.Stamp(command="kklcasadi evaluate models/vdp/* --ekf", commit="f" * 40,
                             time="2025-01-01T00:00:00+00:00", retroactive=True,
                             note="from docs/claims.md and the commit that added the file")
    path = tmp_path / "t.md"
    path.write_text(provenance.markdown("x\n", stamp))
    back = provenance.read(path)
    assert back.retroactive and back.note.startswith("from docs/claims.md") and back.python == "unknown"
    assert "retroactive" not in provenance.stamp(command="x").to_json()


@pytest.mark.parametrize("text, message", [
    ('<!-- provenance {"command": "x"} -->\n', r"t\.md: provenance: expected a stamp naming its command and commit, "
                                              r"received no commit"),
    ('<!-- provenance {"command": "x", "commit": "a", "colour": 1} -->\n', r"unknown fields \['colour'\]"),
    ("<!-- provenance {nope} -->\n", r"t\.md: provenance: expected valid JSON"),
    ('<!-- provenance {"command": "", "commit": "a"} -->\n', r"^command: expected a non-empty string"),
])
def test_a_malformed_stamp_is_named(tmp_path, text, message):
    path = tmp_path / "t.md"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        provenance.read(path)


def test_a_record_is_stamped_once(stamp):
    with pytest.raises(ValueError, match=r"^record: expected a record without a 'provenance' key"):
        provenance.json_record(provenance.json_record({"x": 1}, stamp), stamp)
    with pytest.raises(TypeError, match=r"^record: expected a dict or a list, received str"):
        provenance.json_record("x", stamp)


def test_a_stamped_csv_reads_as_a_log_with_the_files_line_numbers(stamp, tmp_path):
    path = tmp_path / "log.csv"
    t = np.arange(6) * 0.1
    path.write_text(provenance.csv_comment(stamp) + "time,y\n" + "".join(f"{float(v)!r},{float(v)!r}\n" for v in t))
    log = logs.read_log(path, time_col="time", y_cols=("y",), dt=0.1)
    np.testing.assert_array_equal(log.y[:, 0], t)
    path.write_text(provenance.csv_comment(stamp) + "time,y\n0.0,1\n0.1,abc\n0.2,3\n")
    with pytest.raises(ValueError, match=r"row 1 \(line 4\), column 'y': expected a plain decimal number"):
        logs.read_log(path, time_col="time", y_cols=("y",), dt=0.1)
