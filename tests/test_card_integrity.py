"""The card is covered by the model's digest (with the weights' SHA-256): a hand-edited card is refused naming the
field, or accepted through ``kklcasadi resign``, which says what changed; every field is checked against what the
method uses; sizes are checked before anything is decompressed or allocated (deflate bombs, huge headers, deep
JSON, windows and ensembles larger than the weights hold). A property test mutates a valid card at random: it loads
unchanged in meaning or is refused with a one-line error, never a traceback."""

import io
import json
import os
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import write_signed_card
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from kklcasadi import provenance
from kklcasadi.model.digest import DIGEST, MAX_CARD_DEPTH, canonical
from kklcasadi.model.files import CARD_FILE, WEIGHTS_FILE, load_model, resign_model, save_model

ROOT = Path(__file__).resolve().parents[1]


def _card(path):
    return json.loads((path / CARD_FILE).read_text())


def _edit(path, edit):
    """Edit card.json as a person with an editor would: the digest is left as it was."""
    card = _card(path)
    edit(card)
    (path / CARD_FILE).write_text(json.dumps(card, indent=2))


def _one_line(exc):
    text = str(exc)
    assert "\n" not in text and text.strip() == text
    return text


@pytest.fixture
def obs_model(model_dir_factory):
    return model_dir_factory("obs", base=True)


@pytest.mark.parametrize("edit,field", [
    (lambda c: c["architecture"]["encoder"].update(activation="relu"), "'architecture.encoder.activation'"),
    (lambda c: c.update(dt=0.1), "'dt'"),
    (lambda c: c["design"].update(B=[[2.0 * v for v in row] for row in c["design"]["B"]]), "'design.B'"),
    (lambda c: c["system"].pop("fingerprint"), "'system.fingerprint'"),
    (lambda c: c.update(method="dyn"), "'method'"),
    (lambda c: c["training"].update(note="x"), "'training.note'"),
])
def test_a_hand_edited_card_is_refused_naming_the_field(obs_model, edit, field):
    _edit(obs_model, edit)
    with pytest.raises(ValueError) as info:
        load_model(obs_model)
    text = _one_line(info.value)
    assert f"card.json: {field}: expected" in text and f"kklcasadi resign {obs_model}" in text


def test_resign_says_what_changed_and_the_model_then_loads(obs_model, tmp_path):
    before = (obs_model / WEIGHTS_FILE).read_bytes()
    _edit(obs_model, lambda c: c.update(dt=0.1))
    result = subprocess.run([sys.executable, "-m", "kklcasadi", "resign", str(obs_model)], capture_output=True,
                            text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"{obs_model}: signed; 'dt' changed (now 0.1)\n"
    assert load_model(obs_model).dt == 0.1 and (obs_model / WEIGHTS_FILE).read_bytes() == before
    assert resign_model(obs_model) == []                                        # signed: nothing to do


def test_resign_refuses_what_load_refuses(model_dir_factory):
    path = model_dir_factory("bank")
    _edit(path, lambda c: c.update(window=10 ** 9))
    with pytest.raises(ValueError, match=r"'window': expected 1 \(method 'bank' reads no input window\), received "
                                         r"1000000000"):
        resign_model(path)
    shipped = ROOT / "models" / "duffing" / "bank"
    result = subprocess.run([sys.executable, "-m", "kklcasadi", "resign", str(shipped)], capture_output=True,
                            text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 2 and "read-only" in result.stderr and result.stderr.count("\n") == 1


def test_a_card_of_format_1_is_refused_until_resigned(model_dir_factory):
    path = model_dir_factory("autonomous")
    card = _card(path)
    old = {key: value for key, value in card.items() if key != DIGEST}
    old["format_version"] = 1
    (path / CARD_FILE).write_text(json.dumps(old))
    with pytest.raises(ValueError, match=r"'digest': expected the card's digest .*received missing.*kklcasadi resign"):
        load_model(path)
    assert resign_model(path) == ["'format_version' 1 -> 2 (the card had no digest)"]
    assert load_model(path).card["format_version"] == 2


@pytest.mark.parametrize("field,value,match", [
    ("window", 10 ** 9, r"'window': expected 1 \(method 'autonomous' reads no input window\)"),
    ("surprise", 1, r"'surprise': expected no such field"),
])
def test_fields_the_method_does_not_use_are_refused_even_when_signed(model_dir_factory, field, value, match):
    path = model_dir_factory("autonomous")
    write_signed_card(path, {**_card(path), field: value})
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=match):
        load_model(path)
    assert time.perf_counter() - t0 < 5


def test_a_windowed_card_has_a_bounded_window(model_dir_factory):
    path = model_dir_factory("obs")
    write_signed_card(path, {**_card(path), "window": 10 ** 9})
    with pytest.raises(ValueError, match=r"'window': expected at most 10000 samples"):
        load_model(path)


def test_an_ensemble_larger_than_the_weights_is_refused_before_its_arrays_are_listed(model_dir_factory):
    path = model_dir_factory("bank")
    card = _card(path)
    card["architecture"]["bank"]["members"] = 10 ** 9
    write_signed_card(path, card)
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=r"'architecture.bank.members': expected at most the \d+ arrays the weights "
                                         r"hold, received 1000000000"):
        load_model(path)
    assert time.perf_counter() - t0 < 5


