"""``train --resume`` resumes only the checkpoints of the same training (plant fingerprint, method, configuration,
design, sample time, seed, base model) and never replaces a finished model without ``--overwrite``; a second
training to one ``--out`` stops at once."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import one_winner, race

torch = pytest.importorskip("torch")

import kklcasadi.train as kt  # noqa: E402
from kklcasadi import writes  # noqa: E402
from kklcasadi.model.files import load_model  # noqa: E402
from kklcasadi.train import default_config, train_observer  # noqa: E402
from kklcasadi.train.config import LoopConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def tiny(system="duffing", epochs=3):
    loop = LoopConfig(epochs=epochs, batch_size=64, lr=3e-3)
    return default_config(system, "autonomous", width=16, depth=2, n_traj=12, t_keep=2.0, n_pde=200, dtype="float64",
                          encoder=loop, decoder=loop)


def _interrupted(out, system="duffing", config=None, monkeypatch=None):
    """Train and stop before the model is written: the checkpoints and their record stay in OUT/.train."""
    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(kt, "save_model", killed)
        with pytest.raises(KeyboardInterrupt):
            train_observer(system, "autonomous", out, config=config or tiny(system), progress=False)
    assert sorted(p.name for p in (out / ".train").iterdir()) == ["decoder.ckpt.npz", "encoder.ckpt.npz", "run.json"]


def test_resume_takes_only_the_checkpoints_of_the_same_training(tmp_path, monkeypatch):
    out = tmp_path / "m"
    _interrupted(out, monkeypatch=monkeypatch)
    record = json.loads((out / ".train" / "run.json").read_text())
    assert record["method"] == "autonomous" and record["plant"] == kt.systems.get("duffing").fingerprint
    with pytest.raises(ValueError, match=r"resume: expected the checkpoints of this training .* received those of "
                                         r"another: its plant \(fingerprint\) differs"):
        train_observer("vdp", "autonomous", out, config=tiny("vdp"), progress=False, resume=True)
    with pytest.raises(ValueError, match=r"its configuration differs"):
        train_observer("duffing", "autonomous", out, config=tiny(epochs=4), progress=False, resume=True)
    with pytest.raises(ValueError, match=r"its seed differs"):
        train_observer("duffing", "autonomous", out, config=tiny(), seed=1, progress=False, resume=True)
    resumed = load_model(train_observer("duffing", "autonomous", out, config=tiny(), progress=False, resume=True))
    assert not (out / ".train").exists()                     # the model written, its checkpoints are done with
    straight = load_model(train_observer("duffing", "autonomous", tmp_path / "s", config=tiny(), progress=False))
    for name, value in straight.arrays.items():              # the last epoch's checkpoint resumed: the same model
        np.testing.assert_array_equal(resumed.arrays[name], value)


def test_a_new_training_drops_old_checkpoints(tmp_path, monkeypatch):
    out = tmp_path / "m"
    _interrupted(out, monkeypatch=monkeypatch)
    train_observer("vdp", "autonomous", out, config=tiny("vdp"), progress=False)          # without resume: afresh
    assert load_model(out).spec.system.name == "vdp"


def test_checkpoints_without_a_record_are_not_resumed(tmp_path, monkeypatch):
    out = tmp_path / "m"
    _interrupted(out, monkeypatch=monkeypatch)
    (out / ".train" / "run.json").unlink()
    with pytest.raises(ValueError, match="checkpoints without one"):
        train_observer("duffing", "autonomous", out, config=tiny(), progress=False, resume=True)


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory):
    """A training stopped before its model was written (its checkpoints and their record in .train), made once."""
    out = tmp_path_factory.mktemp("interrupted") / "m"
    with pytest.MonkeyPatch.context() as patch:
        _interrupted(out, monkeypatch=patch)
    return out


@pytest.mark.parametrize("text, received", [("{", "a parse error"), ("[1]", "a JSON list"),
                                            ('{"seed": NaN}', r"a parse error \(non-standard JSON constant NaN\)")])
def test_an_unreadable_run_record_is_one_line(interrupted, tmp_path, text, received):
    out = shutil.copytree(interrupted, tmp_path / "m")
    (out / ".train" / "run.json").write_text(text)
    with pytest.raises(ValueError, match=f"^{out / '.train' / 'run.json'}: expected .*received {received}.*"
                                         r"Train again without --resume\.$"):
        train_observer("duffing", "autonomous", out, config=tiny(), progress=False, resume=True)
    assert sorted(p.name for p in (out / ".train").iterdir()) == ["decoder.ckpt.npz", "encoder.ckpt.npz", "run.json"]


@pytest.mark.parametrize("damage, received", [("garbage", "a file numpy cannot read"),
                                             ("truncated", "a file numpy cannot read"),
                                             ("without lr", "none named 'lr'")])
def test_an_unreadable_checkpoint_is_one_line(interrupted, tmp_path, damage, received):
    out = shutil.copytree(interrupted, tmp_path / "m")
    path = out / ".train" / "encoder.ckpt.npz"
    if damage == "garbage":
        path.write_bytes(b"not an archive")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:200])
    else:
        with np.load(path) as data:
            arrays = {k: data[k] for k in data.files if k != "lr"}
        np.savez(path, **arrays)
    with pytest.raises(ValueError, match=f"^checkpoint {path}: expected .*received {received}.*Delete it to start "
                                         r"afresh\.$") as caught:
        train_observer("duffing", "autonomous", out, config=tiny(), progress=False, resume=True)
    assert "\n" not in str(caught.value)


def test_resume_never_replaces_a_finished_model(tmp_path):
    out = tmp_path / "D"
    shutil.copytree(ROOT / "models" / "duffing" / "autonomous", out)       # a finished Duffing model
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    result = subprocess.run([sys.executable, "-m", "kklcasadi", "train", "--system", "vdp", "--method", "autonomous",
                             "--epochs", "1", "--resume", "--out", str(out)], capture_output=True, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "a model already exists there; pass --overwrite" in result.stderr and "--resume" in result.stderr
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    with pytest.raises(FileExistsError, match="resume continues an unfinished training"):
        train_observer("vdp", "autonomous", out, config=tiny("vdp"), progress=False, resume=True)


def _train_to(out, seed, barrier, results):
    torch.set_num_threads(1)
    barrier.wait()
    try:
        train_observer("duffing", "autonomous", out, config=tiny(), seed=seed, progress=False)
        results.put((seed, "wrote"))
    except (FileExistsError, ValueError) as exc:
        results.put((seed, str(exc)))


def test_two_trainings_to_one_new_out_exactly_one_wins(tmp_path):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)                              # an OpenMP pool does not survive a fork
    try:
        for attempt in range(2):
            out = tmp_path / f"m{attempt}"
            winner = one_winner(race(_train_to, [(out, 0), (out, 1)]), "another process is writing", "exists")
            assert load_model(out).card["training"]["seed"] == winner
    finally:
        torch.set_num_threads(threads)


def test_a_second_training_to_one_out_stops_at_once(tmp_path):
    out = tmp_path / "m"
    with writes.claim(out / ".train", "out_dir"):          # another process trains there now
        with pytest.raises(FileExistsError, match=r"out_dir: another process is writing .*\.train now"):
            train_observer("duffing", "autonomous", out, config=tiny(), progress=False)
    assert not (out / "card.json").exists()
