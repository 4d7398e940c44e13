"""The command line on tiny random-weight models: every subcommand runs and reports clearly."""

import os
import shutil
import subprocess
import sys
import warnings

import casadi as ca
import numpy as np
import pytest

from kklcasadi import provenance
from kklcasadi.cli import main
from kklcasadi.model.files import load_model


def test_help_lists_the_subcommands(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for cmd in ("demo", "train", "evaluate", "export", "bench"):
        assert cmd in out


def _subcommands():
    import argparse

    from kklcasadi.cli import build_parser

    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return sub.choices


@pytest.mark.parametrize("command", sorted(_subcommands()))
def test_every_flag_and_positional_has_help(command):
    import argparse

    missing = [a.option_strings or a.dest for a in _subcommands()[command]._actions
               if not isinstance(a, argparse._HelpAction) and not (a.help or "").strip()]
    assert missing == [], f"kklcasadi {command}: no help for {missing}"


def test_version_names_the_package_commit_and_libraries(capsys):
    import casadi

    from kklcasadi import provenance
    from kklcasadi.version import __version__

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    printed = capsys.readouterr().out
    commit = provenance.commit()
    where = "not a git checkout" if commit == "unknown" else f"commit {commit}"
    assert printed.startswith(f"kklcasadi {__version__} ({where}; casadi {casadi.__version__}, torch ")


def test_system_flags_offer_the_systems_with_shipped_models_and_name_the_others(capsys):
    from kklcasadi.model.shipped import shipped
    from kklcasadi.plant import systems

    having = sorted(shipped())
    none = [name for name in systems.names() if name not in having]
    assert having and none                                        # linear and lorenz ship no model
    commands = _subcommands()
    for command, flag in (("demo", "--system"), ("train", "--system"), ("tune", "--system"), ("bench", "--system"),
                          ("compare", "--systems")):
        (action,) = [a for a in commands[command]._actions if flag in a.option_strings]
        assert f"shipped models for {', '.join(having)}; none for {', '.join(none)}" in action.help, command
        assert list(action.choices) == (having if command == "demo" else systems.names()), command
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--system", none[0]])
    assert exc.value.code == 2 and f"argument --system: invalid choice: '{none[0]}'" in capsys.readouterr().err


def test_console_script_entry_point():
    out = subprocess.run([sys.executable, "-m", "kklcasadi", "export", "--help"], capture_output=True, text=True,
                         check=True).stdout
    assert "--casadi" in out and "--c OUT_DIR" in out


def test_demo_prints_the_errors_of_its_run_and_writes_a_plot(model_dir_factory, tmp_path, capsys):
    """The printed SMAPEs are those of the run the demo describes, recomputed here (VM, EKF)."""
    from kklcasadi import metrics
    from kklcasadi.estimators.ekf import EKF
    from kklcasadi.observer.kkl import load_observer
    from kklcasadi.plant import signals
    from kklcasadi.plant.simulate import simulate

    model = model_dir_factory("obs", window=5)
    png = tmp_path / "demo.png"
    assert main(["demo", "--model", str(model), "--T", "6", "--seed", "3", "--out", str(png)]) == 0
    out = capsys.readouterr().out
    obs = load_observer(model)
    x0 = obs.system.sample_box(1, 3)[0]
    tr = simulate(obs.system, x0, signals.make("square", amplitude=[0.8], omega=1.0), T=6.0, dt=obs.dt,
                  process_std=0.1, measurement_std=0.1, seed=3)
    kkl = metrics.smape(tr.x, obs.simulate(tr.t, tr.y, tr.u).xhat)
    ekf = metrics.smape(tr.x, EKF(obs.system, obs.dt).simulate(tr.t, tr.y, tr.u).xhat)
    assert f"SMAPE    KKL (obs) {kkl:6.2f} %   EKF {ekf:6.2f} %" in out, out
    assert png.stat().st_size > 5000 and provenance.read(png).seeds == {"run": 3}


def test_the_demo_figure_shows_the_measurement_each_error_and_the_flagged_samples():
    """estimates_figure: y on its own panel, the states with the first estimator drawn above the others, one
    error panel per estimator holding xhat - x on a shared scale, the flagged samples shaded, labelled axes, and
    the legend above the panels (outside every axes)."""
    import matplotlib
    import numpy as np

    from kklcasadi.evaluation.report import estimates_figure

    matplotlib.use("Agg")
    t = np.linspace(0.0, 10.0, 201)
    x = np.column_stack([np.sin(t), np.cos(t)])
    y = x[:, :1] + 0.1 * np.random.default_rng(0).normal(size=(201, 1))
    kkl, ekf = x + 0.05, x - 0.5 * np.exp(-t)[:, None]
    flags = np.ones(201, bool)
    flags[20:30] = flags[150:160] = False
    fig = estimates_figure(t, x, y, {"KKL (bank)": kkl, "EKF": ekf}, u=np.sign(np.sin(t))[:, None], in_domain=flags,
                           title="test")
    axes = fig.axes
    assert [ax.get_ylabel() for ax in axes] == ["y (measured)", "x1", "x2", "KKL (bank)\nerror", "EKF\nerror", "u"]
    assert axes[-1].get_xlabel() == "t (s)"
    np.testing.assert_array_equal(axes[0].lines[0].get_ydata(), y[:, 0])
    line = {ln.get_label(): ln for ln in axes[1].lines}
    assert line["KKL (bank)"].get_zorder() > line["EKF"].get_zorder() > line["true state"].get_zorder()
    for ax, xhat in zip(axes[3:5], (kkl, ekf)):                        # xhat - x per state, then the zero line
        for i in range(2):
            np.testing.assert_allclose(ax.lines[i].get_ydata(), xhat[:, i] - x[:, i])
    assert axes[3].get_ylim() == axes[4].get_ylim()                  # one error scale
    spans = [p for p in axes[2].patches]
    assert len(spans) == 2 and spans[0].get_x() == t[20]                # the two flagged stretches, on every panel
    (legend,) = fig.legends
    labels = [text.get_text() for text in legend.get_texts()]
    assert "measured y" in labels and "outside the trained domain (20 samples)" in labels and "error of x2" in labels
    fig.canvas.draw()
    box = legend.get_window_extent()
    assert all(box.y0 >= ax.get_window_extent().y1 for ax in axes)     # above every panel: off the data


def test_evaluate_prints_the_protocol_scores_and_writes_plots(model_dir_factory, tmp_path, capsys):
    """The table and scores.json hold each model's SMAPE on the protocol's trials, recomputed here
    with the observer in the CasADi VM (evaluate runs compiled code: within 1e-14 of it)."""
    import json

    import numpy as np

    from kklcasadi import metrics
    from kklcasadi.evaluation.protocol import Protocol
    from kklcasadi.observer.kkl import load_observer

    a = model_dir_factory("autonomous")
    b = model_dir_factory("inject", base=True)
    out = tmp_path / "eval"
    args = ["evaluate", str(a), str(b), "--trials", "3", "--kinds", "zero", "constant", "--noise", "off", "--ekf",
            "--out", str(out)]
    assert main(args) == 0
    table = capsys.readouterr().out
    # every file written carries the command line, the commit and the trials' seed
    written = sorted(p.name for p in out.iterdir())
    assert written == ["duffing_scores.json", "duffing_smape_clean.png", "duffing_table.md"]
    for name in written:
        stamp = provenance.read(out / name)
        assert stamp.command == "kklcasadi " + " ".join(args) and stamp.seeds == {"trials": 2026} and stamp.commit
    scores = {(r["method"], r["kind"]): r
              for r in provenance.json_payload(json.loads((out / "duffing_scores.json").read_text()))}
    assert sorted(scores) == [(m, k) for m in ("EKF", "autonomous", "inject") for k in ("constant", "zero")]
    rows = {line.split("|")[1].strip(): line.split("|")[2:4] for line in table.splitlines()
            if line.startswith("| duffing")}
    for path in (a, b):
        obs = load_observer(path)
        for column, kind in enumerate(("zero", "constant")):
            trials = Protocol(n_trials=3).noise_free().trials(obs.system, kind)
            expected = metrics.smape(trials.x, obs.simulate(trials.t, trials.y, trials.u).xhat)
            record = scores[(obs.method, kind)]
            assert record["noisy"] is False
            np.testing.assert_allclose(record["smape"], expected, rtol=1e-10)
            assert record["smape_mean"] == pytest.approx(np.mean(expected), rel=1e-10)
            assert float(rows[f"duffing {obs.method}"][column]) == round(record["smape_mean"], 1)
    assert float(rows["duffing EKF"][0]) == round(scores[("EKF", "zero")]["smape_mean"], 1)
    # the report is never written over: a second run to the same --out is refused in one line before any run
    before = {name: (out / name).read_bytes() for name in written}
    assert main(args) == 2
    captured = capsys.readouterr()
    assert captured.err.endswith(f"error: --out: {out / 'duffing_scores.json'} exists and this command does not "
                                 "overwrite; move it away, or choose another --out.\n")
    assert "evaluated in" not in captured.err and captured.out == ""
    assert {name: (out / name).read_bytes() for name in written} == before


def test_evaluate_scores_the_mhe_beside_the_models(model_dir_factory, tmp_path, capsys):
    a = model_dir_factory("autonomous")
    assert main(["evaluate", str(a), "--trials", "1", "--kinds", "zero", "--mhe", "3", "--ekf"]) == 0
    table = capsys.readouterr().out
    assert "| duffing MHE N=3 |" in table and "| duffing EKF |" in table
    rows = {line.split("|")[1].strip(): line for line in table.splitlines() if line.startswith("| duffing")}
    mhe_clean = float(rows["duffing MHE N=3"].split("|")[2])
    assert mhe_clean < float(rows["duffing EKF"].split("|")[2])          # noise-free: the exact model wins


def _summary_entry(kind, obs, batch, ours, theirs, box=None):
    """The closing summary's entry for ``kind``, recomputed here: on the runs whose true state stays in the trained
    box (widened by a quarter of its half-width: where training cuts a run) at every sample, the RMSE after 5 s of
    the error over the box's width (in %, the observer's / the EKF's, their ratio) and the mean SMAPE
    (docs/protocol.md); runs with a non-finite EKF estimate leave its side."""
    from kklcasadi import metrics

    if box is None:
        box = (obs.system.x0_box if obs.domain is None else np.column_stack([obs.domain.x_lo, obs.domain.x_hi]))
    x = batch.x
    lo, hi = box[:, 0] - 0.125 * (box[:, 1] - box[:, 0]), box[:, 1] + 0.125 * (box[:, 1] - box[:, 0])
    stays = np.array([np.all((run >= lo) & (run <= hi)) for run in x])   # the box and a quarter of its half-width
    if not stays.any():
        return f"{kind}: every run left the box"
    late = batch.t >= 5.0

    def rmse(xhat, rows):
        return [100 * np.sqrt(np.mean(((xhat[i, late] - x[i, late]) / (box[:, 1] - box[:, 0])) ** 2)) for i in rows]

    rows = np.flatnonzero(stays)
    kept = [i for i in rows if np.isfinite(theirs[i]).all()]
    ours_rmse, ekf_rmse = np.mean(rmse(ours, rows)), np.mean(rmse(theirs, kept))
    lost = ("" if len(kept) == len(rows) else
            f", the EKF diverged on {len(rows) - len(kept)} of {len(rows)}: ratio on the rest")
    count = "" if stays.all() else f" on {stays.sum()} of {len(x)} runs"
    smapes = np.mean(metrics.smape(x[rows], ours[rows])), np.mean(metrics.smape(x[kept], theirs[kept]))
    return (f"{kind} {ours_rmse:.3g} % / {ekf_rmse:.3g} % ({np.mean(rmse(ours, kept)) / ekf_rmse:.2f}x{lost}), SMAPE "
            f"{smapes[0]:.2f} % / {smapes[1]:.2f} %{count}")


def test_train_inject_via_the_cli_ends_with_its_quality_and_what_to_run_next(model_dir_factory, tmp_path, capsys):
    """The closing summary: the observer and the EKF on 3 held-out noisy runs per input kind (seed 7), recomputed
    here from docs/protocol.md's draw, the share inside the trained domain, the wall time, the next commands."""
    import re

    import kklcasadi as kc
    from kklcasadi.evaluation.protocol import Protocol

    base = model_dir_factory("autonomous")
    out = tmp_path / "inject"
    assert main(["train", "--system", "duffing", "--method", "inject", "--out", str(out), "--base", str(base)]) == 0
    assert load_model(out).method == "inject"
    printed = capsys.readouterr().out
    assert re.search(rf"wrote    {re.escape(str(out))}/weights.npz and card.json \(\d+ s\)", printed)
    assert ("quality  the observer / the EKF on 3 held-out runs per input (noise std 0.1 / 0.1, seed 7; not the "
            "benchmark's trials), scored on the runs that stay in the box it was trained in: RMSE after 5 s in % of "
            "the box's width (ratio), SMAPE:") in printed
    obs = kc.load_observer(out)
    ekf = kc.EKF.for_noise(obs.system, obs.dt, process_std=0.1, measurement_std=0.1)
    inside = []
    for kind in ("zero", "constant", "sinusoid", "square"):
        batch = Protocol(n_trials=3, dt=obs.dt, seed=7).trials(obs.system, kind)
        est = obs.simulate(batch.t, batch.y, batch.u)
        assert _summary_entry(kind, obs, batch, est.xhat, ekf.simulate(batch.t, batch.y, batch.u).xhat) in printed
        inside.append(est.in_domain)
    if inside[0] is None:                             # this test model keeps no domain: the line is left out
        assert "\ndomain   " not in printed
    else:                                             # (the share's own test: the slide's below)
        assert "domain   " in printed
    assert f"next     kklcasadi evaluate {out} --ekf" in printed and f"kklcasadi demo --model {out}" in printed


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")
def test_bench_simulation_prints_both_paths_and_their_ratio(capsys):
    """Per integrator: the mapped batch and the loop (ms and trajectories/s of the same time) and
    a speed-up that is the ratio of the two printed times (no speed is asserted)."""
    import re

    assert main(["bench", "simulation", "--trials", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    timed = re.compile(r"duffing (\w+): (mapped batch|Python loop over) (?:of )?2 +([\d.]+) ms +([\d.]+) /s")
    rows = [timed.fullmatch(line.strip()) for line in lines if line.startswith("duffing")]
    assert [(r.group(1), r.group(2)) for r in rows] == [(m, p) for m in ("cvodes", "rk")
                                                         for p in ("mapped batch", "Python loop over")]
    ratios = [float(m) for m in re.findall(r"mapped / loop speed-up: ([\d.]+)x", "\n".join(lines))]
    assert len(ratios) == 2
    for i, ratio in enumerate(ratios):
        mapped_ms, loop_ms = float(rows[2 * i].group(3)), float(rows[2 * i + 1].group(3))
        # printed to 0.005 ms, 0.05 trajectories/s and 0.005 (the ratio)
        for row, ms in ((rows[2 * i], mapped_ms), (rows[2 * i + 1], loop_ms)):
            assert float(row.group(4)) == pytest.approx(2e3 / ms, abs=0.051 + 2e3 / ms * 0.006 / ms)
        assert ratio == pytest.approx(loop_ms / mapped_ms, abs=0.006 + ratio * (0.005 / loop_ms + 0.005 / mapped_ms))


def test_export_refuses_to_overwrite_and_needs_something_to_do(model_dir_factory, tmp_path, capsys):
    model = model_dir_factory("autonomous")
    assert main(["export", str(model), "--c", str(tmp_path / "c"), "--casadi", str(tmp_path / "step.casadi")]) == 0
    f = ca.Function.load(str(tmp_path / "step.casadi"))
    assert f.name_in() == ["z", "w", "y", "y_next", "u_next"]
    assert any(p.suffix == ".c" for p in (tmp_path / "c").iterdir())
    capsys.readouterr()
    step = (tmp_path / "step.casadi").read_bytes()
    assert main(["export", str(model), "--casadi", str(tmp_path / "step.casadi")]) == 2
    assert capsys.readouterr().err == (f"error: --casadi {tmp_path / 'step.casadi'}: the file exists; "
                                       "pass --overwrite to replace it\n")
    assert main(["export", str(model), "--c", str(tmp_path / "c")]) == 2
    assert capsys.readouterr().err == (f"error: --c {tmp_path / 'c'}: the directory is not empty; "
                                       "pass --overwrite to replace its files\n")
    assert (tmp_path / "step.casadi").read_bytes() == step            # refused: nothing was written
    assert main(["export", str(model), "--c", str(tmp_path / "c"), "--overwrite"]) == 0
    assert main(["export", str(model)]) == 2
    assert "nothing to export" in capsys.readouterr().err
    assert main(["export", str(model), "--c", str(tmp_path / "c32"), "--precision", "float32"]) == 0
    assert "#define casadi_real float" in (tmp_path / "c32" / "kkl_obs.c").read_text()


def _cli(*args, env=None):
    return subprocess.run([sys.executable, "-m", "kklcasadi", *args], capture_output=True, text=True, env=env)


@pytest.mark.parametrize("args, expected", [
    (["demo", "--model", "/nope"], "--model: expected an existing model directory or a shipped model's name"),
    (["demo", "--T", "-5"], "argument --T: expected a positive number, received '-5'"),
    (["evaluate", "models/duffing/inject", "--trials", "0"], "argument --trials: expected a positive integer"),
    (["export", "models/duffing/inject", "--name", "1bad", "--casadi", "x.casadi"], "argument --name: expected a C"),
    (["demo", "--system", "lorenz"], "argument --system: invalid choice: 'lorenz' (choose from 'duffing', "),
    (["demo", "--system", "vdp", "--model", "models/duffing/inject"], "--system vdp: the model"),
    (["train", "--method", "inject", "--out", "x"], "--system/--plant: give exactly one"),
    (["train", "--plant", "nope.py", "--method", "inject", "--out", "x"], "--plant: expected an existing Python"),
    (["train", "--system", "duffing", "--box-scale", "0", "--out", "x"],
     "argument --box-scale: expected a positive number, received '0'"),
    (["train", "--system", "duffing", "--method", "inject", "--box-scale", "0.5", "--out", "x"],
     "--box-scale: only --method autonomous or bank takes it, received --method inject"),
    (["train", "--system", "duffing", "--method", "autonomous", "--kinds", "pd", "--out", "x"],
     "--kinds: only --method obs or dyn or obs_stream or dyn_stream or bank takes it, received --method autonomous"),
])
def test_every_cli_error_is_one_line_with_exit_status_2(args, expected):
    result = _cli(*args)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0], result.stderr


def test_a_warning_of_a_command_is_one_line_and_the_library_keeps_pythons(monkeypatch, capsys):
    import warnings

    from kklcasadi.cli import estimate

    def warn_twice(args):
        warnings.warn("a note\nover two lines", UserWarning, stacklevel=2)
        warnings.warn("another note", RuntimeWarning, stacklevel=2)
        return 0

    monkeypatch.setattr(estimate, "run", warn_twice)
    shown = warnings.showwarning
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["estimate", "m", "--data", "d.csv", "--y-cols", "y", "--out", "o.csv"]) == 0
        assert warnings.showwarning is shown                          # Python's display is back after the command
    assert capsys.readouterr().err.splitlines() == ["warning: a note over two lines", "warning: another note"]


def test_torch_free_install_says_how_to_get_training(tmp_path, no_torch_env):
    env = no_torch_env
    for args in (["train", "--system", "duffing", "--method", "autonomous", "--out", str(tmp_path / "m")],
                 ["bench", "training"]):
        result = _cli(*args, env=env)
        assert result.returncode == 2 and "pip install 'kklcasadi[train]'" in result.stderr, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
    code = ("import kklcasadi as kc\ntry:\n    kc.train\nexcept ModuleNotFoundError as exc:\n    print(exc)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env).stdout
    assert "pip install 'kklcasadi[train]'" in out


# --- any sample time, noise levels, plants that escape, the default method ------------------------------------

ESCAPING = '''import casadi as ca
import kklcasadi as kc


def make_plant():
    """x' = x^2 + u: runs away from most of its box under a square input."""
    x, u = ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    return kc.System("runaway", x, u, x ** 2 + u, x, [[-1.0, 1.0]])
'''


@pytest.fixture
def escaping(tmp_path, model_dir_factory):
    path = tmp_path / "runaway.py"
    path.write_text(ESCAPING)
    plant = __import__("kklcasadi").systems.load_plant(f"{path}:make_plant")
    return f"{path}:make_plant", model_dir_factory("autonomous", system=plant)


def test_demo_runs_with_the_cards_process_noise_per_state(model_dir_factory, tmp_path, capsys):
    """A card recording one process-noise std per state (a bank trained with ``process_on="forced"``):
    the demo's run and its EKF use them, and the line prints them."""
    from kklcasadi import metrics
    from kklcasadi.estimators.ekf import EKF
    from kklcasadi.observer.kkl import load_observer
    from kklcasadi.plant import signals
    from kklcasadi.plant.simulate import simulate

    model = model_dir_factory("bank", card_extra={"noise": {"measurement_std": 0.05, "process_std": [0.0, 0.3]}})
    assert main(["demo", "--model", str(model), "--T", "4", "--seed", "2", "--out", str(tmp_path / "d.png")]) == 0
    out = capsys.readouterr().out
    assert "noise std process (0, 0.3), measurement 0.05 (the EKF's too)" in out, out
    obs = load_observer(model)
    tr = simulate(obs.system, obs.system.sample_box(1, 2)[0], signals.make("square", amplitude=[0.8], omega=1.0),
                  T=4.0, dt=obs.dt, process_std=[0.0, 0.3], measurement_std=0.05, seed=2)
    ekf = EKF.for_noise(obs.system, obs.dt, process_std=[0.0, 0.3], measurement_std=0.05)
    assert np.allclose(np.diag(ekf.Q), (np.maximum([0.0, 0.3], 1e-6) * obs.dt) ** 2)
    assert f"EKF {metrics.smape(tr.x, ekf.simulate(tr.t, tr.y, tr.u).xhat):6.2f} %" in out, out


def test_demo_of_a_plant_that_escapes_is_one_line(escaping, tmp_path):
    spec, model = escaping
    result = _cli("demo", "--plant", spec, "--model", str(model), "--T", "20", "--out", str(tmp_path / "d.png"))
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert lines[0].startswith("error: --input square: the plant 'runaway' escaped at t = ")
    assert "--amplitude" in lines[0]
    assert not (tmp_path / "d.png").exists()


def test_evaluate_counts_the_trials_that_escape_per_cell(escaping, tmp_path, capsys):
    spec, model = escaping
    out = tmp_path / "eval"
    assert main(["evaluate", str(model), "--plant", spec, "--trials", "4", "--kinds", "zero", "square", "--noise",
                 "off", "--vm", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    records = {r["kind"]: r for r in provenance.json_payload(__import__("json").loads(
        (out / "runaway_scores.json").read_text()))}
    square = records["square"]
    assert square["escaped"] > 0 and len(square["smape"]) + square["escaped"] == 4
    assert f"runaway square clean: {square['escaped']} of 4 trials escaped" in captured.err
    assert f"({square['escaped']} of 4 escaped)" in captured.out
    assert records["zero"]["escaped"] == 4 - len(records["zero"]["smape"])


def test_evaluate_and_compare_run_at_the_models_dt_and_name_the_flag_otherwise(model_dir_factory, tmp_path, capsys):
    model = model_dir_factory("autonomous", dt=0.1)
    assert main(["evaluate", str(model), "--trials", "1", "--kinds", "zero", "--noise", "off", "--vm", "--ekf",
                 "--dt", "0.1", "--measurement-std", "0.05", "--process-std", "0.02"]) == 0
    assert "| duffing EKF |" in capsys.readouterr().out
    result = _cli("evaluate", str(model), "--trials", "1", "--kinds", "zero", "--vm")
    assert result.returncode == 2 and result.stderr.strip() == (
        f"error: --dt: the protocol runs at dt = 0.05 s, the model {model} at 0.1 s; pass --dt 0.1 (or a model "
        "trained at 0.05 s)")
    root = model.parent.parent / "roots"
    (root / "duffing").mkdir(parents=True)
    (root / "duffing" / "autonomous").symlink_to(model)
    result = _cli("compare", "--systems", "duffing", "--method", "autonomous", "--models-root", str(root),
                  "--trials", "1", "--out", str(tmp_path / "c"))
    assert result.returncode == 2 and "error: --dt: the protocol runs at dt = 0.05 s" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    result = _cli("evaluate", str(model), "--dt", "0.03")
    assert result.returncode == 2 and "--dt 0.03: expected a sample time that divides the horizon T = 50 s" in \
        result.stderr


def test_demo_tells_shipped_models_from_yours(model_dir_factory, tmp_path, capsys):
    assert main(["demo", "--T", "2", "--out", str(tmp_path / "a.png")]) == 0
    assert "model    shipped model models/duffing/bank" in capsys.readouterr().out
    model = model_dir_factory("autonomous")
    assert main(["demo", "--model", str(model), "--T", "2", "--measurement-std", "0.02", "--out",
                 str(tmp_path / "b.png")]) == 0
    out = capsys.readouterr().out
    assert f"model    your model {model}" in out and "measurement 0.02 (the EKF's too)" in out
    assert main(["demo", "--model", str(model), "--dt", "0.004"]) == 2
    assert "--dt 0.004: the model" in capsys.readouterr().err


def test_demo_never_writes_over_a_file_and_writes_its_figure_whole(tmp_path, capsys, monkeypatch):
    png = tmp_path / "a.png"
    assert main(["demo", "--T", "2", "--out", str(png)]) == 0
    first = png.read_bytes()
    capsys.readouterr()
    assert main(["demo", "--T", "2", "--out", str(png)]) == 2
    captured = capsys.readouterr()
    assert captured.err == (f"error: --out: {png} exists and this command does not overwrite; move it away, or "
                            "choose another --out.\n") and captured.out == ""          # before any run
    assert png.read_bytes() == first

    def failing(fd):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", failing)
    assert main(["demo", "--T", "2", "--out", str(tmp_path / "b.png")]) == 2
    assert "error: disk full" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]


def test_train_without_a_method_trains_bank_at_the_given_dt_and_noise(tmp_path, capsys, monkeypatch):
    pytest.importorskip("torch")
    from dataclasses import replace

    import kklcasadi.train as training

    def tiny(system, method, **kw):          # the default bank recipe on a budget a test can afford
        config = training.default_config.__wrapped__(system, method, **kw)
        return replace(config, rollouts=replace(config.rollouts, n_traj=12, T=2.0),
                       decoder=replace(config.decoder, loop=replace(config.decoder.loop, batch_size=64)))

    tiny.__wrapped__ = training.default_config
    monkeypatch.setattr(training, "default_config", tiny)
    out = tmp_path / "bank"
    assert main(["train", "--system", "duffing", "--dt", "0.02", "--measurement-std", "0.03", "--process-std", "0.2",
                 "--epochs", "1", "--out", str(out)]) == 0
    assert "method: bank (the observer for a new plant" in capsys.readouterr().out
    model = load_model(out)
    assert model.method == "bank" and model.dt == 0.02
    assert model.spec.measurement_std == 0.03 and model.spec.process_std == (0.2, 0.2)     # per state
    assert model.card["training"]["measurement_std"] == 0.03


def test_noise_flags_name_the_methods_that_take_them(model_dir_factory, tmp_path):
    base = model_dir_factory("autonomous")
    result = _cli("train", "--system", "duffing", "--method", "inject", "--base", str(base), "--out",
                  str(tmp_path / "i"), "--measurement-std", "0.1")
    assert result.returncode == 2, result.stderr
    assert "--measurement-std: only --method autonomous or bank takes it, received --method inject" in result.stderr
    result = _cli("train", "--system", "duffing", "--method", "autonomous", "--out", str(tmp_path / "a"),
                  "--process-std", "0.1")
    assert result.returncode == 2 and "--process-std: only --method bank takes it" in result.stderr


@pytest.mark.parametrize("method, box_scale", [("bank", lambda c: c.rollouts.box_scale),
                                               ("autonomous", lambda c: c.box_scale)])
def test_train_flags_set_the_fields_the_method_keeps_them_in(method, box_scale):
    pytest.importorskip("torch")
    from dataclasses import replace

    from kklcasadi.cli import build_parser
    from kklcasadi.cli.flags import plant_of
    from kklcasadi.cli.train import training_config
    from kklcasadi.train import default_config

    args = build_parser().parse_args(["train", "--plant", "examples/damped3_plant.py:make_plant", "--method", method,
                                      "--measurement-std", "0.02", "--box-scale", "0.5", "--out", "x"])
    config = training_config(plant_of(args), method, args)
    default = default_config("damped3", method)
    assert box_scale(config) == 0.5 and box_scale(default) == 1.0
    assert config.measurement_std == 0.02
    # nothing else moves: the flags' fields put back give the default
    back = replace(config, measurement_std=default.measurement_std)
    back = replace(back, rollouts=default.rollouts) if method == "bank" else replace(back, box_scale=1.0)
    assert back == default


def test_train_kinds_sets_the_bank_runs_families_and_refuses_unknown_ones():
    pytest.importorskip("torch")
    from kklcasadi import systems
    from kklcasadi.cli import build_parser
    from kklcasadi.cli.flags import CommandError, plant_of
    from kklcasadi.cli.train import training_config
    from kklcasadi.plant.runs import FAMILIES
    from kklcasadi.train.decoder import LOSSES

    def config(*kinds):
        args = build_parser().parse_args(["train", "--plant", "examples/damped3_plant.py:make_plant",
                                          "--kinds", *kinds, "--out", "x"])
        return training_config(plant_of(args), "bank", args)

    assert config("square", "pd").rollouts.kinds == ("square", "pd")
    assert "pd" in FAMILIES
    args = build_parser().parse_args(["train", "--plant", "examples/damped3_plant.py:make_plant", "--skip-path",
                                      "--out", "x"])
    assert training_config(plant_of(args), "bank", args).decoder.skip   # the linear path: asked for, else none
    assert not config("square").decoder.skip
    args = build_parser().parse_args(["train", "--plant", "examples/damped3_plant.py:make_plant", "--teacher",
                                      "models/duffing/bank", "--out", "x"])
    assert training_config(plant_of(args), "bank", args).teacher == "models/duffing/bank"     # distillation
    assert config("square").teacher is None
    # the decoders' loss (DecoderConfig.loss): the CLI's choices are the trainer's, the weight only with mse+smape
    args = build_parser().parse_args(["train", "--plant", "examples/damped3_plant.py:make_plant", "--loss", "mse+smape",
                                      "--smape-weight", "0.5", "--out", "x"])
    decoder = training_config(plant_of(args), "bank", args).decoder
    assert (decoder.loss, decoder.smape_weight) == ("mse+smape", 0.5) and config("square").decoder.loss == "mse"
    loss = next(a for a in build_parser()._subparsers._group_actions[0].choices["train"]._actions
                if a.dest == "loss")
    assert tuple(loss.choices) == LOSSES
    args = build_parser().parse_args(["train", "--plant", "examples/damped3_plant.py:make_plant", "--smape-weight",
                                      "0.5", "--out", "x"])
    with pytest.raises(CommandError, match=r"^--smape-weight: weighs the SMAPE term of --loss mse\+smape, "
                                           r"received --loss mse \(the default\); add --loss mse\+smape$"):
        training_config(plant_of(args), "bank", args)
    # Roessler's shipped recipe already fits mse+smape (SHIPPED): a weight alone retunes it
    args = build_parser().parse_args(["train", "--system", "rossler", "--smape-weight", "1.5", "--out", "x"])
    decoder = training_config(systems.get("rossler"), "bank", args).decoder
    assert (decoder.loss, decoder.smape_weight) == ("mse+smape", 1.5)
    args = build_parser().parse_args(["train", "--system", "rossler", "--loss", "mse", "--smape-weight", "1.5",
                                      "--out", "x"])
    with pytest.raises(CommandError, match=r"received --loss mse; add --loss mse\+smape$"):
        training_config(systems.get("rossler"), "bank", args)
    args = build_parser().parse_args(["train", "--plant", "examples/damped3_plant.py:make_plant", "--method",
                                      "autonomous", "--loss", "smape", "--out", "x"])
    with pytest.raises(CommandError, match=r"^--loss: only --method bank takes it, received --method autonomous$"):
        training_config(plant_of(args), "autonomous", args)
    with pytest.raises(CommandError, match=r"^--kinds: expected a non-empty subset of .*'pd'.*received \('chirp',\)"):
        config("chirp")
    # the latent's model copies (BankConfig.copies): one per weight, bank only
    args = build_parser().parse_args(["train", "--plant", "examples/damped3_plant.py:make_plant", "--copies", "1",
                                      "100", "--out", "x"])
    assert training_config(plant_of(args), "bank", args).copies == (1.0, 100.0) and config("square").copies == ()
    args = build_parser().parse_args(["train", "--plant", "examples/damped3_plant.py:make_plant", "--method",
                                      "autonomous", "--copies", "1", "--out", "x"])
    with pytest.raises(CommandError, match=r"^--copies: only --method bank takes it, received --method autonomous$"):
        training_config(plant_of(args), "autonomous", args)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "--system", "duffing", "--copies", "-1", "--out", "x"])
    # copies at the corners of a family's parameter box (BankConfig.corner_copies), refused where there is no family
    args = build_parser().parse_args(["train", "--system", "duffing", "--param-spread", "0.3", "--corner-copies", "1",
                                      "--out", "x"])
    from kklcasadi.plant import systems

    assert training_config(systems.get("duffing", param_spread=0.3), "bank", args).corner_copies == (1.0,)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "--system", "duffing", "--corner-copies", "0", "--out", "x"])


