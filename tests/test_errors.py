"""One error style: ``ArgumentError`` carries the parts of the message as fields, and the command line names its
own flag from those fields (not by splitting the text)."""

import pickle

import pytest

from kklcasadi.cli.flags import CommandError, flagged, flagged_by
from kklcasadi.validation import ArgumentError, ArgumentTypeError, Text, error, positive_int


def test_error_keeps_the_parts_of_its_message():
    exc = error("window", "a positive int", 0, "Pass 1 or more.")
    assert isinstance(exc, ArgumentError) and isinstance(exc, ValueError) and not isinstance(exc, TypeError)
    assert (exc.argument, exc.expected, exc.received, exc.hint) == ("window", "a positive int", 0, "Pass 1 or more.")
    assert str(exc) == "window: expected a positive int, received 0. Pass 1 or more."
    assert exc.detail == "expected a positive int, received 0. Pass 1 or more."
    typed = error("name", "a string", Text("int"), kind=TypeError)
    assert isinstance(typed, ArgumentTypeError) and isinstance(typed, TypeError) and not isinstance(typed, ValueError)
    assert str(typed) == "name: expected a string, received int."
    with pytest.raises(ArgumentTypeError, match="kind: expected ValueError or TypeError, received KeyError"):
        error("x", "y", 1, kind=KeyError)


def test_argument_errors_survive_pickling():
    exc = error("card.json: 'dt'", "a positive number (seconds)", -1.0)
    back = pickle.loads(pickle.dumps(exc))
    assert type(back) is ArgumentError and str(back) == str(exc) and back.received == -1.0


def _raises(exc):
    def fn():
        raise exc
    return fn


@pytest.mark.parametrize("exc,message", [
    # a Python argument is said of the flag
    (error("threads", "a positive int", 0), "--threads: expected a positive int, received 0."),
    (error("name", "a string", Text("int"), kind=TypeError), "--threads: expected a string, received int."),
    # a file's field keeps its path and field after the flag
    (error("m/card.json: 'dt'", "a positive number", -1), "--threads: m/card.json: 'dt': expected a positive number, "
                                                          "received -1."),
    # any other message is kept whole after the flag, even where it starts with a word and a colon
    (ValueError("plant: importing x.py failed"), "--threads: plant: importing x.py failed"),
    (TypeError("bad"), "--threads: bad"),
])
def test_flagged_names_the_flag_from_the_fields(exc, message):
    with pytest.raises(CommandError) as info:
        flagged("--threads", _raises(exc))
    assert str(info.value) == message


def test_flagged_passes_values_and_other_errors_through():
    assert flagged("--threads", positive_int, 3, "threads") == 3
    with pytest.raises(KeyError):
        flagged("--threads", _raises(KeyError("k")))


def test_flagged_passes_keywords_named_like_its_own_parameters_through():
    # Compiler(flags=...) through flagged("--flags", ...) once raised "got multiple values for argument 'flags'"
    def echo(**kwargs):
        return kwargs
    kwargs = {"flags": ("-O2",), "flag": 1, "default": 2, "fn": 3, "fn_args": 4}
    assert flagged("--flags", echo, **kwargs) == kwargs
    assert flagged_by({"flags": "--flags"}, "--x", echo, **kwargs) == kwargs


def test_the_bench_command_builds_its_compiler_from_the_flags():
    from kklcasadi.cli import build_parser
    from kklcasadi.cli.bench import _compiler

    args = build_parser().parse_args(["bench", "protocol", "--flags=-O2 -ffp-contract=off"])
    assert _compiler(args).flags == ("-O2", "-ffp-contract=off")


# -- --plant runs code: what it does wrong is one line, and only a function that returns a System is called -------

PLANT_HEAD = "import casadi as ca\nimport kklcasadi as kc\n"
DUFFING = ("def make_plant():\n    x, u = ca.SX.sym('x', 2), ca.SX.sym('u', 1)\n"
           "    return kc.System('mine', x, u, [x[1], -x[0] - x[0] ** 3 + u], x[0], [[-1, 1], [-1, 1]])\n")


def _plant_file(tmp_path, body):
    path = tmp_path / "plant.py"
    path.write_text(PLANT_HEAD + body)
    return path


