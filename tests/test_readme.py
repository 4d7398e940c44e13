"""The README is a front door whose commands run as written, from a directory outside the clone; its one-screen
results summary follows from the stored results; every page of docs/results/ is what the script that summarises
it writes now (docs/claims.md says which command and test back each figure)."""

import json
import re
import runpy
import shlex
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi import provenance
from kklcasadi.provenance import json_payload

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
KINDS = ("zero", "constant", "sinusoid", "square")
SYSTEMS = ("duffing", "vdp", "rossler", "fhn")
needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc is not installed")


def section(title):
    """The README's section under ``## title`` (to the next ``## ``)."""
    return re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", README, re.M | re.S).group(1)


def blocks(title, language):
    return re.findall(rf"```{language}\n(.*?)```", section(title), re.S)


def scores(system):
    """``{(method, kind, noisy): per-trial SMAPE array}`` of ``results/protocol/<system>/<system>_scores.json``."""
    cells = json_payload(json.loads((ROOT / "results" / "protocol" / system / f"{system}_scores.json").read_text()))
    return {(c["method"], c["kind"], c["noisy"]): np.array(c["smape"]) for c in cells}


def smape_by_the_formula(x, xhat):
    """docs/protocol.md: 100 / (N nx) sum_k sum_i 2 |x - xhat| / (|x| + |xhat| + 1e-8)."""
    return 100 * np.mean(2 * np.abs(x - xhat) / (np.abs(x) + np.abs(xhat) + 1e-8))


def span(values, digits=2):
    lo, hi = f"{min(values):.{digits}f}", f"{max(values):.{digits}f}"
    return f"{lo}x" if lo == hi else f"{lo}-{hi}x"


# --- the front door -----------------------------------------------------------------------------------------------

def test_the_readme_is_a_front_door_under_300_lines():
    lines = README.splitlines()
    assert len(lines) < 300
    headings = [line for line in lines if line.startswith("## ")]
    assert lines.index("## Your own data") < 120                        # a newcomer reaches their own log early
    for title in ("## Run it", "## From a plant to C in four commands", "## Use it from Python", "## Your own plant",
                  "## Results at a glance", "## A real positioning axis (EMPS)", "## Robust observers"):
        assert title in headings, title
    for link in re.findall(r"\]\((docs/[^)]+)\)", README) + re.findall(r"`(docs/[\w/.-]+\.md)`", README):
        assert (ROOT / link).is_file(), link
    assert "pip install torch --index-url https://download.pytorch.org/whl/cpu" in README


def test_the_readme_commands_are_the_ones_ci_runs():
    commands = re.findall(r"```bash\n(python3 -m venv .*?)\n```", README)
    assert len(commands) == 2 and commands[0].endswith("kklcasadi demo")
    assert commands[1].endswith("ruff check . && python -m pytest -q -n 2")
    ci = (ROOT / ".ci" / "run").read_text()
    assert 'pip install -q -e ".[test]" && ruff check . && python -m pytest -q -n 2' in ci


def test_the_python_snippet_runs_from_a_directory_outside_the_clone_and_prints_a_recomputation(
        tmp_path, monkeypatch, capsys):
    (block,) = blocks("Use it from Python", "python")
    monkeypatch.chdir(tmp_path)                                      # no models/ here: shipped models by name
    namespace: dict = {}
    exec(compile(block, "README.md", "exec"), namespace)
    out = capsys.readouterr().out.splitlines()
    obs, tr, est = namespace["obs"], namespace["tr"], namespace["est"]
    assert obs.model.path == (ROOT / "models" / "duffing" / "bank").resolve()
    assert (tmp_path / "build" / "obs" / "kkl_obs.c").exists()
    assert any("Proposition 1 certificate" in line for line in out)
    # the estimate, one obs.step call per sample (not simulate's mapaccum), bitwise
    z, w = np.zeros(obs.nz), obs.memory_init(tr.y[0], tr.u[0])
    xhat = [np.array(obs.decode(z, w)).ravel()]
    for k in range(tr.t.size - 1):
        z, w, x_next = obs.step(z, w, tr.y[k], tr.y[k + 1], tr.u[k + 1])
        xhat.append(np.array(x_next).ravel())
    np.testing.assert_array_equal(np.array(xhat), est.xhat)
    smape = smape_by_the_formula(tr.x, est.xhat)
    assert float(out[0]) == pytest.approx(smape, rel=1e-12)
    cell = scores("duffing")[("bank", "square", True)]                 # inside its 100 protocol trials' spread
    assert cell.min() <= smape <= cell.max()
    np.testing.assert_array_equal(est.in_domain, [bool(obs.domain_check(zk, wk, xk)) for zk, wk, xk in
                                                  zip(est.z, np.concatenate([tr.y, tr.u], axis=1), est.xhat)])
    assert float(out[1]) == est.in_domain.mean()
    # the certificate it prints is the stored record (kklcasadi certificate)
    record = json_payload(json.loads((ROOT / "results" / "certificates" / "all" /
                                      "certificates_zero.json").read_text()))[0]
    assert record.pop("model") == "models/duffing/autonomous"
    computed = namespace["cert"].to_json()
    assert sorted(computed) == sorted(record)
    for key, value in record.items():
        if isinstance(value, float) or key == "domain":
            np.testing.assert_allclose(computed[key], value, rtol=1e-9, err_msg=key)
        else:
            assert computed[key] == value, key
    rerun = "\n".join(line for line in block.splitlines() if "generate_c" in line)
    exec(compile(rerun, "README.md", "exec"), namespace)               # a second run overwrites its own files