def test_the_closing_summary_scores_in_the_trained_box_and_names_the_runs_that_leave_it(model_dir_factory):
    """A slide driven by a force (q' = v, v' = -v + u; y = q): the summary's open-loop inputs drive the position
    out of the box the observer was trained in (the EMPS axis of issue 45). The old summary gave a ratio of SMAPEs
    over those runs, where the EKF's SMAPE is small only because |q| is large; the new one scores the runs that
    stay in the box (RMSE over the box's width beside SMAPE) and counts the others apart, naming the integrator."""
    import kklcasadi as kc
    from kklcasadi import metrics
    from kklcasadi.cli.train import summary
    from kklcasadi.evaluation.protocol import Protocol

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    plant = kc.System("slide", x, u, ca.vertcat(x[1], -x[1] + u), x[0], [[-1, 1], [-1, 1]], u_box=[[-1, 1]])
    path = model_dir_factory("autonomous", system=plant)
    obs = kc.load_observer(path, system=plant)
    assert obs.domain is None                                   # trained box: the plant's, [-1, 1]^2
    ekf = kc.EKF.for_noise(plant, obs.dt, process_std=0.1, measurement_std=0.1)
    text = summary(path, plant, None)
    left, stayed = {}, 0
    for kind in ("zero", "constant", "sinusoid", "square"):
        batch = Protocol(n_trials=3, dt=obs.dt, seed=7).trials(plant, kind)
        ours = obs.simulate(batch.t, batch.y, batch.u).xhat
        theirs = ekf.simulate(batch.t, batch.y, batch.u).xhat
        assert _summary_entry(kind, obs, batch, ours, theirs) in text
        out = np.abs(batch.x).max(axis=(1, 2)) > 1.25
        stayed += int((~out).sum())
        if out.any():
            left[kind] = int(out.sum())
        if out.all():                                            # the old summary's ratio is not printed for them
            old = np.mean(metrics.smape(batch.x, ours)) / np.mean(metrics.smape(batch.x, theirs))
            assert f"{kind}: every run left the box" in text and f"({old:.2f}x)" not in text
    assert "constant" in left and stayed > 0                     # both cases are exercised
    assert "\ntraining " not in text                             # this card records no recipe of training runs
    assert (f"outside  {sum(left.values())} run(s) left that box ("
            + ", ".join(f"{kind} {n}" for kind, n in left.items())
            + "; x[0] integrates: open-loop inputs drive it out): not the observer's domain, it extrapolates there"
            ) in text


