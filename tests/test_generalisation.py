"""The generalisation benchmark: cases, what a model was fit on, the monitored trajectory, the scores."""
import json
import math
import os

import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi import provenance
from kklcasadi.cli import main
from kklcasadi.estimators.ekf import EKF
from kklcasadi.estimators.pf import ROUGHENING, ParticleFilter
from kklcasadi.evaluation import generalisation as gen
from kklcasadi.evaluation.protocol import Protocol
from kklcasadi.evaluation.trialcache import TrialCache
from kklcasadi.observer.kkl import load_observer
from kklcasadi.plant import signals as sig
from kklcasadi.provenance import strip_markdown

SHORT = gen.Settings(n_trials=3, T=6.0)


def test_the_grid():
    grid = gen.cases()
    assert len(grid) == (1 + 3 * 2 + 3) * 3
    assert gen.Case("zero", "id", 0.1) in grid and gen.Case("chirp", "held_out", 0.2) in grid
    assert not any(c.family == "zero" and c.regime == "ood" for c in grid)
    assert gen.cases(("square", "feedback"), (0.1,), ("ood",)) == [gen.Case("square", "ood", 0.1)]
    with pytest.raises(ValueError, match=r"^regime of family 'chirp': expected one of \['held_out'\]"):
        gen.Case("chirp", "id", 0.1)
    with pytest.raises(ValueError, match=r"^noise: expected a noise std > 0"):
        gen.Case("square", "id", 0.0)


@pytest.mark.parametrize("case, expected", [
    (gen.Case("zero", "id", 0.1), "fit"),
    (gen.Case("constant", "id", 0.05), "fit"),
    (gen.Case("constant", "ood", 0.1), "ood"),
    (gen.Case("square", "id", 0.1), "held out"),
    (gen.Case("random", "held_out", 0.1), "ood"),            # listed, but with a narrower amplitude
    (gen.Case("chirp", "held_out", 0.1), "held out"),
])
def test_categories(case, expected):
    fitted = {"zero": {}, "constant": {"value": (-1.0, 1.0)}, "random": {"amplitude": (0.1, 0.5), "hold": (0.5, 5)}}
    assert gen.category(case, fitted) == expected
    assert gen.category(case, None) == "unknown"


def test_fit_families_come_from_the_card_or_the_training_record(monitored_bank, model_dir_factory):
    path, _ = monitored_bank
    assert gen.fit_families(load_observer(path)) == {"zero": {}, "constant": {"value": (-1.0, 1.0)}}
    record = {"rollouts": {"kinds": ["zero", "square"], "regime": "train"}}
    other = load_observer(model_dir_factory("bank", card_extra={"training": record}))
    assert gen.fit_families(other) == {"zero": {}, "square": {"amplitude": (0.1, 1.0), "omega": (0.5, 2.0)}}
    assert gen.fit_families(load_observer(model_dir_factory("autonomous"))) is None


def test_protocol_families_are_the_protocols_cells():
    cell = gen.Case("square", "ood", 0.1).cell(gen.Settings())
    assert cell == Protocol(regime="ood").cell("square")
    cell = gen.Case("sinusoid", "id", 0.2).cell(gen.Settings(n_trials=7))
    assert cell == Protocol(n_trials=7, process_std=0.2, measurement_std=0.2).cell("sinusoid")


@pytest.mark.parametrize("family", ["chirp", "random", "feedback"])
def test_held_out_cells_are_seeded_and_cached(family, tmp_path):
    plant = kc.systems.get("duffing")
    cell = gen.Case(family, "held_out", 0.1).cell(SHORT)
    assert cell.label == f"{family}-held_out-0.1" and cell.shape() == (3, 120)
    json.dumps(cell.describe())
    a = cell.simulate(plant)
    b = TrialCache(tmp_path).trials(plant, cell)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(TrialCache(tmp_path).trials(plant, cell).y, a.y)      # from disk
    np.testing.assert_array_equal(a.x[:, 0], plant.sample_box(3, 2026))                # the protocol's x0
    rng = np.random.default_rng([2026, gen.FAMILY_STREAMS[family]])
    first = sig.draw(family, rng, sig.family_ranges(family, "held_out"), horizon=6.0,
                     output_range=gen.output_range(plant))
    if family == "feedback":
        assert np.all(np.abs(a.u) <= 1.0) and first == cell.inputs(plant)[0]
    else:
        np.testing.assert_array_equal(a.u[0], first(a.t))
    other = gen.Case(family, "held_out", 0.2).cell(SHORT).simulate(plant)
    np.testing.assert_array_equal(other.x[:, 0], a.x[:, 0])
    assert not np.array_equal(other.y, a.y)