def _rewrite_weights(path, entries, *, compression=zipfile.ZIP_STORED):
    """Write weights.npz from raw entries ``{name: bytes}`` and sign a card that names their SHA-256."""
    import hashlib

    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=compression) as archive:
        for name, data in entries.items():
            archive.writestr(f"{name}.npy", data)
    (path / WEIGHTS_FILE).write_bytes(buffer.getvalue())
    write_signed_card(path, {**_card(path), "weights_sha256": hashlib.sha256(buffer.getvalue()).hexdigest()})


def _npy(array):
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def _entries(path):
    with np.load(path / WEIGHTS_FILE) as npz:
        return {name: _npy(npz[name]) for name in npz.files}


def test_a_deflate_bomb_is_refused_from_the_archive_directory(model_dir_factory):
    path = model_dir_factory("autonomous")
    entries = _entries(path)
    zeros = b"\0" * (64 * 2 ** 20)                                  # 64 MiB that deflate to 64 kB
    for bomb in ({**entries, "bomb": zeros},                        # an extra array
                 {**entries, "encoder/W0": zeros}):                 # in place of an array of the card
        _rewrite_weights(path, bomb, compression=zipfile.ZIP_DEFLATED)
        assert (path / WEIGHTS_FILE).stat().st_size < 2 ** 20
        t0 = time.perf_counter()
        with pytest.raises(ValueError) as info:
            load_model(path)
        assert time.perf_counter() - t0 < 2
        text = _one_line(info.value)
        assert "'bomb': expected only the arrays the architecture names" in text or \
            "'encoder/W0': expected" in text and "bytes uncompressed" in text


def test_a_header_that_claims_a_huge_array_is_refused_before_allocating(model_dir_factory):
    path = model_dir_factory("autonomous")
    entries = _entries(path)
    real = np.load(io.BytesIO(entries["encoder/W0"]))
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (10 ** 6, 10 ** 5)})
    fake = header.getvalue() + real.tobytes()                       # 745 GiB declared, the real bytes behind it
    _rewrite_weights(path, {**entries, "encoder/W0": fake})
    with pytest.raises(ValueError, match=r"'encoder/W0': expected shape \(\d+, \d+\), received shape \(1000000, "
                                         r"100000\)"):
        load_model(path)
    long_header = b"\x93NUMPY\x02\x00" + (200_000).to_bytes(4, "little") + b" " * 200_000
    _rewrite_weights(path, {**entries, "encoder/W0": long_header + real.tobytes()})
    with pytest.raises(ValueError, match=r"'encoder/W0': expected .*bytes uncompressed|unreadable header"):
        load_model(path)


def test_pickles_and_object_arrays_are_refused(model_dir_factory):
    path = model_dir_factory("autonomous")
    entries = _entries(path)
    shape = np.load(io.BytesIO(entries["encoder/b0"])).shape
    buffer = io.BytesIO()
    np.save(buffer, np.array([object()] * shape[0], dtype=object), allow_pickle=True)
    _rewrite_weights(path, {**entries, "encoder/b0": buffer.getvalue()})
    with pytest.raises(ValueError, match=r"'encoder/b0': expected"):
        load_model(path)