@pytest.mark.parametrize("body,match", [
    ("raise KeyError('speed')\n" + DUFFING, r"plant: expected importing .*plant.py to run without error, received "
                                            r"KeyError: 'speed'"),
    ("import sys\nsys.exit(0)\n" + DUFFING, r"plant: expected importing .*plant.py to define the plant, received a "
                                            r"call of sys.exit\(0\)"),
    ("def make_plant():\n    return {}['a']\n", r"plant: expected .*plant.py:make_plant\(\) to run without error, "
                                               r"received KeyError: 'a'"),
    ("def make_plant():\n    raise SystemExit(3)\n", r"received a call of sys.exit\(3\)"),
    ("def make_plant(x):\n    return x\n", r"a Python function without arguments that returns one, received function "
                                          r"make_plant"),
    ("make_plant = 3\n", r"received int"),
    ("def make_plant():\n    return 'duffing'\n", r"make_plant\(\) to return a kklcasadi.System, received str"),
])
def test_a_plant_file_that_raises_or_exits_is_reported(tmp_path, body, match):
    from kklcasadi.plant.systems import load_plant

    with pytest.raises((ArgumentError, ArgumentTypeError), match=match):
        load_plant(f"{_plant_file(tmp_path, body)}:make_plant")


def test_a_module_function_is_checked_before_it_is_called():
    from kklcasadi.plant.systems import load_plant

    # os.getcwd is not a Python function: refused without being called (else the error would name a str it returned)
    with pytest.raises(ArgumentTypeError, match=r"os:getcwd to be a kklcasadi.System or a Python function without "
                                                r"arguments that returns one, received builtin_function_or_method"):
        load_plant("os:getcwd")
    with pytest.raises(ArgumentTypeError, match="received function abspath"):
        load_plant("os.path:abspath")
    with pytest.raises(ArgumentError, match="expected an importable module or a .py file, received 'no_such_mod'"):
        load_plant("no_such_mod:make_plant")
    assert load_plant("kklcasadi.plant.systems:duffing").name == "duffing"


def _cli(*args):
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    return subprocess.run([sys.executable, "-m", "kklcasadi", *args], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(root)})


def test_a_plant_file_that_exits_stops_the_command_with_status_2(tmp_path):
    from pathlib import Path

    plant = _plant_file(tmp_path, "import sys\nsys.exit(0)\n" + DUFFING)
    model = Path(__file__).resolve().parents[1] / "models" / "duffing" / "bank"
    data = tmp_path / "log.csv"
    data.write_text("time,y\n0,0.1\n0.05,0.1\n")
    for args in (["demo", "--model", str(model), "--plant", f"{plant}:make_plant", "--out", str(tmp_path / "d.png")],
                 ["estimate", str(model), "--plant", f"{plant}:make_plant", "--data", str(data), "--y", "y",
                  "--out", str(tmp_path / "e.csv")]):
        result = _cli(*args)
        assert result.returncode == 2, (args, result.stdout, result.stderr)
        assert result.stderr.count("\n") == 1 and "--plant: expected importing" in result.stderr
        assert "sys.exit(0)" in result.stderr
    assert not (tmp_path / "d.png").exists() and not (tmp_path / "e.csv").exists()


def test_training_data_with_nan_blame_the_plant_not_the_learning_rate():
    pytest.importorskip("torch")
    import numpy as np
    import torch

    from kklcasadi.train.config import LoopConfig
    from kklcasadi.train.loop import ArrayDataset, fit

    x = np.random.default_rng(0).normal(size=(64, 2))
    x[5, 1] = np.nan
    data = ArrayDataset({"x": x})
    w = torch.zeros(2, requires_grad=True)
    def loss(batch, epoch):
        return (((batch["x"] * w).sum(-1) - 1.0) ** 2).mean(), {}

    with pytest.raises(ArgumentError, match=r"stage: data: expected finite training data, received NaN or inf in x\. "
                                            r"They come from simulating the plant"):
        fit([w], loss, data, LoopConfig(epochs=2, batch_size=8, lr=1e-2), name="stage", progress=False)