def _pipeline(tmp_path):
    """The README's plant file and the four commands, and a log of the plant in ``tmp_path`` (outside the clone)."""
    plant_file = next(b for b in blocks("Your own plant", "python") if b.startswith("# pendulum.py"))
    (tmp_path / "pendulum.py").write_text(plant_file)
    (commands,) = blocks("From a plant to C in four commands", "bash")
    plant = kc.systems.load_plant(str(tmp_path / "pendulum.py") + ":make_plant")
    tr = kc.simulate(plant, [0.4, 0.0], kc.signals.make("sinusoid", amplitude=0.3, omega=1.0), T=10.0, dt=0.05,
                     process_std=0.05, measurement_std=0.01, seed=4)
    rows = "".join(f"{t!r},{y!r},{u!r}\n" for t, y, u in zip(tr.t.tolist(), tr.y[:, 0].tolist(), tr.u[:, 0].tolist()))
    (tmp_path / "log.csv").write_text("time,theta,u\n" + rows)
    return plant, commands.strip().splitlines()


def _run(line, cwd):
    done = subprocess.run(["bash", "-c", line], cwd=cwd, capture_output=True, text=True,
                          env={"PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin", "HOME": str(cwd)})
    assert done.returncode == 0, (line, done.stderr[-2000:])
    return done.stdout


def _run_here(line, cwd, monkeypatch):
    """A ``kklcasadi ...`` line through the command line's own entry point in this process (as the console
    script calls it, without an interpreter's start-up per line), any other line in bash; from ``cwd``."""
    if not line.startswith("kklcasadi "):
        return _run(line, cwd)
    from kklcasadi.cli import main

    monkeypatch.chdir(cwd)
    assert main(shlex.split(line)[1:]) == 0, line


def _check_pipeline_outputs(tmp_path, plant):
    est = np.genfromtxt(tmp_path / "est.csv", delimiter=",", names=True, skip_header=1)
    obs = kc.load_observer(tmp_path / "pendulum_bank", system=plant)
    log = np.genfromtxt(tmp_path / "log.csv", delimiter=",", names=True)
    expected = obs.simulate(log["time"], log["theta"][:, None], log["u"][:, None]).xhat
    np.testing.assert_allclose(np.column_stack([est["x1"], est["x2"]]), expected, rtol=1e-12, atol=1e-12)  # compiled
    assert provenance.read(tmp_path / "est.csv").command.startswith("kklcasadi estimate pendulum_bank")
    from_c = np.genfromtxt(tmp_path / "est_c.csv", delimiter=",", names=True)       # read by name, header written
    assert from_c.dtype.names == ("time", "x1", "x2", "in_domain", "status")
    np.testing.assert_array_equal(from_c["time"], log["time"])
    np.testing.assert_array_equal(from_c["status"], 0)                              # every sample fed
    np.testing.assert_allclose(np.column_stack([from_c["x1"], from_c["x2"]]), expected, rtol=1e-12,
                               atol=1e-12)                                          # the vector exp/tanh: 1e-14


