"""The shipped models' one lookup: the package's _models (a link to models/ in the tree, package data when
installed), found from any directory; a user's models elsewhere are not shipped."""

import configparser
import fnmatch
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from kklcasadi.model import shipped

ROOT = Path(__file__).resolve().parents[1]


def test_the_package_reaches_the_models_of_the_tree():
    assert (ROOT / "kklcasadi" / "_models").is_symlink()
    assert shipped.SHIPPED_ROOT == (ROOT / "models").resolve()
    cards = sorted(ROOT.glob("models/*/*/card.json"))
    assert len(cards) >= 4
    listing = shipped.shipped()
    assert sum(len(methods) for methods in listing.values()) == len(cards)
    assert shipped.is_shipped(ROOT / "models" / "duffing" / "bank")


def test_the_package_data_holds_every_shipped_card_and_weights_file():
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    patterns = [p.strip() for p in config["options.package_data"]["kklcasadi"].replace("\n", ",").split(",")
                if p.strip()]
    files = [f"_models/{p.relative_to(ROOT / 'models')}" for p in (ROOT / "models").glob("*/*/*")
             if p.name in ("card.json", "weights.npz")]
    assert files and all(any(fnmatch.fnmatch(f, pattern) for pattern in patterns) for f in files)


def test_a_copy_elsewhere_is_the_users_model(tmp_path):
    copy = tmp_path / "models" / "duffing" / "bank"
    shutil.copytree(ROOT / "models" / "duffing" / "bank", copy)
    assert not shipped.is_shipped(copy)


