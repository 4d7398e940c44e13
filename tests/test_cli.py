"""The command line on tiny random-weight models: every subcommand runs and reports clearly."""

import shutil
import subprocess
import sys

import casadi as ca
import pytest

from kklcasadi.cli import main
from kklcasadi.modelfile import load_model


def test_help_lists_the_subcommands(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for cmd in ("demo", "train", "evaluate", "export", "bench"):
        assert cmd in out


def test_console_script_entry_point():
    out = subprocess.run([sys.executable, "-m", "kklcasadi.cli", "export", "--help"], capture_output=True, text=True,
                         check=True).stdout
    assert "--casadi" in out and "--c OUT_DIR" in out


def test_demo_runs_on_a_model_and_writes_a_plot(model_dir_factory, tmp_path, capsys):
    model = model_dir_factory("obs", window=5)
    png = tmp_path / "demo.png"
    assert main(["demo", "--model", str(model), "--T", "6", "--out", str(png)]) == 0
    out = capsys.readouterr().out
    assert "SMAPE" in out and "EKF" in out
    assert png.stat().st_size > 5000


def test_evaluate_prints_a_table_and_writes_plots(model_dir_factory, tmp_path, capsys):
    a = model_dir_factory("autonomous")
    b = model_dir_factory("inject", base=True)
    out = tmp_path / "eval"
    assert main(["evaluate", str(a), str(b), "--trials", "2", "--kinds", "zero", "constant", "--noise", "off",
                 "--ekf", "--out", str(out)]) == 0
    table = capsys.readouterr().out
    assert "| duffing autonomous |" in table and "| duffing inject |" in table and "| duffing EKF |" in table
    assert (out / "duffing_smape_clean.png").exists() and (out / "duffing_scores.json").exists()


def test_export_writes_c_and_a_casadi_function(model_dir_factory, tmp_path, capsys):
    model = model_dir_factory("autonomous")
    assert main(["export", str(model), "--c", str(tmp_path / "c"), "--casadi", str(tmp_path / "step.casadi")]) == 0
    f = ca.Function.load(str(tmp_path / "step.casadi"))
    assert f.name_in() == ["z", "w", "y", "y_next", "u_next"]
    assert any(p.suffix == ".c" for p in (tmp_path / "c").iterdir())
    with pytest.raises(SystemExit, match="exists; pass --overwrite"):
        main(["export", str(model), "--casadi", str(tmp_path / "step.casadi")])
    with pytest.raises(SystemExit, match="nothing to export"):
        main(["export", str(model)])


def test_train_inject_via_the_cli(model_dir_factory, tmp_path):
    base = model_dir_factory("autonomous")
    out = tmp_path / "inject"
    assert main(["train", "--system", "duffing", "--method", "inject", "--out", str(out), "--base", str(base)]) == 0
    assert load_model(out).method == "inject"


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")
def test_bench_simulation_runs(capsys):
    assert main(["bench", "simulation", "--trials", "2"]) == 0
    assert "speed-up" in capsys.readouterr().out
