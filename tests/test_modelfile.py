"""Model files: round trips, atomic and refusing writes, and a clear ValueError for every kind of
damaged or inconsistent model directory (torch-free)."""

import dataclasses
import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import write_signed_card

from kklcasadi import writes
from kklcasadi.model import variants
from kklcasadi.model.card import FORMAT, model_array_shapes
from kklcasadi.model.files import CARD_FILE, WEIGHTS_FILE, load_model, save_model

NX, NU, NY = 2, 1, 1
NZ = NY * (2 * NX + 1)


def make_card(method="autonomous", nu=NU, base=None):
    arch = {"encoder": {"sizes": [NX, 8, 8, NZ], "activation": "tanh"},
            "decoder": {"sizes": [NZ, 8, 8, NX], "activation": "relu"}}
    if method in ("obs", "obs_stream"):
        arch.update({"context": {"hidden": 6, "proj": 3},
                     "gain": {"sizes": [NZ + 3, 7, NZ * nu], "activation": "tanh"}})
    if method == "bank":
        arch = {"decoder": {"sizes": [NZ + NY + nu, 8, NX], "activation": "tanh"},
                "bank": {"y_poles": [1.0], "u_poles": [], "y_resonators": [], "clock": None}}
    if method in ("dyn", "dyn_stream"):
        arch["hyper"] = {"hidden": 6, "embed": 4, "backbone": [9, 9], "rank": 2}
    return {
        "method": method,
        "system": {"name": "duffing", "nx": NX, "nu": nu, "ny": NY},
        "design": {"A": (-np.diag(np.arange(1.0, NZ + 1))).tolist(),
                   "B": np.ones((NZ, NY)).tolist()},
        "dt": 0.05, "window": 100 if variants.get(method).windowed else 1,
        "architecture": arch,
        "base": base,
        "noise": {"measurement_std": 0.0},
        "training": {"seed": 0, "final_loss": np.float64(1.5e-3)},
    }


def random_arrays(card, seed=0):
    rng = np.random.default_rng(seed)
    shapes = model_array_shapes({**card, "format": FORMAT})
    return {name: rng.uniform(0.5, 2.0, shape) if name.endswith("_std") else rng.normal(size=shape)
            for name, shape in shapes.items()}


@pytest.fixture
def saved(tmp_path):
    card = make_card()
    arrays = random_arrays(card)
    return save_model(tmp_path / "autonomous", arrays, card), card, arrays


def rewrite_card(directory, edit):
    """Edit the card and sign it again: what the loader checks after the digest is what the test sees."""
    card = json.loads((directory / CARD_FILE).read_text())
    edit(card)
    write_signed_card(directory, card)