@needs_gcc
def test_the_pipeline_runs_from_a_directory_outside_the_clone(tmp_path, monkeypatch):
    """Every command of "From a plant to C" from a temporary directory: estimate, export, the C build and its run
    as written, on a bank of the README's plant trained here with a small budget (the README's train command,
    minutes, runs as written in the slow test below; here its flags are parsed and checked by the command's own
    code); the C program's estimates are the Python observer's, and estimate's are too."""
    from kklcasadi.cli import build_parser
    from kklcasadi.cli.train import training_config
    from kklcasadi.train import train_observer

    plant, commands = _pipeline(tmp_path)
    train, rest = commands[0], commands[1:]
    args = build_parser().parse_args(shlex.split(train)[1:])
    assert (args.command, args.plant, args.out) == ("train", "pendulum.py:make_plant", "pendulum_bank")
    config = training_config(plant, "bank", args)
    assert config.measurement_std == 0.01
    small = replace(config, rollouts=replace(config.rollouts, n_traj=8, T=10.0),
                    decoder=replace(config.decoder, loop=replace(config.decoder.loop, epochs=1)))
    train_observer(plant, "bank", tmp_path / "pendulum_bank", config=small, dt=0.05, seed=0, progress=False,
                   threads=1)
    for line in rest:
        _run_here(line, tmp_path, monkeypatch)
    _check_pipeline_outputs(tmp_path, plant)


@needs_gcc
@pytest.mark.slow
def test_the_whole_pipeline_runs_as_written(tmp_path):
    """The four commands verbatim, training included (about 2 minutes on 2 cores)."""
    plant, commands = _pipeline(tmp_path)
    printed = _run(commands[0], tmp_path)
    assert "quality  the observer / the EKF" in printed and "next     kklcasadi evaluate" in printed
    for line in commands[1:]:
        _run(line, tmp_path)
    _check_pipeline_outputs(tmp_path, plant)


def test_every_command_line_of_the_readme_parses_and_names_models_that_exist(tmp_path, monkeypatch):
    """The ``kklcasadi`` lines of every bash block parse with the command line's own parser, and every model they
    name is a shipped model's name or a folder an earlier command of the README writes."""
    from kklcasadi.cli import build_parser
    from kklcasadi.model.shipped import resolve

    monkeypatch.chdir(tmp_path)
    written, lines = set(), []
    for block in re.findall(r"```bash\n(.*?)```", README, re.S):
        lines += [line.split("#")[0].strip() for line in block.replace("\\\n", " ").splitlines()
                  if line.startswith("kklcasadi ")]
    assert len(lines) >= 12
    for line in lines:
        args = build_parser().parse_args(shlex.split(line)[1:])
        for model in [getattr(args, "model", None), *(getattr(args, "models", None) or [])]:
            if model is not None and model not in written and args.command not in ("demo",):
                assert resolve(model), line
        if args.command == "demo" and args.model is not None:
            assert args.model in written, line
        if args.command == "train":
            written.add(args.out)


# --- the results ----------------------------------------------------------------------------------------------------

