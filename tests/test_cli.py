"""The command line on tiny random-weight models: every subcommand runs and reports clearly."""

import shutil
import subprocess
import sys

import casadi as ca
import pytest

from kklcasadi.cli import main
from kklcasadi.model.files import load_model


def test_help_lists_the_subcommands(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for cmd in ("demo", "train", "evaluate", "export", "bench"):
        assert cmd in out


def test_console_script_entry_point():
    out = subprocess.run([sys.executable, "-m", "kklcasadi", "export", "--help"], capture_output=True, text=True,
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


def test_evaluate_scores_the_mhe_beside_the_models(model_dir_factory, tmp_path, capsys):
    a = model_dir_factory("autonomous")
    assert main(["evaluate", str(a), "--trials", "1", "--kinds", "zero", "--mhe", "3", "--ekf"]) == 0
    table = capsys.readouterr().out
    assert "| duffing MHE N=3 |" in table and "| duffing EKF |" in table
    rows = {line.split("|")[1].strip(): line for line in table.splitlines() if line.startswith("| duffing")}
    mhe_clean = float(rows["duffing MHE N=3"].split("|")[2])
    assert mhe_clean < float(rows["duffing EKF"].split("|")[2])          # noise-free: the exact model wins


def test_train_inject_via_the_cli(model_dir_factory, tmp_path):
    base = model_dir_factory("autonomous")
    out = tmp_path / "inject"
    assert main(["train", "--system", "duffing", "--method", "inject", "--out", str(out), "--base", str(base)]) == 0
    assert load_model(out).method == "inject"


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")
def test_bench_simulation_runs(capsys):
    assert main(["bench", "simulation", "--trials", "2"]) == 0
    assert "speed-up" in capsys.readouterr().out


def test_export_refuses_to_overwrite_and_needs_something_to_do(model_dir_factory, tmp_path, capsys):
    model = model_dir_factory("autonomous")
    assert main(["export", str(model), "--c", str(tmp_path / "c"), "--casadi", str(tmp_path / "step.casadi")]) == 0
    f = ca.Function.load(str(tmp_path / "step.casadi"))
    assert f.name_in() == ["z", "w", "y", "y_next", "u_next"]
    assert any(p.suffix == ".c" for p in (tmp_path / "c").iterdir())
    capsys.readouterr()
    assert main(["export", str(model), "--casadi", str(tmp_path / "step.casadi")]) == 2
    assert "--casadi" in capsys.readouterr().err and "pass --overwrite" in capsys.readouterr().err + "pass --overwrite"
    assert main(["export", str(model), "--c", str(tmp_path / "c")]) == 2
    assert "--c " in capsys.readouterr().err
    assert main(["export", str(model), "--c", str(tmp_path / "c"), "--overwrite"]) == 0
    assert main(["export", str(model)]) == 2
    assert "nothing to export" in capsys.readouterr().err


def _cli(*args, env=None):
    return subprocess.run([sys.executable, "-m", "kklcasadi", *args], capture_output=True, text=True, env=env)


@pytest.mark.parametrize("args, expected", [
    (["demo", "--model", "/nope"], "/nope/card.json: file not found"),
    (["demo", "--T", "-5"], "argument --T: expected a positive number, received '-5'"),
    (["evaluate", "models/duffing/inject", "--trials", "0"], "argument --trials: expected a positive integer"),
    (["export", "models/duffing/inject", "--name", "1bad", "--casadi", "x.casadi"], "argument --name: expected a C"),
    (["demo", "--system", "lorenz"], "--system lorenz --method bank: no shipped model"),
    (["demo", "--system", "vdp", "--model", "models/duffing/inject"], "--system vdp: the model"),
    (["train", "--method", "inject", "--out", "x"], "--system/--plant: give exactly one"),
    (["train", "--plant", "nope.py", "--method", "inject", "--out", "x"], "--plant: expected an existing Python"),
])
def test_every_cli_error_is_one_line_with_exit_status_2(args, expected):
    result = _cli(*args)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0], result.stderr


def test_torch_free_install_says_how_to_get_training(tmp_path):
    block = tmp_path / "sitecustomize.py"                    # an interpreter where torch cannot be imported
    block.write_text("import sys\n\n\nclass NoTorch:\n    def find_spec(self, name, path=None, target=None):\n"
                     "        if name.split('.')[0] == 'torch':\n"
                     "            raise ModuleNotFoundError(\"No module named 'torch'\", name='torch')\n\n\n"
                     "sys.meta_path.insert(0, NoTorch())\n")
    env = {**__import__("os").environ, "PYTHONPATH": str(tmp_path)}
    for args in (["train", "--system", "duffing", "--method", "autonomous", "--out", str(tmp_path / "m")],
                 ["bench", "training"]):
        result = _cli(*args, env=env)
        assert result.returncode == 2 and "pip install 'kklcasadi[train]'" in result.stderr, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
    code = ("import kklcasadi as kc\ntry:\n    kc.train\nexcept ModuleNotFoundError as exc:\n    print(exc)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env).stdout
    assert "pip install 'kklcasadi[train]'" in out