def test_an_installed_package_finds_its_models_from_any_directory(tmp_path):
    """The layout pip install . writes: kklcasadi/_models/<system>/<method>/ holding real files."""
    site = tmp_path / "site"
    shutil.copytree(ROOT / "kklcasadi", site / "kklcasadi", symlinks=True,
                    ignore=shutil.ignore_patterns("__pycache__", "_models"))
    for name in ("card.json", "weights.npz"):
        target = site / "kklcasadi" / "_models" / "duffing" / "bank" / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(ROOT / "models" / "duffing" / "bank" / name, target)
    elsewhere = tmp_path / "work"
    (elsewhere / "models" / "duffing" / "mine").mkdir(parents=True)      # a user's ./models is not listed
    shutil.copyfile(ROOT / "models" / "duffing" / "bank" / "card.json", elsewhere / "models" / "duffing" / "mine" /
                    "card.json")
    code = ("import kklcasadi.model.shipped as s\n"
            "print(s.SHIPPED_ROOT)\nprint(s.shipped())\nprint(s.shipped_model('duffing', 'bank'))\n"
            "print(s.is_shipped(s.shipped_model('duffing', 'bank')))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=elsewhere, capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}).stdout.splitlines()
    assert out == [str((site / "kklcasadi" / "_models").resolve()), "{'duffing': ['bank']}",
                   str(site / "kklcasadi" / "_models" / "duffing" / "bank"), "True"]


def test_a_shipped_model_loads_by_name_from_any_directory(tmp_path, monkeypatch, capsys):
    """kc.load_observer("duffing/bank") and the command line name shipped models anywhere; a directory of that
    name where it is given wins; neither is one error naming both readings."""
    import pytest

    import kklcasadi as kc
    from kklcasadi.cli import main

    monkeypatch.chdir(tmp_path)                                         # outside the clone
    for name in ("duffing/bank", "models/duffing/bank", Path("vdp") / "autonomous"):
        resolved = shipped.resolve(name)
        assert resolved.parent.parent == shipped.SHIPPED_ROOT and shipped.is_shipped(resolved)
    obs = kc.load_observer("duffing/bank")
    assert obs.method == "bank" and obs.model.path == (ROOT / "models" / "duffing" / "bank").resolve()
    mine = tmp_path / "duffing" / "bank"                                # a user's folder of that name wins
    shutil.copytree(ROOT / "models" / "duffing" / "autonomous", mine)
    assert shipped.resolve("duffing/bank") == Path("duffing/bank") and kc.load_observer("duffing/bank").method == \
        "autonomous"
    with pytest.raises(ValueError, match=r"^path: expected an existing model directory or a shipped model's name "
                                         r"SYSTEM/METHOD \(duffing: autonomous, .*\), received 'duffing/nope'"):
        kc.load_observer("duffing/nope")
    with pytest.raises(ValueError, match=r"received '/nope/bank'"):                    # an absolute path is a path
        shipped.resolve("/nope/bank")
    with pytest.raises(TypeError, match=r"^path: expected a model directory or a shipped model's name"):
        shipped.resolve(3)
    assert main(["export", "vdp/autonomous", "--casadi", str(tmp_path / "step.casadi")]) == 0
    assert (tmp_path / "step.casadi").exists()
    assert main(["demo", "--model", "fhn/nope"]) == 2
    assert "error: --model: expected an existing model directory or a shipped model's name" in \
        capsys.readouterr().err


def test_the_shipped_robust_observers_are_their_recipe():
    """models/<system>/robust is ``kklcasadi train`` with the flags of :data:`kklcasadi.train.bank.ROBUST`
    (issue 46.6): the card's configuration, seed, parameter box and noise models are the recipe's, the card
    records the nominal plant, and the model loads by its shipped name."""
    import itertools
    import json
    from dataclasses import asdict

    import numpy as np
    import pytest

    import kklcasadi as kc
    from kklcasadi.cli import build_parser
    from kklcasadi.cli.train import training_config
    from kklcasadi.train import with_epochs
    from kklcasadi.train.bank import ROBUST, BankConfig, robust_command

    robust = sorted(system for system, methods in shipped.shipped().items() if "robust" in methods)
    assert robust == sorted(kc.systems.families()) == ["duffing", "vdp"]
    for system in robust:
        args = build_parser().parse_args(robust_command(system))
        assert Path(args.out) == Path("models") / system / "robust" and args.method == "bank"
        family = kc.systems.get(system, param_spread=args.param_spread)
        expected = with_epochs(training_config(family, "bank", args), args.epochs)
        card = json.loads((ROOT / args.out / "card.json").read_text())
        training = card["training"]
        recipe = json.loads(json.dumps(asdict(expected)))
        default = json.loads(json.dumps(asdict(BankConfig())))
        gained = [key for key in recipe["rollouts"] if key not in training["config"]["rollouts"]]   # since the fit
        assert all(recipe["rollouts"][key] == default["rollouts"][key] for key in gained), gained
        recipe["rollouts"] = {key: value for key, value in recipe["rollouts"].items() if key not in gained}
        added = [key for key in recipe if key not in training["config"]]      # fields BankConfig gained since the fit
        assert all(recipe[key] == default[key] for key in added), added
        assert training["config"] == {key: value for key, value in recipe.items() if key not in added}
        assert training["seed"] == args.seed == 11 and expected.members == 1
        runs = training["runs"]
        assert runs["runs"] == expected.rollouts.n_traj == {"duffing": 3000, "vdp": 1000}[system]
        copies = card["architecture"]["bank"]["copies"]          # one copy per corner of the box first, then nominal
        corners = [list(c) for c in itertools.product(*family.param_box.tolist())]
        assert copies["params"] == corners + [family.param_nominal.tolist()] * 3
        assert copies["weights"] == [1.0] * len(corners) + [1.0, 100.0, 1e4]
        assert set(runs["noise_models"]) == set(args.noise_model) == {"gauss", "student-t:3"}
        assert min(runs["noise_models"].values()) > 0.4 * runs["runs"]          # one drawn per run, both drawn
        params = runs["params"]
        assert params["names"] == list(family.param_names)
        np.testing.assert_allclose(params["box"], family.param_box, rtol=0, atol=1e-15)
        drawn = np.asarray(params["drawn_range"])                 # the Latin hypercube reaches the box's edges
        np.testing.assert_allclose(drawn, family.param_box.T, rtol=0, atol=0.002)
        assert card["system"]["fingerprint"] == kc.systems.get(system).fingerprint      # the nominal plant
        obs = kc.load_observer(f"{system}/robust")
        assert obs.method == "bank" and obs.model.path == (ROOT / "models" / system / "robust").resolve()
    assert all("--param-spread" in flags and "student-t:3" in flags for flags in ROBUST.values())
    with pytest.raises(ValueError, match=r"^system: expected a shipped system with a parameterised form"):
        robust_command("fhn")


def test_a_model_a_user_adds_under_models_is_theirs(tmp_path, monkeypatch):
    """Shipped means the package's own (SHIPPED_MODELS), not any directory under models/ of a clone."""
    root = tmp_path / "models"
    for method in ("bank", "mine"):
        (root / "duffing" / method).mkdir(parents=True)
        shutil.copyfile(ROOT / "models" / "duffing" / "bank" / "card.json", root / "duffing" / method / "card.json")
    monkeypatch.setattr(shipped, "SHIPPED_ROOT", root)
    assert shipped.shipped() == {"duffing": ["bank"]}
    assert shipped.is_shipped(root / "duffing" / "bank") and not shipped.is_shipped(root / "duffing" / "mine")
    assert [p.name for p in shipped.shipped_models("duffing")] == ["bank"]
    with pytest.raises(ValueError, match="no shipped model models/duffing/mine"):
        shipped.shipped_model("duffing", "mine")
    assert shipped.inside_shipped(root / "duffing" / "bank" / "x.png")
    assert shipped.inside_shipped(root / "duffing" / "obs")
    assert not shipped.inside_shipped(root / "duffing" / "mine") and not shipped.inside_shipped(root / "duffing")


def test_the_table_names_exactly_the_models_in_the_repository():
    listed = subprocess.run(["git", "ls-files", "models/*/*/card.json"], cwd=ROOT, capture_output=True, text=True)
    if listed.returncode != 0 or not listed.stdout:
        pytest.skip("not a git checkout")
    tracked = sorted(tuple(Path(line).parts[1:3]) for line in listed.stdout.split())
    assert tracked == sorted((s, m) for s, methods in shipped.SHIPPED_MODELS.items() for m in methods)
