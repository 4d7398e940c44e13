"""The observer-step figures that docs/results/speed.md shows are written by ``kklcasadi bench observer --write``
with the digest of each model's card; they must have been measured on the cards that ship now. No test asserts
a speed (it depends on the machine and its load, which the table states)."""

import hashlib
import re
from pathlib import Path

from kklcasadi import provenance
from kklcasadi.cli import main
from kklcasadi.evaluation.bench import Timing
from kklcasadi.evaluation.bench.observer_step import STEP_COLUMNS, card_digest, step_table
from kklcasadi.model.shipped import resolve, shipped


def test_the_step_table_shows_microseconds_per_step_and_the_default_builds_instructions():
    default = STEP_COLUMNS[0][1]
    timings = [Timing("gcc -std=c99 -O3 compile (shared library)", 0.5, 1),
               Timing(default, 2e-3, 100, instructions=12345.4),
               Timing(default + " -march=native", 1e-3, 100),          # not the default build: not shown
               Timing("C portable, -std=c99 -O3 -DKKLC_NO_DISPATCH", 3e-3, 200),
               Timing("CasADi VM (Function.call)", 0.5, 1000)]
    table = step_table([("duffing/x", "ab" * 32, timings)], (1.0, 2.5, 3.0))
    header, rule, row = table.splitlines()[:3]
    assert header.startswith("| model | card sha256 | C default (-O3) (us) | C portable (us)")
    assert row.split(" | ")[1:] == ["`" + "ab" * 8 + "`", "20.00", "15.00", "", "", "500.00", "12,345 |"]
    assert rule.count("---") == header.count("|") - 1
    assert "load average 1.00 / 2.50 / 3.00" in table


def test_the_card_digest_is_the_sha256_of_card_json(tmp_path):
    (tmp_path / "card.json").write_bytes(b'{"method": "bank"}')
    assert card_digest(tmp_path) == hashlib.sha256(b'{"method": "bank"}').hexdigest()


def test_bench_write_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "step.md"
    out.write_text("kept")
    assert main(["bench", "observer", "--model", "duffing/bank", "--write", str(out)]) == 2
    assert "--write" in capsys.readouterr().err and out.read_text() == "kept"


ROOT = Path(__file__).resolve().parents[1]
STEP_FILES = sorted((ROOT / "results" / "speed").glob("*/observer_step*.md"))


def _rows(path):
    """``(model name, card digest prefix)`` of each row of a step table."""
    return re.findall(r"^\| `([^`]+)` \| `([0-9a-f]{16})` \|", path.read_text(), re.M)


def test_the_step_figures_were_measured_on_the_shipped_cards():
    """Every row of the step tables names a shipped model whose card is the one measured (by its SHA-256), and
    every shipped compact observer is shown beside its system's bank: a changed model needs the command in
    the table's stamp run again (then python benchmarks/summarize_pages.py)."""
    assert STEP_FILES
    shown = set()
    for path in STEP_FILES:
        command = provenance.read(path).command
        assert command.startswith("kklcasadi bench observer")
        for name, digest in _rows(path):
            assert card_digest(resolve(name)).startswith(digest), (
                f"{path.name}: the card of {name} changed since it was timed; run `{command} --overwrite` and "
                "python benchmarks/summarize_pages.py")
            shown.add(name)
    compact = {f"{system}/compact" for system, methods in shipped().items() if "compact" in methods}
    assert compact and compact | {name.replace("compact", "bank") for name in compact} <= shown


def test_bench_write_is_refused_for_a_benchmark_without_a_table(tmp_path, capsys):
    out = tmp_path / "training.md"
    assert main(["bench", "training", "--write", str(out)]) == 2
    assert "--write" in capsys.readouterr().err and not out.exists()


def test_bench_protocol_writes_what_it_prints_stamped(tmp_path, capsys):
    """``kklcasadi bench protocol --write``: the stamped file holds the printed tables; an existing file is
    refused before the benchmark runs."""
    out = tmp_path / "protocol.md"
    argv = ["bench", "protocol", "--models", str(ROOT / "models" / "duffing" / "autonomous"), "--trials", "1",
            "--vm-trials", "1", "--plain-trials", "0", "--no-ekf", "--threads", "1", "--write", str(out)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    body = provenance.strip_markdown(out.read_text())
    assert "| autonomous |" in body and "- warm caches" in body and body.strip() in printed
    assert provenance.read(out).command.startswith("kklcasadi bench protocol")
    assert provenance.read(out).seeds == {"trials": 2026}                   # docs/protocol.md's trial seed
    kept = out.read_text()
    assert main(argv) == 2
    assert "--write" in capsys.readouterr().err and out.read_text() == kept
