"""examples/emps_rig.py in a reduced form: a tiny training budget, the raw 1 kHz log estimated and scored."""

import hashlib
import json
import runpy
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "emps_rig.py"


@pytest.fixture(scope="module")
def example():
    return runpy.run_path(str(EXAMPLE), run_name="emps_rig")


def test_the_development_part_is_the_logs_rows_before_the_split_as_logged(example, tmp_path):
    dev = example["write_development_part"](tmp_path)
    raw = example["DATA"].read_text().splitlines()
    lines = dev.read_text().splitlines()
    assert lines == raw[:len(lines)]                                  # the same text, a prefix of the log
    t = np.genfromtxt(dev, delimiter=",", names=True)["time"]
    assert t.max() < example["SPLIT"] <= float(raw[len(lines)].split(",")[0])
    assert abs(len(lines) - 1 - 0.6 * (len(raw) - 1)) <= 1           # the first 60 % of the rows


@pytest.fixture(scope="module")
def reduced(example, tmp_path_factory):
    """One run of the example on a tiny budget: (its folder, the scores it returned)."""
    tmp_path = tmp_path_factory.mktemp("emps")
    return tmp_path, example["main"](tmp_path, epochs=1, runs=12, horizon=4.0, results=tmp_path / "emps.json",
                                     page_path=tmp_path / "emps.md")


def test_example_runs_in_a_reduced_form(example, reduced):
    from kklcasadi import provenance

    tmp_path, table = reduced
    results, page = tmp_path / "emps.json", tmp_path / "emps.md"
    assert list(table) == list(example["ESTIMATORS"])
    for row in table.values():
        for part in ("development", "scored"):
            assert np.isfinite(row[part]["q"]) and np.isfinite(row[part]["q_dot"])
    ekf = table["EKF (noise from the log)"]["scored"]
    assert ekf["q"] < 1e-5 and ekf["q_dot"] < 1e-3                  # it follows the position it measures
    text = page.read_text()
    assert text.startswith("<!-- provenance") and "| EKF (noise from the log) |" in text and "chose nothing" in text
    record = provenance.json_payload(json.loads(results.read_text()))
    assert provenance.strip_markdown(text) == example["page"](record)
    assert record["cases"]["like"]["command"] == (
        "kklcasadi train --plant examples/emps/emps_plant.py:make_plant --dt 0.01 --like OUT/emps_dev.csv "
        "--time-col time --y-cols q --u-cols u --out DIR")
    assert record["cases"]["u_box"]["command"].endswith("--measurement-std 1e-6 --out DIR")
    card = json.loads((tmp_path / "like" / "card.json").read_text())
    source = card["training"]["rollouts"]["envelope"]["sources"][0]
    assert source["sha256"] == hashlib.sha256((tmp_path / "emps_dev.csv").read_bytes()).hexdigest()
    assert card["domain"]["x_lo"] == [-0.01, -0.2] and card["training"]["runs"]["stabilised"] is True
    assert record["ekf_noise"] == card["noise"]
    assert (tmp_path / "emps_velocity.png").stat().st_size > 20000
    assert provenance.read(tmp_path / "emps_velocity.png") == provenance.read(results)


@pytest.mark.parametrize("taken, flag", [("emps_dev.csv", "--out"), ("like", "--out"), ("est_u_box.csv", "--out"),
                                         ("emps.json", "--results"), ("emps_velocity.png", "--results"),
                                         ("emps.md", "--page")])
def test_example_refuses_any_file_it_would_write_before_any_work(example, tmp_path, taken, flag):
    folder = tmp_path / {"--out": "out", "--results": "results", "--page": "docs"}[flag]
    folder.mkdir()
    (folder / taken).write_text("kept")
    with pytest.raises(FileExistsError, match=f"^{flag}: .*{taken} exists and this command does not overwrite"):
        example["main"](tmp_path / "out", results=tmp_path / "results" / "emps.json",
                        page_path=tmp_path / "docs" / "emps.md")
    assert [p for p in tmp_path.rglob("*") if p.is_file()] == [folder / taken]
    assert (folder / taken).read_text() == "kept"


def test_example_leaves_no_half_written_result_when_it_fails(example, reduced, tmp_path, monkeypatch):
    """A plot that fails after the estimates: the record, the PNG and the page are not written, not even a part."""
    import shutil

    done, _ = reduced
    monkeypatch.setitem(example["main"].__globals__, "train",        # the reduced run's models, not trained again
                        lambda case, model, dev, **_: shutil.copytree(done / case, model))

    def failing(*args):
        raise OSError("disk")

    monkeypatch.setitem(example["main"].__globals__, "plot", failing)
    results = tmp_path / "results" / "emps.json"
    with pytest.raises(OSError, match="disk"):
        example["main"](tmp_path / "out", results=results, page_path=tmp_path / "docs" / "emps.md")
    assert not (tmp_path / "results").exists() and not (tmp_path / "docs").exists()
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["emps_dev.csv", "est_like.csv", "est_u_box.csv",
                                                                    "like", "u_box"]


def test_the_page_is_the_stored_records():
    """docs/results/emps.md is what examples/emps_rig.py writes from results/real_rig/emps/emps.json."""
    from kklcasadi import provenance

    example = runpy.run_path(str(EXAMPLE), run_name="emps_rig")
    root = EXAMPLE.parents[1]
    record = provenance.json_payload(json.loads((root / "results" / "real_rig" / "emps" / "emps.json").read_text()))
    text = (root / "docs" / "results" / "emps.md").read_text()
    assert provenance.strip_markdown(text) == example["page"](record)
    assert provenance.read(root / "docs" / "results" / "emps.md").command == example["COMMAND"]
    assert provenance.read(root / "results" / "real_rig" / "emps" / "emps_velocity.png").command == example["COMMAND"]


def test_the_readme_states_the_records_figures():
    """The README's EMPS section: each observer's velocity over the EKF's and its position error, from the record."""
    import re

    from kklcasadi import provenance

    example = runpy.run_path(str(EXAMPLE), run_name="emps_rig")
    root = EXAMPLE.parents[1]
    table = provenance.json_payload(json.loads((root / "results" / "real_rig" / "emps" / "emps.json")
                                               .read_text()))["scores"]
    readme = (root / "README.md").read_text()
    text = re.sub(r"\s+", " ", re.search(r"^## A real positioning axis \(EMPS\)\n(.*?)(?=^## )", readme,
                                          re.M | re.S).group(1))
    ekf = table["EKF (noise from the log)"]["scored"]["q_dot"]
    for case, label in example["LABELS"].items():
        cell = table[label]["scored"]
        assert (f"{cell['q_dot'] / ekf:.2f}x the EKF's velocity RMSE {example['CASE_NAMES'][case]} (position "
                f"{1e3 * cell['q']:.2g} mm)") in text, case
    assert "[docs/results/emps.md](docs/results/emps.md)" in text and "chose nothing" in text