@pytest.mark.parametrize("stays,line", [
    ([True, True, False, False], "domain   75.0 % of the estimates inside the domain the maps were trained on, on the "
                                 "runs that stay in the box (42.5 % over every run)"),
    ([True, True, True, True], "domain   42.5 % of the estimates inside the domain the maps were trained on, on the "
                               "runs that stay in the box"),
    ([False, False, False, False], "domain   42.5 % of the estimates inside the domain the maps were trained on "
                                   "(every run left the box)"),
])
def test_the_summary_gives_the_domain_share_on_the_runs_that_stay_in_the_box(stays, line):
    """EMPS's summary said 30.6 % inside the domain, over runs that had left the trained box; the share is now taken
    on the runs that stay in it (here (1 + 0.5) / 2 = 75 %), the share over every run ((1 + 0.5 + 0 + 0.2) / 4 =
    42.5 %) beside it."""
    from kklcasadi.cli.train import domain_line

    assert domain_line(np.array([1.0, 0.5, 0.0, 0.2]), np.array(stays)) == line


def test_the_closing_summary_scores_runs_drawn_by_the_cards_training_recipe(model_dir_factory):
    """A card that records its training runs' recipe (``training.config.rollouts``, as a bank model's; here the
    shipped duffing bank model's, on a small random model): the summary's line draws 12 held-out runs by it (seed
    7, not the training seed 11) and scores the observer and the EKF on them, recomputed here."""
    import json
    from dataclasses import fields, replace
    from pathlib import Path

    import kklcasadi as kc
    from kklcasadi import metrics
    from kklcasadi.cli.train import recipe_lines
    from kklcasadi.plant.runs import RolloutConfig, rollouts

    shipped = json.loads((Path(__file__).resolve().parents[1] / "models/duffing/bank/card.json").read_text())
    record = shipped["training"]["config"]["rollouts"]
    assert shipped["training"]["seed"] != 7 and shipped["training"]["time_scale"] == 1.0
    path = model_dir_factory("autonomous", card_extra={"training": {"config": {"rollouts": record}, "time_scale": 1.0}})
    obs = kc.load_observer(path)
    box = obs.system.x0_box
    ekf = kc.EKF.for_noise(obs.system, obs.dt, process_std=0.1, measurement_std=0.1)
    lines = recipe_lines(obs, box, ekf, 0.1, 0.1)
    recipe = RolloutConfig(**{f.name: tuple(record[f.name]) if isinstance(record[f.name], list) else record[f.name]
                              for f in fields(RolloutConfig) if f.name in record})
    runs = rollouts(obs.system, replace(recipe, n_traj=12, chunk=12), 7, dt=obs.dt, measurement_std=0.1,
                    process_std=0.1, time_scale=1.0)
    assert len(runs.x) == 12                                     # escape_scale 10: none is cut
    ours = obs.simulate(runs.t, runs.y, runs.u).xhat
    theirs = ekf.simulate(runs.t, runs.y, runs.u).xhat
    late = runs.t >= 5.0

    def rmse(xhat):
        return np.mean([100 * np.sqrt(np.mean(((xhat[i, late] - runs.x[i, late]) / (box[:, 1] - box[:, 0])) ** 2))
                        for i in range(12)])

    assert lines == [f"training the same on 12 held-out runs drawn as its training runs were (families zero, "
                     f"constant, sinusoid, square, multisine, feedback; seed 7): RMSE {rmse(ours):.3g} % / "
                     f"{rmse(theirs):.3g} % ({rmse(ours) / rmse(theirs):.2f}x), SMAPE "
                     f"{np.mean(metrics.smape(runs.x, ours)):.2f} % / {np.mean(metrics.smape(runs.x, theirs)):.2f} %"]