def test_a_deep_or_huge_card_is_refused_before_it_is_parsed(model_dir_factory):
    path = model_dir_factory("autonomous")
    (path / CARD_FILE).write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ValueError, match=rf"expected JSON nested at most {MAX_CARD_DEPTH} levels deep, received "
                                         r"100000 levels"):
        load_model(path)
    with open(path / CARD_FILE, "wb") as stream:
        stream.truncate(5 * 2 ** 20)
    with pytest.raises(ValueError, match="expected a card of at most"):
        load_model(path)


# -- the property: a mutated card is loaded unchanged in meaning or refused in one line --------------------------

JSON = st.recursive(st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70)
                    | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=8),
                    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
                    max_leaves=6)


def _paths(value, prefix=()):
    yield prefix
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _paths(item, prefix + (key,))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _paths(item, prefix + (i,))


def _mutate(card, path, op, value):
    card = json.loads(json.dumps(card))
    if not path:
        return value if op == "replace" else card
    parent = card
    for key in path[:-1]:
        parent = parent[key]
    key = path[-1]
    if op == "replace":
        parent[key] = value
    elif op == "delete":
        del parent[key]
    elif op == "add" and isinstance(parent, dict):
        parent[f"{key}_extra"] = value
    elif op == "add":
        parent.insert(key, value)
    return card


@pytest.fixture(scope="module")
def valid_model(tmp_path_factory):
    source = load_model(ROOT / "models" / "duffing" / "obs")
    root = tmp_path_factory.mktemp("property")
    shutil.copytree(source.base.path, root / "autonomous")
    return save_model(root / "obs", dict(source.arrays), {**source.card, "base": {**source.card["base"],
                                                                                  "path": "../autonomous"}})


@pytest.mark.parametrize("method", [[], {}, 3, None, ["bank"]])
def test_a_signed_card_whose_method_is_not_a_name_is_refused_in_one_line(valid_model, tmp_path_factory, method):
    """The property test's case (a signed card with ``"method": []`` ended in ``TypeError: unhashable type``)."""
    card = _card(valid_model)
    work = tmp_path_factory.mktemp("method")
    shutil.copytree(valid_model.parent, work, dirs_exist_ok=True)
    write_signed_card(work / "obs", {**{k: v for k, v in card.items() if k != DIGEST}, "method": method})
    with pytest.raises(ValueError) as caught:
        load_model(work / "obs")
    _one_line(caught.value)
    assert str(work / "obs") in str(caught.value) and "'method'" in str(caught.value)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_mutated_card_loads_unchanged_in_meaning_or_is_refused_in_one_line(valid_model, tmp_path_factory, data):
    card = _card(valid_model)
    body = {key: value for key, value in card.items() if key != DIGEST}
    path = data.draw(st.sampled_from(list(_paths(body))))
    op = data.draw(st.sampled_from(["replace", "delete", "add"]))
    mutated = _mutate(body, path, op, data.draw(JSON))
    signed = data.draw(st.booleans())                   # signed: a tool that signs; unsigned: an editor
    work = tmp_path_factory.mktemp("mutant")
    shutil.copytree(valid_model.parent, work, dirs_exist_ok=True)
    target = work / "obs"
    if signed and isinstance(mutated, dict):
        write_signed_card(target, mutated)
    else:
        (target / CARD_FILE).write_text(json.dumps(mutated if not isinstance(mutated, dict)
                                                   else {**mutated, DIGEST: card[DIGEST]}))
    try:
        model = load_model(target)
    except (ValueError, TypeError) as exc:                # one line, naming the card (or the weights) it refused
        _one_line(exc)
        assert str(target) in str(exc)
        event(f"{'signed' if signed else 'unsigned'}: refused")
        return
    event(f"{'signed' if signed else 'unsigned'}: loaded")
    if not signed:                                        # an unsigned edit that loads changed nothing
        assert canonical({k: v for k, v in model.card.items() if k != DIGEST}) == canonical(body)
    else:
        assert canonical({k: v for k, v in model.card.items() if k != DIGEST}) == canonical(mutated)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_card_with_damaged_bytes_is_refused_in_one_line(valid_model, tmp_path_factory, data):
    text = bytearray((valid_model / CARD_FILE).read_bytes())
    for _ in range(data.draw(st.integers(1, 4))):
        text[data.draw(st.integers(0, len(text) - 1))] = data.draw(st.integers(0, 255))
    work = tmp_path_factory.mktemp("damaged")
    shutil.copytree(valid_model.parent, work, dirs_exist_ok=True)
    (work / "obs" / CARD_FILE).write_bytes(bytes(text))
    try:
        model = load_model(work / "obs")
    except (ValueError, TypeError) as exc:
        _one_line(exc)
        return
    assert canonical(model.card) == canonical(_card(valid_model))      # e.g. a changed blank: the same card


