"""The benchmark scripts never write over a file and never leave a half-written result: each refuses, before any
work, a run whose output exists (one line naming the flag that names it), and renders its files before writing
them together (kklcasadi.writes). The scripts with a reduced run of their own are tested beside it
(tests/test_bank.py: monitor_quantiles.py, ensemble_members.py; test_codegen.py: float32_c.py; test_generalisation.py:
compare_generalisation.py; test_results.py: pages.py)."""

import os
import runpy
import sys
from pathlib import Path

import pytest

from kklcasadi import provenance

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"


def _run(monkeypatch, script, *args):
    monkeypatch.syspath_prepend(str(script.parent))                      # the scripts import their siblings
    monkeypatch.setattr(sys, "argv", [str(script), *map(str, args)])
    runpy.run_path(str(script), run_name="__main__")


#: script, its arguments (TMP: the test's folder), the file made to exist first, and the flag the refusal names
REFUSALS = [
    ("primed_mhe_covariance.py", ["duffing", "--out", "TMP"], "duffing_primed_mhe.json", "--out"),
    ("pf_roughening.py", ["--out", "TMP", "--seed", "3030"], "pf_roughening_3030.md", "--out"),
    ("tune/confirm.py", ["TMP", "--plant", "nowhere.py:make_plant"], "confirm.md", "OUT"),
    ("accuracy/decoder_pairs.py", ["duffing", "--out", "TMP/pairs"], "pairs.md", "--out"),
    ("accuracy/qube.py", ["--tag", "not_stored", "--out", "TMP"], "not_stored_both", "--out"),
    ("accuracy/probe.py", ["duffing", "--tag", "t", "--save", "TMP"], "duffing_t.npz", "--save"),
    ("covariance_heads.py", ["duffing/bank", "--out", "TMP"], "card.json", "--out"),
    ("bitwise_estimates.py", ["record", "TMP/before.npz"], "before.npz", "OUT.npz"),
]
#: The scripts that import torch (the decoder fits).
NEEDS_TORCH = ("accuracy/decoder_pairs.py", "accuracy/qube.py", "accuracy/probe.py", "covariance_heads.py")


@pytest.mark.parametrize("script, args, taken, flag", REFUSALS, ids=[r[0] for r in REFUSALS])
def test_a_benchmark_refuses_its_existing_output_before_any_work(tmp_path, monkeypatch, capsys, script, args, taken,
                                                                 flag):
    if script in NEEDS_TORCH:
        pytest.importorskip("torch")
    monkeypatch.chdir(tmp_path)                                          # probe.py writes under ./results/levers
    (tmp_path / taken).write_text("kept")
    with pytest.raises(FileExistsError, match=f"^{flag}: .*{taken} exists and this command does not overwrite"):
        _run(monkeypatch, BENCHMARKS / script, *(str(a).replace("TMP", str(tmp_path)) for a in args))
    assert [p.name for p in tmp_path.iterdir()] == [taken] and (tmp_path / taken).read_text() == "kept"
    assert capsys.readouterr().out == ""


def test_the_qube_accuracy_driver_refuses_a_stored_record_by_its_tag(monkeypatch):
    pytest.importorskip("torch")
    stored = ROOT / "results" / "real_rig" / "qube" / "p16_both_fit.json"
    before = stored.read_bytes()
    with pytest.raises(FileExistsError, match="^--tag: .*p16_both_fit.json exists and this command does not"):
        _run(monkeypatch, BENCHMARKS / "accuracy" / "qube.py", "--tag", "p16", "--outputs", "both", "--runs", "fit")
    assert stored.read_bytes() == before


def test_the_primed_mhe_benchmark_writes_its_table_and_record_as_one_or_nothing(tmp_path, monkeypatch):
    """A reduced run (one zero-input trial of 6 s, horizon 3): both files under one stamp; a write that fails
    leaves neither, nor a temporary file."""
    script = BENCHMARKS / "primed_mhe_covariance.py"
    out = tmp_path / "out"
    _run(monkeypatch, script, "duffing", "--out", out, "--trials", "1", "--T", "6", "--kinds", "zero", "--horizon", "3")
    names = ["duffing_primed_mhe.json", "duffing_primed_mhe.md"]
    assert sorted(p.name for p in out.iterdir()) == names
    assert provenance.read(out / names[0]) == provenance.read(out / names[1])
    assert "| duffing | zero | primed MHE, covariance head | 1 |" in (out / names[1]).read_text()

    def failing(fd):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", failing)
    with pytest.raises(OSError, match="disk full"):
        _run(monkeypatch, script, "duffing", "--out", tmp_path / "again", "--trials", "1", "--T", "6", "--kinds",
             "zero", "--horizon", "3")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
