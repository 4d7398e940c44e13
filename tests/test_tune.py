"""kklcasadi tune: the search space over the configuration fields, the validation cells, the card's
``search`` field, and a real study on SQLite: two worker processes, one killed mid-trial (SIGKILL)
and its trial retried by the heartbeat, then the study resumed."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from kklcasadi.evaluation import tune as tn
from kklcasadi.model.files import load_model
from kklcasadi.plant import signals as sig

ROOT = Path(__file__).resolve().parents[1]
optuna = pytest.importorskip("optuna", reason="the tune extra is not installed: pip install 'kklcasadi[tune]'")
train = pytest.importorskip("kklcasadi.train", reason="tune trains observers (torch)")


@pytest.mark.parametrize("method", sorted(tn.SPACES))
def test_every_space_names_fields_of_its_default_config(method):
    space = tn.search_space(method, system="duffing")
    assert space.baseline() == train.default_config("duffing", method)       # the caps are the default budget
    names = [d["name"] for d in space.describe()]
    assert len(names) == len(set(names)) and set(space.budget) <= set(names)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=3))
    trial = study.ask()
    config = space.suggest(trial)
    assert type(config) is type(space.base)
    assert space.suggest(optuna.trial.FixedTrial(trial.params)) == config      # a trial replays from its params


def test_bank_space_sets_the_fields_it_names():
    space = tn.search_space("bank", system="duffing", caps={"runs": 40, "epochs": 6})
    params = {"y_filters_n": 3, "y_filters_slow": 0.1, "y_filters_span": 100.0, "u_filters_n": 0, "clock_on": False,
              "decoder_width": 64, "decoder_depth": 2, "noise": 0.07, "lr": 2e-3, "runs": 24, "epochs": 5}
    config = space.suggest(optuna.trial.FixedTrial(params))
    np.testing.assert_allclose(config.y_poles, [0.1, 1.0, 10.0], rtol=1e-12)
    assert config.u_poles == () and config.clock is None and config.decoder.hidden == (64, 64)
    assert config.measurement_std == config.process_std == 0.07
    assert (config.rollouts.n_traj, config.decoder.loop.epochs, config.decoder.loop.lr) == (24, 5, 2e-3)
    base = space.baseline()
    assert (base.rollouts.n_traj, base.decoder.loop.epochs) == (40, 6)
    assert replace(base, rollouts=space.base.rollouts, decoder=space.base.decoder) == space.base
    runs = next(d for d in space.dims if d.name == "runs")
    assert (runs.low, runs.high, runs.log) == (20, 40, True)


def test_a_renamed_field_names_the_table_to_update(monkeypatch):
    monkeypatch.setitem(tn.SPACES, "bank", (tn.Float("noise", "rollouts.noise_std", 0.05, 0.2),))
    with pytest.raises(ValueError, match=r"'noise_std'.*RolloutConfig.*update kklcasadi\.evaluation\.tune\.SPACES"):
        tn.search_space("bank", system="duffing")
    with pytest.raises(ValueError, match="caps: expected budget names"):
        tn.search_space("autonomous", system="duffing", caps={"trajectories": 3})


def test_validation_leaves_out_what_the_config_fits_on():
    config = train.default_config("duffing", "bank")             # every family, id and ood ranges ("wide")
    assert tn.fitted_families(config) == {(k, r) for k in (*sig.BENCHMARK_KINDS, "multisine", "feedback")
                                          for r in ("id", "ood")}
    assert [c.name for c in tn.validation_cells(config)] == ["chirp", "random"]
    narrow = replace(config, rollouts=replace(config.rollouts, kinds=sig.BENCHMARK_KINDS, regime="train"))
    assert tn.fitted_families(narrow) == {(k, "id") for k in sig.BENCHMARK_KINDS}
    names = [c.name for c in tn.validation_cells(narrow)]
    assert names == ["chirp", "random", "constant-ood", "sinusoid-ood", "square-ood"]
    ood = replace(config, rollouts=replace(config.rollouts, kinds=("constant", "square"), regime="ood"))
    assert [c.name for c in tn.validation_cells(ood)] == ["chirp", "random", "sinusoid-ood"]
    obs = train.default_config("duffing", "obs")                 # Phase-2 data: constant, sinusoid, square (train)
    assert tn.fitted_families(obs) == {("constant", "id"), ("sinusoid", "id"), ("square", "id")}


def test_validation_trials_are_their_own():
    config = train.default_config("duffing", "bank")
    narrow = replace(config, rollouts=replace(config.rollouts, kinds=sig.BENCHMARK_KINDS, regime="train"))
    cells = tn.validation_cells(narrow, n_trials=6)
    chirp, random, _, sine, _ = cells
    again = tn.validation_cells(narrow, n_trials=6)[0].signals(1)
    t = np.linspace(0, 50, 101)
    for a, b in zip(chirp.signals(1), again):
        np.testing.assert_array_equal(a(t), b(t))
    for s in sine.signals(1):                                        # docs/protocol.md's ood ranges
        assert 1.0 <= s.amplitude[0] <= 2.0 and 3.0 <= s.omega <= 6.0
    assert all(0.5 <= s.hold <= 3.0 for s in random.signals(1))
    keys = {json.dumps(c.describe(), sort_keys=True) for c in cells}
    assert len(keys) == len(cells) and all(c.seed == tn.VALIDATION_SEED != 2026 for c in cells)


def _search_entry(**changes):
    entry = {"study": "s", "storage": "sqlite:///x.db", "trial": 3, "value": 1.2, "params": {"a": 1, "b": "x"},
             "space": [{"name": "a"}], "objective": {"score": "..."}, "baseline": None}
    return {**entry, **changes}


def test_the_card_records_the_search(model_dir_factory):
    path = model_dir_factory("bank", card_extra={"search": _search_entry(baseline=1.3)})
    search = load_model(path).spec.search
    assert (search.study, search.trial, search.value, search.baseline) == ("s", 3, 1.2, 1.3)
    assert load_model(model_dir_factory("bank")).spec.search is None


@pytest.mark.parametrize("entry,match", [
    (_search_entry(trial=-1), r"'search\.trial': expected an integer >= 0"),
    (_search_entry(trial=True), r"'search\.trial'"),
    (_search_entry(value=float("nan")), r"'search\.value': expected a finite number"),
    (_search_entry(study=""), r"'search\.study': expected a non-empty string"),
    (_search_entry(params={"a": [1]}), r"'search\.params'"),
    (_search_entry(space=[]), r"'search\.space': expected a non-empty list"),
    (_search_entry(baseline="1"), r"'search\.baseline'"),
    ({"study": "s"}, r"'search': expected an object with exactly the keys"),
])
def test_a_bad_search_entry_names_the_field(model_dir_factory, entry, match):
    with pytest.raises(ValueError, match=match):
        model_dir_factory("bank", card_extra={"search": entry})


def test_the_command_line_errors_are_one_line(tmp_path, capsys):
    from kklcasadi.cli import main

    assert main(["tune", "--trials", "1", "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.startswith("error: --system/--plant: give exactly one")
    assert main(["tune", "--system", "duffing", "--method", "obs", "--trials", "1", "--out", str(tmp_path)]) == 2
    assert "error: --base: expected the Phase-1 model 'obs' builds on" in capsys.readouterr().err


# -- a real study: worker processes on one SQLite file -------------------------------------------------

#: Tiny budgets: 16-32 runs of 50 s, 2-3 epochs, 4 validation trials per cell (a trial takes 1-3 s).
TINY = ["--system", "duffing", "--runs", "32", "--epochs", "3", "--val-trials", "4", "--heartbeat", "1", "--quiet"]


def _worker(out: Path, trials: int, seed: int, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "kklcasadi", "tune", *TINY, "--out", str(out), "--trials",
                             str(trials), "--sampler-seed", str(seed), *extra], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _finish(proc: subprocess.Popen, timeout: float = 900) -> str:
    out, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, out
    return out


def _running_trial_of(study_name: str, out: Path, pid: int, timeout: float = 300):
    """The trial that worker ``pid`` is running, once it trains: its objective has started (so its
    heartbeat is on) and drawn its last parameter (``epochs``)."""
    worker = f"{socket.gethostname()}:{pid}"
    url = tn.storage_url(None, out)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not (out / "study.db").exists():
            time.sleep(0.1)
            continue
        try:
            study = optuna.load_study(study_name=study_name, storage=url)
        except KeyError:                                     # not created yet
            time.sleep(0.1)
            continue
        for trial in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
            if trial.user_attrs.get("worker") == worker and "epochs" in trial.params:
                return trial
        time.sleep(0.05)
    pytest.fail(f"worker {pid} started no trial within {timeout} s")


@pytest.mark.slow           # three worker processes that each train (52 s): the default run stays under 10 minutes
def test_two_workers_one_killed_mid_trial_is_retried_and_the_study_resumes(tmp_path):
    out = tmp_path / "study"
    url = tn.storage_url(None, out)
    out.mkdir()
    optuna.storages.RDBStorage(url)          # Optuna's tables first (workers that create them at once can clash)
    a, b = _worker(out, 3, 1), _worker(out, 3, 2)
    try:
        killed = _running_trial_of("duffing-bank", out, a.pid)
        a.send_signal(signal.SIGKILL)
        a.wait(timeout=10)
        killed_at = time.monotonic()
        study = optuna.load_study(study_name="duffing-bank", storage=url)
        assert study.trials[killed.number].state == optuna.trial.TrialState.RUNNING       # it died mid-trial
        _finish(b)
    finally:
        for proc in (a, b):
            if proc.poll() is None:
                proc.kill()
    time.sleep(max(0.0, killed_at + 3.5 - time.monotonic()))       # past the grace period (3 heartbeats)
    log = _finish(_worker(out, 4, 3))                                # run again: resumes, one trial more
    study = optuna.load_study(study_name="duffing-bank", storage=url)
    states = [t.state for t in study.trials]
    assert study.trials[killed.number].state == optuna.trial.TrialState.FAIL
    retries = [t for t in study.trials if t.system_attrs.get("failed_trial") == killed.number]
    assert len(retries) == 1 and retries[0].state == optuna.trial.TrialState.COMPLETE
    assert retries[0].params == killed.params
    assert states.count(optuna.trial.TrialState.COMPLETE) == 4 and states.count(optuna.trial.TrialState.FAIL) == 1
    assert len({t.user_attrs["worker"] for t in study.trials}) == 3                 # a, b and the resumed run
    best = load_model(out / "best").spec.search
    assert (best.study, best.trial, best.value) == ("duffing-bank", study.best_trial.number, study.best_value)
    assert best.params == study.best_trial.params and best.space == study.user_attrs["record"]["space"]
    assert [c["name"] for c in best.objective["cells"]] == ["chirp", "random"]      # bank fits on the ood ranges
    listed = [line.split("|")[1].strip() for line in log.splitlines() if line.startswith("| ") and
              line.split("|")[1].strip().isdigit()]
    assert str(retries[0].number) in listed and str(killed.number) not in listed      # the retry, not the killed
    assert (out / "search.png").stat().st_size > 0 and "4 complete, 1 fail" in (out / "summary.md").read_text()
    from kklcasadi import provenance

    for name in ("summary.md", "search.png"):          # the last worker's command line, its seeds
        stamp = provenance.read(out / name)
        assert stamp.command.startswith("kklcasadi tune ") and "--sampler-seed 3" in stamp.command, name
        assert stamp.seeds == {"training": 0, "sampler": 3, "validation": tn.VALIDATION_SEED}, name