def test_the_closing_summary_counts_the_runs_on_which_the_ekf_diverged(model_dir_factory, monkeypatch):
    """An EKF can diverge (a stiff plant, a first update from a wide prior): its runs with non-finite estimates
    are counted and left out of the ratio, instead of a 'nan %' for the whole input kind."""
    import dataclasses

    import kklcasadi as kc
    from kklcasadi.cli.train import summary
    from kklcasadi.estimators.ekf import EKF
    from kklcasadi.evaluation.protocol import Protocol

    path = model_dir_factory("autonomous")
    simulate = EKF.simulate

    def first_run_lost(self, t, y, u, **kw):
        est = simulate(self, t, y, u, **kw)
        xhat = est.xhat.copy()
        xhat[0, 5:] = np.nan
        return dataclasses.replace(est, xhat=xhat)

    monkeypatch.setattr(EKF, "simulate", first_run_lost)
    obs = kc.load_observer(path)
    text = summary(path, obs.system, None)
    batch = Protocol(n_trials=3, dt=obs.dt, seed=7).trials(obs.system, "zero")     # its runs stay in the box
    ekf = kc.EKF.for_noise(obs.system, obs.dt, process_std=0.1, measurement_std=0.1)
    entry = _summary_entry("zero", obs, batch, obs.simulate(batch.t, batch.y, batch.u).xhat,
                           first_run_lost(ekf, batch.t, batch.y, batch.u).xhat)
    assert ", the EKF diverged on 1 of 3: ratio on the rest)" in entry and entry in text


def test_the_recipe_line_scores_runs_shorter_than_the_settling_time_on_their_second_half(model_dir_factory):
    """A fast plant's training runs last less than the summary's 5 s (the card's ``time_scale`` shortens them): the
    recipe line scores their second half and says so, where it printed ``nan %`` (an empty mean) before."""
    import json
    from pathlib import Path

    import kklcasadi as kc
    from kklcasadi.cli.train import recipe_lines

    shipped = json.loads((Path(__file__).resolve().parents[1] / "models/duffing/bank/card.json").read_text())
    record = shipped["training"]["config"]["rollouts"]
    path = model_dir_factory("autonomous", card_extra={"training": {"config": {"rollouts": record},
                                                                    "time_scale": 40.0}})
    obs = kc.load_observer(path)
    ekf = kc.EKF.for_noise(obs.system, obs.dt, process_std=0.1, measurement_std=0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)                 # no mean of an empty slice
        (line,) = recipe_lines(obs, obs.system.x0_box, ekf, 0.1, 0.1)
    assert "RMSE after" in line and "nan" not in line, line