def test_a_reformatted_card_still_loads(valid_model, tmp_path):
    shutil.copytree(valid_model.parent, tmp_path, dirs_exist_ok=True)
    _edit(tmp_path / "obs", lambda card: None)           # indented differently, the same card
    assert canonical(load_model(tmp_path / "obs").card) == canonical(_card(valid_model))


# -- the shipped models: their cards were signed once (kklcasadi.model.files.resign_model), nothing else changed ----
# -- but for the covariance heads benchmarks/covariance_heads.py fits again (issue 49) ---------------------------

SIGNED_AFTER = "3672a05"             # a commit whose shipped cards had format_version 1 and no digest


def _git(*args):
    result = subprocess.run(["git", *args], cwd=ROOT, capture_output=True)
    return result.stdout if result.returncode == 0 else None


def _shipped():
    from kklcasadi.model.shipped import SHIPPED_MODELS

    return [(system, method) for system, methods in SHIPPED_MODELS.items() for method in methods]


def _unsigned_commit(path):
    """The last commit whose ``path`` was a card of format_version 1 (before it was signed), or None for a card
    that was signed when it was first committed."""
    for commit in _git("log", "--format=%H", "--", path).decode().split():
        text = _git("show", f"{commit}:{path}")
        if text is not None and json.loads(text).get("format_version") == 1:
            return commit
    return None


def _last_commit(path):
    """The last commit that changed ``path``."""
    commit = _git("log", "-1", "--format=%H", "--", path).decode().strip()
    assert commit, f"{path} is not committed"
    return commit


def _signed_commit(path, unsigned):
    """The commit that signed ``path``: the first to change it after ``unsigned``."""
    history = _git("log", "--format=%H", "--", path).decode().split()
    return history[history.index(unsigned) - 1] if history.index(unsigned) else None


def _weights(commit, where):
    blob = _git("show", f"{commit}:{where}/weights.npz")
    with np.load(io.BytesIO(blob)) as data:
        return {name: data[name] for name in data.files}


#: What benchmarks/covariance_heads.py writes into a shipped bank's card (its head, its inflation and how they were
#: fit).
HEAD_FIELDS = (("architecture", "covariance"), ("architecture", "inflation"), ("training", "covariance"))


def _without_head(card):
    card = json.loads(json.dumps(card))
    for parent, name in HEAD_FIELDS:
        card.get(parent, {}).pop(name, None)
    return {k: v for k, v in card.items() if k not in (DIGEST, "format_version", "weights_sha256")}


def _written_signed(where):
    """A card written signed by its training: card and weights committed together, as written, and it loads."""
    last = _last_commit(f"{where}/card.json")
    assert _last_commit(f"{where}/weights.npz") == last, f"{where}: its card changed without its weights"
    load_model(ROOT / where)
    for name in ("card.json", "weights.npz"):
        assert _git("rev-parse", f"{last}:{where}/{name}") == _git("hash-object", f"{where}/{name}"), where


