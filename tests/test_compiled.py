import shutil

import casadi as ca
import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.estimators.ekf import EKF
from kklcasadi.evaluation.compiled import (
    CompiledEKF,
    CompiledEstimator,
    Compiler,
    CompilerWarning,
    compile_function,
    ekf_estimator,
    observer_estimator,
)
from kklcasadi.model import variants
from kklcasadi.observer.kkl import load_observer

needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")

#: Every registered variant (and obs on top of inject), as ``model_dir_factory`` arguments.
VARIANTS = {name: (name, {"base": True} if name == "inject" else {}) for name in variants.names()}
VARIANTS["obs-inject"] = ("obs", {"base": True, "card_extra": {"model_based_injection": True}})


def _trials(plant, m=3, n=25, seed=0):
    """Seeded measured trials: ``t`` (n,), ``y`` (m, n, ny), ``u`` (m, n, nu), float64."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.05
    return t, rng.normal(size=(m, n, plant.ny)), rng.uniform(-1, 1, (m, n, plant.nu))


@needs_gcc
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_the_compiled_observer_is_bitwise_the_vm_and_simulate(model_dir_factory, tmp_path, variant):
    method, options = VARIANTS[variant]
    obs = load_observer(model_dir_factory(method, **options))
    t, y, u = _trials(obs.system)
    compiled = observer_estimator(obs, compiler=Compiler(cache_dir=tmp_path))
    vm = observer_estimator(obs, compiler=None)
    reference = obs.simulate(t, y, u).xhat
    # same expression graph, portable flags without FMA contraction: bitwise equal (tolerance 0)
    np.testing.assert_array_equal(vm(t, y, u), reference)
    np.testing.assert_array_equal(compiled(t, y, u), reference)
    f = vm.trajectory(t.size)
    g = compiled.function(t.size)
    assert g.name() == f.name() and g.name_in() == ["y", "u", "s0"] and g.name_out() == ["xhat"]
    s0 = np.random.default_rng(1).normal(size=obs.nz)              # any initial state, not only z0 = 0
    np.testing.assert_array_equal(np.asarray(g(y[0].T, u[0].T, s0)), np.asarray(f(y[0].T, u[0].T, s0)))


@needs_gcc
@pytest.mark.parametrize("variant", sorted(VARIANTS))
@pytest.mark.parametrize("kernels", ["axpy_matvec", "fast_kernels"])
def test_the_evaluation_kernels_keep_the_vm_values(model_dir_factory, tmp_path, variant, kernels):
    """kklcasadi evaluate's sources: axpy mat-vecs bitwise; with the vector exp/tanh within 1e-14 (1 + |VM|)."""
    from kklcasadi.observer import codegen

    method, options = VARIANTS[variant]
    obs = load_observer(model_dir_factory(method, **options))
    t, y, u = _trials(obs.system)
    reference = obs.simulate(t, y, u).xhat
    compiler = Compiler(cache_dir=tmp_path, postprocess=getattr(codegen, kernels))
    fast = observer_estimator(obs, compiler=compiler)(t, y, u)
    tol = 0.0 if kernels == "axpy_matvec" else codegen.VECTOR_MATH_TOLERANCE
    assert np.max(np.abs(fast - reference) / (1 + np.abs(reference))) <= tol
    with pytest.raises(TypeError, match="source: expected the C source as str"):
        getattr(codegen, kernels)(b"int x;")


@needs_gcc
def test_the_compiled_ekf_is_bitwise_its_simulate(tmp_path):
    plant = kc.systems.get("vdp")
    ekf = EKF(plant, 0.05)
    t, y, u = _trials(plant, m=4)
    reference = ekf.simulate(t, y, u).xhat
    np.testing.assert_array_equal(ekf_estimator(ekf, compiler=None)(t, y, u), reference)
    np.testing.assert_array_equal(ekf_estimator(ekf, compiler=Compiler(cache_dir=tmp_path))(t, y, u), reference)


@needs_gcc
def test_libraries_are_cached_by_source_and_the_postprocess_hook_is_applied(tmp_path):
    x = ca.MX.sym("x", 3)
    f = ca.Function("cube_sum", [x], [ca.sum1(x ** 3)])
    lib = Compiler(cache_dir=tmp_path).library(f)
    mtime = lib.stat().st_mtime_ns
    assert Compiler(cache_dir=tmp_path).library(f) == lib and lib.stat().st_mtime_ns == mtime   # not rebuilt
    assert lib.with_suffix(".c").read_text() == Compiler().source(f)
    seen = []

    def hook(source: str) -> str:
        seen.append(len(source))
        return source + "\n/* post-processed */\n"

    hooked = Compiler(cache_dir=tmp_path, postprocess=hook)
    assert hooked.library(f) != lib and seen
    assert hooked.library(f).with_suffix(".c").read_text().endswith("/* post-processed */\n")
    assert compile_function(f, cache_dir=tmp_path, flags=("-O1",)).name() == "cube_sum"
    np.testing.assert_array_equal(np.asarray(hooked.compile(f)([1.0, 2.0, 3.0])), 36.0)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".build-")]