def test_feedback_set_points_follow_the_output_range():
    lo, hi = gen.output_range(kc.systems.get("rossler"))
    np.testing.assert_allclose(lo, [-10.0], atol=0.05)
    np.testing.assert_allclose(hi, [10.0], atol=0.05)


def test_the_monitored_trajectory_is_the_observer(monitored_bank):
    path, _ = monitored_bank
    obs = load_observer(path)
    batch = gen.Case("square", "ood", 0.1).cell(SHORT).simulate(obs.system)
    est = obs.simulate(batch.t, batch.y, batch.u)
    xhat, inside = gen.MonitoredObserver(obs, compiler=None).estimate(batch.t, batch.y, batch.u)
    np.testing.assert_array_equal(xhat, est.xhat)
    np.testing.assert_array_equal(inside, est.in_domain)
    assert 0 < inside.mean() < 1


def test_run_scores_every_estimator_on_the_same_trials(monitored_bank):
    path, _ = monitored_bank
    obs = load_observer(path)
    cases = [gen.Case("constant", "ood", 0.1), gen.Case("chirp", "held_out", 0.2), gen.Case("zero", "id", 0.1)]
    cache = TrialCache(None)
    report = gen.run([("bank", obs)], cases, SHORT, trials=cache, pf_particles=40, compiler=None)
    (model,) = report.models
    for i, case in enumerate(cases):
        batch = cache.trials(obs.system, case.cell(SHORT))
        est = obs.simulate(batch.t, batch.y, batch.u)
        np.testing.assert_array_equal(model.smape[i], kc.metrics.smape(batch.x, est.xhat))
        np.testing.assert_array_equal(model.flagged_share[i], (~est.in_domain[:, batch.t >= 5.0]).mean(axis=1))
        ekf = EKF(obs.system, 0.05, Q=np.eye(2) * (case.noise * 0.05) ** 2, R=np.eye(1) * case.noise ** 2)
        xhat_ekf = ekf.simulate(batch.t, batch.y, batch.u).xhat
        np.testing.assert_allclose(report.ekf[i], kc.metrics.smape(batch.x, xhat_ekf), rtol=1e-12)
        pf = ParticleFilter(obs.system, 0.05, n_particles=40, process_std=case.noise, measurement_std=case.noise,
                            roughening=ROUGHENING, seed=2026)
        np.testing.assert_array_equal(report.pf[i], kc.metrics.smape(batch.x, pf(batch.t, batch.y, batch.u)))
        np.testing.assert_array_equal(report.bad(model, i), model.smape[i] > 1.5 * report.ekf[i])
    assert [model.category(c) for c in cases] == ["ood", "held out", "fit"]
    summary = {g["group"]: g for g in report.monitor_summary(model)}
    assert summary["in distribution"]["trials"] == 3 and summary["ood and held out, noise 0.1"]["trials"] == 3
    assert summary["other noise levels"]["cases"] == 1
    bad = report.bad(model, 0)
    hits = int((bad & (model.flagged_share[0] >= 0.5)).sum())
    g = summary["ood and held out, noise 0.1"]
    assert g["bad"] == int(bad.sum()) and (g["recall"] is None or math.isclose(g["recall"], hits / bad.sum()))
    data = json.loads(json.dumps(report.to_json()))
    assert (data["pf_particles"], data["pf_roughening"]) == (40, ROUGHENING)
    assert data["cases"][1]["models"]["bank"]["category"] == "held out"
    assert math.isclose(data["cases"][0]["models"]["bank"]["ratio_ekf"], model.smape[0].mean() / report.ekf[0].mean())
    table = report.markdown()
    assert "| chirp | held_out | 0.2 | held out | 3 |" in table and "bank / PF" in table
    assert "bank: in distribution" in report.monitor_markdown()