def test_the_shipped_cards_were_only_signed(tmp_path):
    if _git("cat-file", "-e", f"{SIGNED_AFTER}^{{commit}}") is None:
        pytest.skip(f"not a git checkout with commit {SIGNED_AFTER}")
    for system, method in _shipped():
        where = f"models/{system}/{method}"
        before = _unsigned_commit(f"{where}/card.json")          # its last card without a digest
        if before is None:          # written signed (the compacts): card and weights committed together, as written
            _written_signed(where)
            continue
        signed = _signed_commit(f"{where}/card.json", before)
        old = json.loads(_git("show", f"{before}:{where}/card.json"))
        assert signed is not None, f"{where}: never signed after {before}"
        at_signing = json.loads(_git("show", f"{signed}:{where}/card.json"))
        if _card(ROOT / where).get(provenance.KEY) != at_signing.get(provenance.KEY):  # trained again since (its own
            _written_signed(where)                                               # stamp): written signed, as above
            continue
        assert old["format_version"] == 1 and at_signing["format_version"] == 2 and DIGEST not in old
        assert {k: v for k, v in at_signing.items() if k not in (DIGEST, "format_version")} == \
            {k: v for k, v in old.items() if k != "format_version"}
        # the weights bit for bit: the blob of the commit before is the one signed
        assert _git("rev-parse", f"{before}:{where}/weights.npz") == _git("rev-parse", f"{signed}:{where}/weights.npz")
        # since then only the covariance head may have been fit again (its card entries and its covariance/* arrays)
        new = _card(ROOT / where)
        assert new["format_version"] == 2 and _without_head(new) == _without_head(at_signing)
        then = _weights(signed, where)
        with np.load(ROOT / where / "weights.npz") as now:
            assert {n for n in now.files if not n.startswith("covariance/")} == \
                {n for n in then if not n.startswith("covariance/")}
            for name in now.files:
                if not name.startswith("covariance/"):
                    np.testing.assert_array_equal(now[name], then[name], err_msg=f"{where}: {name}")
    # and the estimates of a model loaded from the old card (signed as it was) and from the new one, bit for bit
    import kklcasadi as kc

    for system in ("duffing", "vdp", "rossler", "fhn"):
        old_dir = tmp_path / system / "bank"
        shutil.copytree(ROOT / "models" / system / "bank", old_dir)
        where = f"models/{system}/bank/card.json"
        before = _unsigned_commit(where)
        old = json.loads(_git("show", f"{before}:{where}"))
        (old_dir / "weights.npz").write_bytes(_git("show", f"{before}:models/{system}/bank/weights.npz"))
        write_signed_card(old_dir, {**old, "format_version": 2})
        plant = kc.systems.get(system)
        tr = kc.simulate(plant, plant.sample_box(1, 3)[0], kc.signals.make("sinusoid", amplitude=0.5, omega=1.0),
                         T=5.0, dt=0.05, measurement_std=0.05, seed=4)
        a = kc.load_observer(ROOT / "models" / system / "bank").simulate(tr.t, tr.y, tr.u)
        b = kc.load_observer(old_dir).simulate(tr.t, tr.y, tr.u)
        np.testing.assert_array_equal(a.xhat, b.xhat)
        np.testing.assert_array_equal(a.z, b.z)


def test_a_damaged_digest_of_a_field_is_refused(valid_model, tmp_path):
    """The digests of the fields are part of the card: one byte of a field's name in them damaged (found by the
    property test above: 'architecture.gain.sizes' with a blank for its first letter) is refused, not loaded."""
    work = tmp_path / "work"
    shutil.copytree(valid_model.parent, work)
    text = (work / "obs" / CARD_FILE).read_text()
    assert text.count('"architecture.gain.sizes"') == 1
    (work / "obs" / CARD_FILE).write_text(text.replace('"architecture.gain.sizes"', '" rchitecture.gain.sizes"'))
    with pytest.raises(ValueError, match=r"'digest\.fields': expected the digests of the card's fields it was written "
                                         r"with, received other digests") as info:
        load_model(work / "obs")
    _one_line(info.value)


@pytest.mark.parametrize("name", ["\n", "a\tb", "x\r\ny", "\x00"])
def test_a_field_with_a_control_character_in_its_name_is_named_on_one_line(valid_model, tmp_path, name):
    """Found by the property test above: a card edited to hold a field named "\\n" was refused with a message
    broken over two lines; the field's name is shown escaped."""
    body = {key: value for key, value in _card(valid_model).items() if key != DIGEST}
    work = tmp_path / "m"
    shutil.copytree(valid_model.parent, work)
    write_signed_card(work / "obs", {**body, name: None})
    with pytest.raises((ValueError, TypeError)) as refused:
        load_model(work / "obs")
    _one_line(refused.value)
    assert name.encode("unicode_escape").decode("ascii") in str(refused.value)