def test_a_missing_compiler_falls_back_to_the_vm_with_a_warning(model_dir_factory, tmp_path):
    obs = load_observer(model_dir_factory("obs"))
    t, y, u = _trials(obs.system, m=2)
    missing = Compiler(command="kklcasadi-no-such-cc", cache_dir=tmp_path)
    assert not missing.available()
    est = observer_estimator(obs, compiler=missing)
    with pytest.warns(CompilerWarning, match="'kklcasadi-no-such-cc' not found on PATH.*CasADi VM"):
        xhat = est(t, y, u)
    np.testing.assert_array_equal(xhat, obs.simulate(t, y, u).xhat)
    with pytest.raises(FileNotFoundError, match="kklcasadi-no-such-cc"):
        missing.library(obs.decode)
    assert not list(tmp_path.iterdir())


@needs_gcc
def test_a_failing_compiler_is_an_error_with_its_output(tmp_path):
    broken = Compiler(cache_dir=tmp_path, postprocess=lambda source: source + "\n#error deliberately broken\n")
    z = ca.MX.sym("z")
    with pytest.raises(RuntimeError, match="(?s)compiling 'decode' failed.*source kept in.*deliberately broken"):
        broken.compile(ca.Function("decode", [z], [2 * z]))
    assert [p.suffixes for p in tmp_path.iterdir()] == [[".failed", ".c"]]
    with pytest.raises(TypeError, match="postprocess: expected it to return the C source as str"):
        Compiler(cache_dir=tmp_path, postprocess=lambda source: None).source(ca.Function("f", [], []))


def test_arguments_are_checked(model_dir_factory):
    obs = load_observer(model_dir_factory("autonomous"))
    est = observer_estimator(obs, compiler=None)
    t, y, u = _trials(obs.system, m=2)
    with pytest.raises(ValueError, match=r"y: expected shape \(M, 25, 1\), received \(25, 1\)"):
        est(t, y[0], u[0])
    with pytest.raises(ValueError, match=r"u: expected shape \(2, 25, 1\), received \(3, 25, 1\)"):
        est(t, y, np.zeros((3, 25, 1)))
    with pytest.raises(ValueError, match="t: expected samples spaced by dt = 0.05"):
        est(t * 2, y, u)
    y_bad = y.copy()
    y_bad[1, 4, 0] = np.nan
    with pytest.raises(ValueError, match="y: expected finite values, received nan at trial 1, sample 4"):
        est(t, y_bad, u)
    assert est(t, y[:0], u[:0]).shape == (0, 25, 2)
    with pytest.raises(TypeError, match="compiler: expected a kklcasadi.evaluation.compiled.Compiler or None"):
        observer_estimator(obs, compiler="gcc")
    with pytest.raises(ValueError, match="n_threads: expected a positive int or None, received 0"):
        observer_estimator(obs, n_threads=0)
    with pytest.raises(TypeError, match="observer: expected a kklcasadi.KKLObserver"):
        observer_estimator(EKF(obs.system, 0.05))
    with pytest.raises(TypeError, match="ekf: expected a kklcasadi.estimators.ekf.EKF"):
        CompiledEKF(obs)
    with pytest.raises(TypeError, match="flags: expected a tuple of str"):
        Compiler(flags="-O3")
    with pytest.raises(TypeError, match="f: expected a casadi.Function"):
        Compiler().compile(obs)
    with pytest.raises(TypeError, match="abstract"):
        CompiledEstimator(2, 1, 1, 0.05)


@needs_gcc
def test_bench_protocol_times_each_method_against_the_vm(model_dir_factory, tmp_path):
    from kklcasadi.evaluation.bench.protocol import bench_protocol
    from kklcasadi.model.shipped import shipped_models

    result = bench_protocol("duffing", models=[model_dir_factory("autonomous")], n_trials=2, vm_trials=1,
                            kinds=("zero",), cache_dir=tmp_path, progress=False)
    assert result.cells == 2 and [m.label for m in result.methods] == ["autonomous", "EKF"]
    assert all(m.max_diff <= 1e-14 and m.trials == 4 and m.vm_trials == 2 for m in result.methods)
    assert result.warm_s < result.cold_s
    table = result.table()
    assert "| autonomous |" in table and "full protocol, warm caches" in table
    rows = [line for line in table.splitlines() if line.startswith("|")]
    assert len(rows) == 4 and all(line.count("|") == 9 for line in rows)     # 8 columns, every row
    assert [p.name for p in shipped_models("duffing")][:3] == ["autonomous", "inject", "obs"]
    with pytest.raises(ValueError, match="vm_trials: expected an int in"):
        bench_protocol("duffing", n_trials=2, vm_trials=3)