@pytest.mark.parametrize("noise", [0.05, 0.2])
def test_the_case_ekf_is_tuned_to_the_cases_noise(noise):
    """case_ekf: the EKF every generalisation table scores, Q = (noise dt)^2 I and R = noise^2 I."""
    plant = kc.systems.get("vdp")
    ekf = gen.case_ekf(plant, noise, 0.05)
    np.testing.assert_array_equal(ekf.Q, np.eye(plant.nx) * (noise * 0.05) ** 2)
    np.testing.assert_array_equal(ekf.R, np.eye(plant.ny) * noise ** 2)
    with pytest.raises(ValueError, match=r"^noise: expected a finite number > 0, received 0.0"):
        gen.case_ekf(plant, 0.0, 0.05)


def test_run_refuses_observers_of_two_plants(model_dir_factory):
    a, b = load_observer(model_dir_factory("bank")), load_observer(model_dir_factory("bank", system="vdp"))
    with pytest.raises(ValueError, match=r"^observers: expected observers of one plant \('duffing'\)"):
        gen.run([("a", a), ("b", b)], [gen.Case("zero", "id", 0.1)], SHORT)


def test_the_command(monitored_bank, tmp_path, capsys):
    path, _ = monitored_bank
    out = tmp_path / "gen"
    assert main(["generalise", str(path), "--families", "zero", "random", "--noise-levels", "0.1", "--trials", "2",
                 "--labels", "mine", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| zero | id | 0.1 | fit | 2 |" in printed and "| random | held_out | 0.1 | held out | 2 |" in printed
    data = json.loads((out / "duffing_generalisation.json").read_text())
    assert [c["family"] for c in data["cases"]] == ["zero", "random"] and "mine" in data["models"]
    assert provenance.strip_markdown((out / "duffing_generalisation.md").read_text()).startswith("**duffing, mine**")
    for name in ("duffing_generalisation.md", "duffing_generalisation.json"):
        stamp = provenance.read(out / name)
        assert stamp.command.startswith("kklcasadi generalise ") and stamp.seeds == {"trials": 2026}
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert main(["generalise", str(path), "--families", "zero", "--noise-levels", "0.1", "--trials", "2",
                 "--out", str(out)]) == 2                             # never over the report: refused before any run
    assert capsys.readouterr().err == (f"error: --out: {out / 'duffing_generalisation.md'} exists and this command "
                                       "does not overwrite; move it away, or choose another --out.\n")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert main(["generalise", str(path), "--families", "chirp", "--regimes", "id"]) == 2
    assert "error: --families, --regimes: no case" in capsys.readouterr().err


def test_a_model_without_a_monitor_or_a_record(model_dir_factory):
    obs = load_observer(model_dir_factory("autonomous"))
    assert obs.domain_check is None
    report = gen.run([("plain", obs)], [gen.Case("zero", "id", 0.1)], SHORT, compiler=None)
    (model,) = report.models
    assert model.flagged_share == [None] and model.fit_families is None and report.monitor_summary(model) == []
    assert "| zero | id | 0.1 | unknown | 3 |" in report.markdown() and report.markdown().endswith("| - | - |")
    with pytest.raises(ValueError, match=r"^observer: expected an observer with a domain monitor"):
        gen.MonitoredObserver(obs)


def test_compare_generalisation_prints_the_stored_lever_tables_and_refuses_other_trials(tmp_path, capsys):
    """benchmarks/compare_generalisation.py: the lever tables under results/generalisation/ are what it
    prints of their reports (ratios recomputed from the mean SMAPEs); reports of other trials are refused."""
    import runpy
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    script = str(root / "benchmarks" / "compare_generalisation.py")

    def records(name):                                 # results/generalisation/<system>/<name>
        return root / "results" / "generalisation" / name.split("_")[0] / name

    tables = {name: [name] for name in ("duffing_3030_cheap_levers", "duffing_3030_lr", "vdp_3030_lr")}
    tables["duffing_3030_cheap_filters"] = ["duffing_3030_cheap_levers", "duffing_3030_cheap_filters"]
    tables["rossler_3030_runs"] = ["rossler_3030_recipe", "rossler_3030_runs"]
    tables["duffing_3030_cheap_pd"] = ["duffing_3030_cheap_levers", "duffing_3030_cheap_pd"]
    tables["vdp_3030_cheap_pd"] = ["vdp_3030_cheap_pd"]
    tables["vdp_3030_pd_compare"] = ["vdp_3030_members3", "vdp_3030_pd"]
    tables["duffing_3030_pd_compare"] = ["duffing_3030_runs8000", "duffing_3030_pd"]
    tables.update({f"{s}_3030_members3_compare": [f"{s}_3030_members3"] for s in ("duffing", "vdp")})

    def printed_by(*args):
        argv, sys.argv = sys.argv, ["compare_generalisation.py", *map(str, args)]
        try:
            with pytest.raises(SystemExit, match="0"):
                runpy.run_path(script, run_name="__main__")
        finally:
            sys.argv = argv
        return capsys.readouterr().out

    for name, inputs in tables.items():
        printed = printed_by(*(records(f"{n}.json") for n in inputs))
        assert printed.strip() and printed in strip_markdown(records(f"{name}.md").read_text()) + "\n", name
        report = json.loads(records(f"{inputs[0]}.json").read_text())
        case = report["cases"][0]
        label, model = next(iter(case["models"].items()))
        assert f"| {model['smape_mean'] / case['ekf']['smape_mean']:.3f}x |" in printed.splitlines()[2]
    # two reports of one label (models/vdp/bank before and with the pd family), relabelled per report
    scored = records
    printed = printed_by(scored("vdp_generalisation_no_pd.json"), scored("vdp_generalisation_no_copies.json"),
                         "--labels", "without pd,with pd")
    assert printed.startswith("| case | without pd | with pd |")
    assert printed in strip_markdown(scored("vdp_generalisation_pd_compare.md").read_text()) + "\n"
    for system, after in (("duffing", ""), ("vdp", "_copies_5_substeps")):   # ... before and with the model copies
        printed = printed_by(scored(f"{system}_generalisation_no_copies.json"),
                             scored(f"{system}_generalisation{after}.json"), "--labels", "no_copies,copies")
        assert printed in strip_markdown(scored(f"{system}_generalisation_copies_compare.md").read_text()) + "\n"
    printed = printed_by(scored("vdp_generalisation_copies_5_substeps.json"), scored("vdp_generalisation.json"),
                         "--labels", "copies,sub2skip")          # ... and with two substeps and skip paths
    assert printed in strip_markdown(scored("vdp_generalisation_sub2skip_compare.md").read_text()) + "\n"
    # --out: the table under a stamp, never over a file (an input report included), whole or not at all
    inputs = [records(f"{n}.json") for n in tables["vdp_3030_pd_compare"]]
    out = tmp_path / "compare.md"
    assert printed_by(*inputs, "--out", out) in strip_markdown(out.read_text()) + "\n"
    first = out.read_bytes()
    for taken in (out, inputs[0]):
        before = taken.read_bytes()
        with pytest.raises(FileExistsError, match=f"^--out: .*{taken.name} exists and this command does not"):
            printed_by(*inputs, "--out", taken)
        assert taken.read_bytes() == before
    assert out.read_bytes() == first

    def failing(fd):
        raise OSError("disk full")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(os, "fsync", failing)
        with pytest.raises(OSError, match="disk full"):
            printed_by(*inputs, "--out", tmp_path / "again.md")
    assert [p.name for p in tmp_path.iterdir()] == ["compare.md"]
    module = runpy.run_path(script)
    with pytest.raises(SystemExit, match=r"--labels: expected one label per report \(2\), received 1"):
        module["load"]([scored("vdp_generalisation_no_pd.json"), scored("vdp_generalisation.json")], ["a"])
    other = json.loads(records("duffing_3030_lr.json").read_text())
    other["cases"][0]["ekf"]["smape"][0] += 1.0
    path = tmp_path / "other.json"
    path.write_text(json.dumps(other))
    with pytest.raises(SystemExit, match="differ.*other trials"):
        module["load"]([records("duffing_3030_lr.json"), path])
