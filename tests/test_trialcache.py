import os
import warnings
from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.evaluation import trialcache
from kklcasadi.evaluation.protocol import Protocol
from kklcasadi.evaluation.trialcache import TrialCache, TrialCacheWarning, cache_root

#: A short protocol (3 trials of 2 s, RK4 plant) so every cell simulates in milliseconds.
SHORT = Protocol(n_trials=3, T=2.0, method="rk")
ARRAYS = ("t", "x", "u", "y", "ok")


def _assert_same_batch(a, b):
    for name in ARRAYS:
        left, right = getattr(a, name), getattr(b, name)
        assert left.dtype == right.dtype, name
        np.testing.assert_array_equal(left, right, err_msg=name)


def _load_quietly(cache, system, protocol, kind):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return cache.load(system, protocol.cell(kind))


def test_a_cached_cell_equals_a_fresh_simulation_bitwise(tmp_path):
    plant = kc.systems.get("duffing")
    cache = TrialCache(tmp_path)
    assert cache.load(plant, SHORT.cell("square")) is None
    stored = cache.trials(plant, SHORT.cell("square"))
    assert cache.path(plant, SHORT.cell("square")).exists()
    loaded = _load_quietly(TrialCache(tmp_path), plant, SHORT, "square")
    fresh = SHORT.trials(plant, "square")
    _assert_same_batch(stored, fresh)
    _assert_same_batch(loaded, fresh)
    assert not loaded.x.flags.writeable
    assert [p.name for p in tmp_path.iterdir()] == [cache.path(plant, SHORT.cell("square")).name]   # no temp files
    with np.load(cache.path(plant, SHORT.cell("square")), allow_pickle=False) as data:
        assert set(data.files) == {*ARRAYS, "description", "digest"}


def test_noise_free_and_noisy_cells_are_separate_files(tmp_path):
    plant = kc.systems.get("vdp")
    cache = TrialCache(tmp_path)
    clean, noisy = SHORT.noise_free(), SHORT
    assert cache.path(plant, clean.cell("zero")) != cache.path(plant, noisy.cell("zero"))
    assert "clean" in cache.path(plant, clean.cell("zero")).name
    assert "noisy" in cache.path(plant, noisy.cell("zero")).name
    _assert_same_batch(cache.trials(plant, clean.cell("zero")), clean.trials(plant, "zero"))
    _assert_same_batch(cache.trials(plant, noisy.cell("zero")), noisy.trials(plant, "zero"))


def _duffing_like(box=((-1, 1), (-1, 1)), cubic=1.0):
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    return kc.System("duffing", x, u, [x[1], -x[0] - cubic * x[0] ** 3 + u], x[0], box)


def test_the_key_follows_every_protocol_field_the_system_the_regime_and_the_version(monkeypatch, tmp_path):
    cache = TrialCache(tmp_path)
    plant = kc.systems.get("duffing")
    base = cache.key(plant, SHORT.cell("square"))
    assert cache.key(kc.systems.get("duffing"), Protocol(n_trials=3, T=2.0, method="rk").cell("square")) == base
    assert cache.key(_duffing_like(), SHORT.cell("square")) == base                 # same definition, rebuilt
    changed = [replace(SHORT, n_trials=4), replace(SHORT, T=3.0), replace(SHORT, dt=0.1), replace(SHORT, seed=7),
               replace(SHORT, process_std=0.2), replace(SHORT, measurement_std=0.0), replace(SHORT, regime="ood"),
               replace(SHORT, method="cvodes"), replace(SHORT, t_settle=1.0)]
    keys = {cache.key(plant, p.cell("square")) for p in changed}
    assert len(keys) == len(changed) and base not in keys
    assert cache.key(plant, SHORT.cell("sinusoid")) != base
    assert cache.key(kc.systems.get("vdp"), SHORT.cell("square")) != base
    assert cache.key(_duffing_like(box=((-1, 1), (-2, 2))), SHORT.cell("square")) != base
    assert cache.key(_duffing_like(cubic=1.0 + 1e-12), SHORT.cell("square")) != base
    assert _duffing_like(cubic=1.0 + 1e-12).definition_digest != plant.definition_digest
    monkeypatch.setattr(trialcache, "__version__", "999.0")
    assert cache.key(plant, SHORT.cell("square")) != base


@pytest.mark.parametrize("damage", ["truncate", "garbage", "flip"])
def test_a_damaged_file_is_reported_and_simulated_again(tmp_path, damage):
    plant = kc.systems.get("duffing")
    cache = TrialCache(tmp_path)
    path = cache.store(plant, SHORT.cell("constant"), SHORT.trials(plant, "constant"))
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "garbage":
        data = bytearray(b"not a zip file" * 10)
    else:
        data[len(data) // 2] ^= 0xFF                                   # inside the arrays
    path.write_bytes(bytes(data))
    with pytest.warns(TrialCacheWarning, match="ignoring"):
        batch = cache.trials(plant, SHORT.cell("constant"))
    _assert_same_batch(batch, SHORT.trials(plant, "constant"))
    _assert_same_batch(_load_quietly(cache, plant, SHORT, "constant"), batch)     # rewritten, valid again


def test_arrays_that_do_not_match_their_digest_are_not_used(tmp_path):
    plant = kc.systems.get("duffing")
    cache = TrialCache(tmp_path)
    path = cache.store(plant, SHORT.cell("zero"), SHORT.trials(plant, "zero"))
    with np.load(path, allow_pickle=False) as data:
        content = {name: data[name] for name in data.files}
    content["x"] = content["x"].copy()
    content["x"][0, 1, 0] += 1e-9
    with open(path, "wb") as handle:
        np.savez(handle, **content)
    with pytest.warns(TrialCacheWarning, match="digest"):
        assert cache.load(plant, SHORT.cell("zero")) is None


def test_a_file_of_another_cell_under_this_name_is_not_used(tmp_path):
    plant = kc.systems.get("duffing")
    cache = TrialCache(tmp_path)
    other = replace(SHORT, seed=5)
    source = cache.store(plant, other.cell("zero"), other.trials(plant, "zero"))
    os.replace(source, cache.path(plant, SHORT.cell("zero")))
    with pytest.warns(TrialCacheWarning, match="another system, protocol"):
        assert cache.load(plant, SHORT.cell("zero")) is None


def test_store_refuses_a_batch_of_another_shape(tmp_path):
    plant = kc.systems.get("duffing")
    batch = replace(SHORT, n_trials=2).trials(plant, "zero")
    with pytest.raises(ValueError, match=r"x has shape \(2, 40, 2\), expected \(3, 40, 2\)"):
        TrialCache(tmp_path).store(plant, SHORT.cell("zero"), batch)
    with pytest.raises(TypeError, match="batch: expected a kklcasadi.TrajectoryBatch"):
        TrialCache(tmp_path).store(plant, SHORT.cell("zero"), {"x": 1})
    with pytest.raises(TypeError, match="directory: expected a path or None"):
        TrialCache(3)


def test_the_default_directory_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("KKLCASADI_CACHE", str(tmp_path / "root"))
    assert cache_root() == tmp_path / "root"
    assert TrialCache.default().directory == tmp_path / "root" / "trials"
    monkeypatch.delenv("KKLCASADI_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_root() == tmp_path / "xdg" / "kklcasadi"