def _pages(monkeypatch):
    """Every generated page of docs/results/: {name: (the command that writes it, a function giving its text)}."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks" / "accuracy"))
    pages = {"protocol.md": ("python benchmarks/summarize.py",
                             runpy.run_path(str(ROOT / "benchmarks" / "summarize.py"))["page"]),
             "generalisation.md": ("python benchmarks/summarize_generalisation.py",
                                   runpy.run_path(str(ROOT / "benchmarks" / "summarize_generalisation.py"))["page"]),
             "levers.md": ("python benchmarks/accuracy/tables.py --page",
                           runpy.run_path(str(ROOT / "benchmarks" / "accuracy" / "tables.py"))["page"])}
    pages["robustness.md"] = ("python benchmarks/summarize_robustness.py",
                              runpy.run_path(str(ROOT / "benchmarks" / "summarize_robustness.py"))["page"])
    emps = runpy.run_path(str(ROOT / "examples" / "emps_rig.py"), run_name="emps_rig")
    record = json_payload(json.loads((ROOT / "results" / "real_rig" / "emps" / "emps.json").read_text()))
    pages["emps.md"] = (emps["COMMAND"], lambda: emps["page"](record))
    rest = runpy.run_path(str(ROOT / "benchmarks" / "summarize_pages.py"))["PAGES"]
    pages.update({name: ("python benchmarks/summarize_pages.py", page) for name, page in rest.items()})
    return pages


def test_every_results_page_is_what_its_script_writes_now(monkeypatch):
    pages = _pages(monkeypatch)
    assert sorted(pages) == sorted(p.name for p in (ROOT / "docs" / "results").glob("*.md"))
    for name, (command, page) in pages.items():
        path = ROOT / "docs" / "results" / name
        text = page()
        assert provenance.strip_markdown(path.read_text()) == text, f"docs/results/{name} is stale: run {command}"
        assert provenance.read(path).command == command and f"Generated by `{command}`" in text
        for file in re.findall(r"`(results/[\w/.-]+\.(?:json|md|png))`", text):
            assert (ROOT / file).is_file(), (name, file)               # every file a page names exists


def _step_rows(path):
    """``{model: (C default us, instructions)}`` of a ``kklcasadi bench observer --write`` table."""
    rows = {}
    for line in provenance.strip_markdown(path.read_text()).splitlines():
        if line.startswith("| `"):
            cols = [c.strip() for c in line.strip().strip("|").split("|")]
            rows[cols[0].strip("`")] = (cols[2], cols[-1])
    return rows


def test_which_observer_to_pick_follows_from_the_results():
    """Each row of the compact observers' table, recomputed from their scored trials (the protocol's noisy cells and
    generalise's default seed, beside the bank's stored scores on the same trials: the EKF's are equal; the last
    column the compact's largest ratio to the bank over the generalisation cases) and from the step table written
    by kklcasadi bench observer; every shipped compact has its row."""
    text = re.sub(r"\s+", " ", section("Which observer to pick"))
    names = {"duffing": "Duffing", "vdp": "Van der Pol", "rossler": "Roessler", "fhn": "FitzHugh-Nagumo"}
    systems = [s for s in SYSTEMS if (ROOT / "models" / s / "compact" / "card.json").exists()]
    assert systems
    for s in systems:
        cells = {(c["method"], c["kind"]): c["smape_mean"] for c in json_payload(json.loads(
            (ROOT / "results" / "protocol" / s / "compact" / f"{s}_scores.json").read_text())) if c["noisy"]}
        shipped = {(m, k): v.mean() for (m, k, noisy), v in scores(s).items() if noisy}    # the bank's, same trials
        assert all(cells["EKF", k] == pytest.approx(shipped["EKF", k], rel=1e-12) for k in KINDS)
        protocol = span([cells["compact", k] / shipped["bank", k] for k in KINDS], 3)

        def report(path):
            return json_payload(json.loads((ROOT / "results" / "generalisation" / s / path).read_text()))

        compact, bank = report(f"compact/{s}_generalisation.json"), report(f"{s}_generalisation.json")
        assert [c["ekf"]["smape_mean"] for c in compact["cases"]] == [c["ekf"]["smape_mean"] for c in bank["cases"]]
        worst = [max(c["models"][label]["ratio_ekf"] for c in r["cases"]) for r, label in ((compact, "compact"),
                                                                                             (bank, "bank"))]
        per_case = max(c["models"]["compact"]["smape_mean"] / b["models"]["bank"]["smape_mean"]
                       for c, b in zip(compact["cases"], bank["cases"]))
        steps = _step_rows(ROOT / "results" / "speed" / s / f"observer_step_{s}.md")
        (c_us, c_n), (b_us, b_n) = steps[f"{s}/compact"], steps[f"{s}/bank"]
        assert (f"| {names[s]} | {c_us} / {b_us} us | {c_n} / {b_n} | {protocol} | {worst[0]:.3f}x and "
                f"{worst[1]:.3f}x | {per_case:.3f}x |") in text, s


def test_the_results_at_a_glance_follow_from_the_results(monkeypatch):
    """Each figure of the README's one-screen summary, recomputed from the stored results it names."""
    glance = section("Results at a glance")
    text = re.sub(r"\s+", " ", glance)
    ratio = {s: [scores(s)[("bank", k, True)].mean() / scores(s)[("EKF", k, True)].mean() for k in KINDS]
             for s in SYSTEMS}
    names = {"duffing": "Duffing", "vdp": "Van der Pol", "rossler": "Roessler", "fhn": "FitzHugh-Nagumo"}
    for s in SYSTEMS:
        assert f"{span(ratio[s])} on {names[s]}" in text, s
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    paper = runpy.run_path(str(ROOT / "benchmarks" / "summarize.py"))["PAPER_BEST"]    # docs/protocol.md's
    others = [min(v.mean() for (m, k2, n), v in scores(s).items() if n and k2 == k and m not in ("bank", "EKF"))
              / scores(s)[("EKF", k, True)].mean() for s in SYSTEMS for k in KINDS]
    assert f"the paper's observers, trained noise-free, {min(others):.1f}-{max(others):.1f}x" in text
    beaten = [p / scores(s)[("bank", k, False)].mean() for s in SYSTEMS for p, k in zip(paper[s], KINDS)]
    assert f"beats the paper's best in every cell ({min(beaten):.1f}-{max(beaten):.0f}x)" in text
    ekf_ahead = [s for s in SYSTEMS if all(scores(s)[("EKF", k, False)].mean() < scores(s)[("bank", k, False)].mean()
                                           for k in KINDS)]
    count = {3: "three of the four systems", 4: "all four systems"}[len(ekf_ahead)]
    assert f"the EKF, with its exact model, is ahead on {count}" in text
    listed = [names[s] for s in ekf_ahead]
    listed_text = ", ".join(listed[:-1]) + " and " + listed[-1]
    lose = [r for s in SYSTEMS for r in ratio[s] if r > 1]
    assert f"the EKF is still ahead in {len(lose)} of the 16 cells (by {round(100 * (min(lose) - 1))}-" \
           f"{round(100 * (max(lose) - 1))} %)" in text
    clean = [scores(s)[("bank", k, False)].mean() / scores(s)[("EKF", k, False)].mean()
             for s in ekf_ahead for k in KINDS]
    assert f"noise-free it is {int(min(clean))}-{int(np.ceil(max(clean)))}x better on {listed_text}" in text
    worst_id, worst_other = 0.0, (0.0, None)
    for s in SYSTEMS:
        report = json_payload(json.loads((ROOT / "results" / "generalisation" / s /
                                          f"{s}_generalisation.json").read_text()))
        for c in report["cases"]:
            r = c["models"]["bank"]["ratio_ekf"]
            if c["regime"] == "id":
                worst_id = max(worst_id, r)
            elif r > worst_other[0]:
                worst_other = (r, (s, c["family"], c["noise"]))
    assert worst_id < 1.1 and worst_other[0] < 1.3 and worst_other[1] == ("duffing", "chirp", 0.05)
    assert f"(at most {worst_id:.2f}x) and 1.3x elsewhere (at most {worst_other[0]:.2f}x, the swept sine on " \
           "Duffing at noise 0.05)" in text
    damped = ROOT / "results" / "own_plant" / "damped3"
    own = []
    for name, method in (("damped3_scores.json", None), ("damped3_seed1_scores.json", None),
                         ("damped3_copies_scores.json", "copies")):
        cells = {(c["method"], c["kind"], c["noisy"]): c["smape_mean"] for c in
                 json_payload(json.loads((damped / name).read_text()))}
        method = method or next(m for m, _, _ in cells if m != "EKF")
        own.append([cells[method, k, True] / cells["EKF", k, True] for k in KINDS])
    assert f"{span(own[0] + own[1])} the EKF; {span(own[2])} with model copies" in text
    qube = [json_payload(json.loads((ROOT / "results" / "real_rig" / "qube" / f"hardware_{case}.json").read_text()))
            [case]["scored_mean"] for case in ("theta_alpha", "alpha")]
    velocity = [b / e for r in qube for b, e in zip(r["KKL (bank)"][2:], r["EKF"][2:])]
    assert f"velocities within {span(velocity)} of the EKF" in text
    like = json_payload(json.loads((ROOT / "results" / "real_rig" / "qube" / "hardware_like.json").read_text()))
    velocity = [b / e for r in like.values() for b, e in zip(r["scored_mean"]["KKL (bank)"][2:],
                                                             r["scored_mean"]["EKF"][2:])]
    assert f"{span(velocity)} with `--like` alone" in text
    copy = json_payload(json.loads((ROOT / "results" / "real_rig" / "qube" / "hardware_like_copy.json").read_text()))
    velocity = [b / e for b, e in zip(copy["theta_alpha"]["scored_mean"]["KKL (bank)"][2:],
                                      copy["theta_alpha"]["scored_mean"]["EKF"][2:])]
    assert f"{span(velocity)} with both encoders and the noise copy" in text
    states = json_payload(json.loads((ROOT / "results" / "real_rig" / "qube" / "hardware_like_read.json")
                                     .read_text()))
    velocity = [b / e for b, e in zip(states["alpha"]["scored_mean"]["KKL (bank)"][2:],
                                      states["alpha"]["scored_mean"]["EKF"][2:])]
    assert f"{span(velocity)} with the pendulum encoder alone and its copy over the states the equations read" in text
    timing = provenance.strip_markdown((ROOT / "results" / "speed" / "duffing" / "protocol_duffing.md").read_text())
    warm = float(re.search(r"- warm caches \(.*?\): ([\d.]+) s wall", timing).group(1))
    assert f"about {round(warm / 30) / 2:g} minutes on 2 cores" in text
    summary = provenance.strip_markdown((ROOT / "results" / "tune" / "two_masses" / "summary.md").read_text())
    baseline = float(re.search(r"baseline \(the recipe at the budget caps\): ([\d.]+)", summary).group(1))
    best = min(float(line.split("|")[2]) for line in summary.splitlines() if re.match(r"\| \d+ \| [\d.]+ \|", line))
    assert f"by {round(100 * (1 - best / baseline))} %" in text