def rewrite_weights(directory, arrays):
    """Replace the weights and update the card's hash, so that only the content is wrong."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    (directory / WEIGHTS_FILE).write_bytes(buffer.getvalue())
    digest = hashlib.sha256(buffer.getvalue()).hexdigest()
    rewrite_card(directory, lambda card: card.update(weights_sha256=digest))


def test_reading_and_exporting_need_no_torch():
    code = ("import sys, kklcasadi, kklcasadi.model.files, kklcasadi.nets.builders, kklcasadi.observer.kkl; "
            "sys.exit('torch was imported' if 'torch' in sys.modules else 0)")
    subprocess.run([sys.executable, "-c", code], check=True,
                   cwd=Path(__file__).resolve().parents[1])


# ----------------------------------------------------------------------------- round trips

@pytest.mark.parametrize("method", variants.names())
def test_roundtrip(tmp_path, method):
    card = make_card(method, nu=2)
    arrays = random_arrays(card)
    path = save_model(tmp_path / method, arrays, card)
    model = load_model(path)
    assert model.path == path and model.method == method and model.base is None
    assert set(model.arrays) == set(arrays)
    for name, value in arrays.items():
        assert model.arrays[name].dtype == np.float64
        assert np.array_equal(model.arrays[name], value)
    assert model.card["format"] == "kklcasadi.model" and model.card["format_version"] == 2
    assert model.card["kklcasadi_version"] == "0.1.0"
    assert model.card["training"]["final_loss"] == 1.5e-3
    assert model.card["weights_sha256"] == hashlib.sha256(
        (path / WEIGHTS_FILE).read_bytes()).hexdigest()
    np.testing.assert_array_equal(model.A, -np.diag([1.0, 2, 3, 4, 5]))
    windowed = variants.get(method).windowed
    assert model.B.shape == (NZ, NY) and model.dt == 0.05 and model.window == (100 if windowed else 1)


def test_model_is_immutable(saved):
    model = load_model(saved[0])
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.card = {}
    with pytest.raises(ValueError):
        model.arrays["decoder/W0"][0, 0] = 1.0


def test_nz_may_differ_from_the_default_if_consistent(tmp_path):
    card = make_card()
    nz = 3
    card["design"] = {"A": (-np.eye(nz)).tolist(), "B": np.ones((nz, NY)).tolist()}
    card["architecture"]["encoder"]["sizes"][-1] = nz
    card["architecture"]["decoder"]["sizes"][0] = nz
    assert load_model(save_model(tmp_path / "m", random_arrays(card), card)).A.shape == (3, 3)


def test_base_model_is_loaded_and_checked(tmp_path, saved):
    base_path, base_card, base_arrays = saved
    sha = load_model(base_path).card["weights_sha256"]
    card = make_card("obs", base={"path": "../autonomous", "weights_sha256": sha})
    obs_path = save_model(tmp_path / "obs", random_arrays(card), card)
    model = load_model(obs_path)
    assert model.base.path == base_path and model.base.method == "autonomous"

    # the base model changes after the obs model was trained on it
    save_model(base_path, random_arrays(base_card, seed=1), base_card, overwrite=True)
    with pytest.raises(ValueError, match=r"base\.weights_sha256.*retrain"):
        load_model(obs_path)
    shutil.rmtree(base_path)
    with pytest.raises(ValueError, match=r"base\.path.*file not found"):
        load_model(obs_path)


def test_base_must_describe_the_same_system(tmp_path):
    other = make_card()
    other["system"] = {**other["system"], "name": "vdp"}
    base = save_model(tmp_path / "vdp", random_arrays(other), other)
    sha = load_model(base).card["weights_sha256"]
    card = make_card("obs", base={"path": "../vdp", "weights_sha256": sha})
    with pytest.raises(ValueError, match="'system'"):
        save_model(tmp_path / "obs", random_arrays(card), card)


# ----------------------------------------------------------------------------- writing

def test_refuses_to_overwrite_unless_asked(saved):
    path, card, arrays = saved
    new = random_arrays(card, seed=3)
    with pytest.raises(FileExistsError, match="overwrite=True"):
        save_model(path, new, card)
    assert np.array_equal(load_model(path).arrays["encoder/W0"], arrays["encoder/W0"])
    save_model(path, new, card, overwrite=True)
    assert np.array_equal(load_model(path).arrays["encoder/W0"], new["encoder/W0"])


def test_failed_write_leaves_the_old_files_intact(saved, monkeypatch):
    path, card, arrays = saved
    before = {name: (path / name).read_bytes() for name in (CARD_FILE, WEIGHTS_FILE)}

    def failing_exchange(a, b):
        raise OSError("disk full")

    monkeypatch.setattr(writes, "_exchange", failing_exchange)
    with pytest.raises(OSError, match="disk full"):
        save_model(path, random_arrays(card, seed=4), card, overwrite=True)
    assert {name: (path / name).read_bytes() for name in before} == before
    assert sorted(os.listdir(path)) == [CARD_FILE, WEIGHTS_FILE]
    assert sorted(os.listdir(path.parent)) == [path.name]                # no temporary directory left


def test_save_validates_before_writing(tmp_path):
    card = make_card()
    arrays = random_arrays(card)
    arrays["decoder/W1"] = np.zeros((3, 3))
    with pytest.raises(ValueError, match=r"decoder/W1.*shape \(8, 8\)"):
        save_model(tmp_path / "m", arrays, card)
    arrays = {**random_arrays(card), "stray": np.zeros(2)}
    with pytest.raises(ValueError, match="stray"):
        save_model(tmp_path / "m", arrays, card)
    arrays = random_arrays(card)
    arrays["encoder/b0"][2] = np.nan
    with pytest.raises(ValueError, match="encoder/b0.*finite"):
        save_model(tmp_path / "m", arrays, card)
    with pytest.raises(ValueError, match="NaN"):
        save_model(tmp_path / "m", random_arrays(card),
                   {**card, "training": {"loss": float("nan")}})
    assert not (tmp_path / "m").exists()


# ----------------------------------------------------------------------------- damaged files

def test_missing_files(tmp_path, saved):
    path = saved[0]
    with pytest.raises(ValueError, match=r"card\.json: file not found"):
        load_model(tmp_path / "nowhere")
    (path / WEIGHTS_FILE).unlink()
    with pytest.raises(ValueError, match=r"weights\.npz: file not found"):
        load_model(path)


def test_invalid_json(saved):
    path = saved[0]
    (path / CARD_FILE).write_text('{"method": "obs",')
    with pytest.raises(ValueError, match=r"card\.json: expected strict JSON, received a parse error"):
        load_model(path)
    (path / CARD_FILE).write_text('{"dt": NaN}')
    with pytest.raises(ValueError, match="NaN"):
        load_model(path)


def test_truncated_weights(saved):
    path = saved[0]
    data = (path / WEIGHTS_FILE).read_bytes()
    (path / WEIGHTS_FILE).write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"weights_sha256.*modified or swapped"):
        load_model(path)
    digest = hashlib.sha256(data[: len(data) // 2]).hexdigest()
    rewrite_card(path, lambda card: card.update(weights_sha256=digest))
    with pytest.raises(ValueError, match=r"weights\.npz: expected a plain \.npz archive, received an unreadable"):
        load_model(path)


def test_corrupted_weights(saved):
    path = saved[0]
    data = bytearray((path / WEIGHTS_FILE).read_bytes())
    data[len(data) // 3] ^= 0xFF
    (path / WEIGHTS_FILE).write_bytes(bytes(data))
    with pytest.raises(ValueError, match="weights_sha256"):
        load_model(path)


def test_swapped_weights_file(tmp_path, saved):
    path, card, _ = saved
    other = save_model(tmp_path / "other", random_arrays(card, seed=7), card)
    shutil.copy(other / WEIGHTS_FILE, path / WEIGHTS_FILE)
    with pytest.raises(ValueError, match=r"card\.json: 'weights_sha256'"):
        load_model(path)


def test_pickled_arrays_are_refused(saved):
    path, _, arrays = saved
    rewrite_weights(path, {**arrays, "encoder/W0": np.array([{"evil": 1}], dtype=object)})
    with pytest.raises(ValueError, match="'encoder/W0': expected"):
        load_model(path)


@pytest.mark.parametrize("edit,match", [
    (lambda a: a.pop("decoder/b2"), r"decoder/b2.*missing"),
    (lambda a: a.update({"decoder/W0": np.zeros((8, 4))}), r"decoder/W0.*shape \(8, 5\)"),
    (lambda a: a.update({"extra": np.zeros(1)}), "extra"),
    (lambda a: a["encoder/W1"].__setitem__((0, 0), np.inf), "encoder/W1.*finite"),
    (lambda a: a.update({"encoder/in_std": np.zeros(2)}), "encoder/in_std.*positive"),
    (lambda a: a.update({"encoder/b0": np.zeros(8, dtype=np.float32)}), "encoder/b0.*float64"),
])
def test_bad_arrays_name_the_array(saved, edit, match):
    path, _, arrays = saved
    edit(arrays)
    rewrite_weights(path, arrays)
    with pytest.raises(ValueError, match=match) as info:
        load_model(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("edit,match", [
    (lambda c: c.pop("dt"), r"'dt': expected a required field"),
    (lambda c: c.update(window="100"), r"'window': expected a positive integer"),
    (lambda c: c.update(window=True), r"'window': expected a positive integer"),
    (lambda c: c.update(dt=-0.05), r"'dt': expected a positive number"),
    (lambda c: c.update(method="kalman"), r"'method': expected one of"),
    (lambda c: c.update(format="other"), r"'format'"),
    (lambda c: c.update(format_version=3), r"'format_version': expected 2"),
    (lambda c: c["system"].update(nx=0), r"'system\.nx'"),
    (lambda c: c["system"].pop("name"), r"'system'"),
    (lambda c: c["design"].update(A=[[1.0, 0.0]]), r"'design\.A': expected a square matrix"),
    (lambda c: c["design"].update(B=[[1.0]] * 4), r"'design\.B': expected 5 rows"),
    (lambda c: c["design"].update(B=[[1.0, 1.0]] * 5), r"'design\.B': expected 1 columns"),
    (lambda c: c["design"]["A"][0].__setitem__(0, "x"), r"'design\.A'"),
    (lambda c: c["architecture"]["decoder"].update(sizes=[5, 8, 8, 3]),
     r"'architecture\.decoder\.sizes': expected \[5, \.\.\., 2\]"),
    (lambda c: c["architecture"]["encoder"].update(activation="gelu"),
     r"'architecture\.encoder\.activation'"),
    (lambda c: c["architecture"].update(hyper={}),
     r"'architecture': expected an object with exactly"),
    (lambda c: c.update(base={"path": 3}), r"'base'"),
    (lambda c: c.update(noise={"measurement_std": -1}), r"'noise\.measurement_std'"),
    (lambda c: c.update(training=[]), r"'training'"),
    (lambda c: c.update(weights_sha256="abc"), r"'weights_sha256': expected 64 lowercase hex"),
])
def test_hand_edited_card_names_the_field(saved, edit, match):
    path = saved[0]
    rewrite_card(path, edit)
    with pytest.raises(ValueError, match=match) as info:
        load_model(path)
    assert str(path / CARD_FILE) in str(info.value)


def test_method_specific_architecture_is_checked(tmp_path):
    card = make_card("obs", nu=2)
    card["architecture"]["gain"]["sizes"][-1] = NZ        # nz, but nz*nu = 10 is needed
    with pytest.raises(ValueError, match=r"architecture\.gain\.sizes.*nz\*nu = 10"):
        save_model(tmp_path / "m", {}, card)
    card = make_card("dyn")
    card["architecture"]["hyper"]["rank"] = 0
    with pytest.raises(ValueError, match=r"hyper\.rank"):
        save_model(tmp_path / "m", {}, card)
