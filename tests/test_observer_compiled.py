"""KKLObserver.simulate through its compiled step (kklcasadi.observer.compiled): bitwise the CasADi VM on shipped
models and on a small plant's model, across chunks; the VM with a one-line note where there is no C compiler."""

import warnings

import numpy as np
import pytest

from kklcasadi.compiler import Compiler, CompilerWarning
from kklcasadi.observer.compiled import CompiledTrajectory
from kklcasadi.observer.kkl import COMPILED_FROM, load_observer


def _samples(obs, m, n, seed=0):
    """Times, outputs and inputs of ``m`` trials of ``n`` samples; half of the inputs exactly 0."""
    rng = np.random.default_rng(seed)
    y = 0.5 * rng.standard_normal((m, n, obs.ny))
    u = np.where(rng.random((m, n, obs.nu)) < 0.5, 0.0, rng.standard_normal((m, n, obs.nu)))
    return np.arange(n) * obs.dt, y, u


def _assert_same(a, b):
    for name in ("xhat", "z", "in_domain", "cov"):
        left, right = getattr(a, name), getattr(b, name)
        assert (left is None) == (right is None), name
        if left is not None:
            np.testing.assert_array_equal(left, right, err_msg=name)


@pytest.mark.parametrize("name", ["duffing/bank", "duffing/obs_stream", "duffing/inject"])
def test_simulate_compiled_is_bitwise_the_vm_on_shipped_models(name):
    obs = load_observer(name)
    t, y, u = _samples(obs, 2, 150)
    compiled = obs.simulate(t, y, u, vm=False)
    _assert_same(compiled, obs.simulate(t, y, u, vm=True))
    if name == "duffing/bank":                      # the covariance head and the ensemble's spread, compiled too
        assert compiled.cov is not None and compiled.in_domain is not None and obs.monitor.spec.spread is not None
    single = obs.simulate(t, y[1], u[1], vm=False)
    _assert_same(single, obs.simulate(t, y[1], u[1], vm=True))


@pytest.mark.parametrize("method", ["obs_stream", "dyn", "bank"])
def test_chunks_of_a_small_plants_model_carry_the_state_bitwise(model_dir_factory, mimo_plant, method):
    obs = load_observer(model_dir_factory(method, system=mimo_plant), system=mimo_plant)
    t, y, u = _samples(obs, 3, 200, seed=1)
    vm = obs.simulate(t, y, u, vm=True)
    z, w, xhat, P, spread = CompiledTrajectory(obs, chunk=64).run(          # 64 + 64 + 64 + 7 steps, the last padded
        np.zeros((obs.nz, 3)), np.asarray(obs.memory_init.map(3)(y[:, 0].T, u[:, 0].T)), y, u, n_threads=2)
    np.testing.assert_array_equal(z, vm.z[:, 1:])
    np.testing.assert_array_equal(xhat, vm.xhat[:, 1:])
    assert w.shape == (3, 199) + obs.memory_shape and (P is None) == (vm.cov is None) and spread is None
    _assert_same(obs.simulate(t, y, u, vm=False), vm)


def test_without_a_compiler_simulate_runs_the_vm_with_a_one_line_note(model_dir_factory, monkeypatch):
    obs = load_observer(model_dir_factory("obs"))
    t, y, u = _samples(obs, 2, 60)
    reference = obs.simulate(t, y, u, vm=True)
    monkeypatch.setattr(Compiler, "available", lambda self: False)
    with pytest.warns(CompilerWarning) as notes:
        _assert_same(obs.simulate(t, y, u, vm=False), reference)
    assert len(notes) == 1 and "\n" not in str(notes[0].message)
    assert "not found on PATH" in str(notes[0].message) and "vm=True" in str(notes[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        obs.simulate(t, y, u, vm=True)                    # the VM chosen: no note
        obs.simulate(t, y, u)                             # short: the VM by default, no note
    m = COMPILED_FROM // (t.size - 1) + 1
    long_y, long_u = np.repeat(y[:1], m, axis=0), np.repeat(u[:1], m, axis=0)
    with pytest.warns(CompilerWarning, match="runs the CasADi VM"):
        obs.simulate(t, long_y, long_u)                   # long enough for the compiled step, which is missing


def test_vm_is_a_bool_or_none(model_dir_factory):
    obs = load_observer(model_dir_factory("autonomous"))
    t, y, u = _samples(obs, 1, 5)
    with pytest.raises(TypeError, match="vm: expected True, False or None, received str"):
        obs.simulate(t, y[0], u[0], vm="yes")