def test_the_robust_observers_section_follows_from_the_results():
    """The README's "Robust observers" figures, recomputed from the scored reports of ``kklcasadi robustness``
    (results/robustness/<system>/<system>_robustness.json, Duffing's and Van der Pol's pooled)."""
    text = re.sub(r"\s+", " ", section("Robust observers"))
    ratio: dict = {}
    reports = [ROOT / "results" / "robustness" / s / f"{s}_robustness.json" for s in ("duffing", "vdp")]
    for path in reports:
        report = json_payload(json.loads(path.read_text()))
        assert report["settings"]["n_trials"] == 100 and report["settings"]["seed"] == 2026
        for case in report["cases"]:
            kind, models, baselines = case["case"]["kind"], case["models"], case["baselines"]
            ratio.setdefault(("robust", kind), []).append(models["robust"]["ratios"]["tuned"])
            ratio.setdefault(("bank", kind), []).append(models["bank"]["ratios"]["tuned"])
            ratio.setdefault(("exact", kind), []).append(models["robust"]["ratios"]["ekf"])
            ratio.setdefault(("augmented", kind), []).append(baselines["augmented"]["smape_mean"]
                                                             / models["robust"]["smape_mean"])
    assert f"at the box's corners it is {span(ratio['robust', 'corner'])} the tuned EKF (`bank` " \
        f"{span(ratio['bank', 'corner'])})" in text
    assert f"It costs {span(ratio['exact', 'exact'])} the EKF where the model is exact" in text
    assert f"is {span(ratio['robust', 'noise'])} the tuned EKF under Student-t noise, outliers and quantisation" \
        in text
    assert f"({span(ratio['augmented', 'corner'])} `robust`'s error at the corners)" in text
    assert "[docs/results/robustness.md](docs/results/robustness.md)" in text
    rows = {s: _step_rows(ROOT / "results" / "speed" / s / f"observer_step_{s}.md") for s in ("duffing", "vdp")}
    (d_us, d_n), (v_us, v_n) = rows["duffing"]["duffing/robust"], rows["vdp"]["vdp/robust"]
    (db_us, db_n), (vb_us, vb_n) = rows["duffing"]["duffing/bank"], rows["vdp"]["vdp/bank"]
    assert (f"Its C step (default build) costs {d_us} us and {d_n} instructions on Duffing and {v_us} us and {v_n} on "
            f"Van der Pol, against `bank`'s {db_us} us / {db_n} and {vb_us} us / {vb_n}") in text


def test_the_first_observers_training_time_is_its_cards():
    """The README's training time of a first observer is the stored card's (``training.wall_time_s``), on the threads
    that card records (kklcasadi.train.TRAIN_THREADS, the default)."""
    card = json.loads((ROOT / "results" / "own_plant" / "damped3" / "fast" / "card_seed0.json").read_text())
    training = card["training"]
    text = " ".join(README.split())
    assert f"the damped 3-state plant's took {round(training['wall_time_s'])} s on 2 cores" in text
    assert "`results/own_plant/damped3/fast`; one torch thread unless `--threads N`" in text
    assert training["threads"] == 1 and training["machine"]["cpus"] == 2
    command = card[provenance.KEY]["command"].split()          # the one command: no flag beyond the plant and --out
    assert command[:4] == ["kklcasadi", "train", "--plant", "examples/damped3_plant.py:make_plant"]
    assert command[4] == "--out" and len(command) == 6
