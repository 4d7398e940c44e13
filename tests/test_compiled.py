import shutil

import casadi as ca
import numpy as np
import pytest
from conftest import assert_exp_tanh_ulps

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
    precompile,
    reuse_decoded,
    skip_at_zero_input,
    split_step,
)
from kklcasadi.evaluation.protocol import Profile
from kklcasadi.model import variants
from kklcasadi.observer.kkl import load_observer

needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")

#: Every registered variant (and obs on top of inject), as ``model_dir_factory`` arguments.
VARIANTS = {name: (name, {"base": True} if name == "inject" else {}) for name in variants.names()}
VARIANTS["obs-inject"] = ("obs", {"base": True, "card_extra": {"model_based_injection": True}})


#: The variants whose trials with the same inputs share work (a memory that does work of its own).
SHARING = {"obs", "obs-inject", "dyn", "obs_stream", "dyn_stream"}


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
    """kklcasadi evaluate's sources: axpy mat-vecs bitwise; with the vector exp/tanh and the fused multiply-adds
    within FUSED_TOLERANCE (1 + |VM|)."""
    from kklcasadi.observer import codegen

    method, options = VARIANTS[variant]
    obs = load_observer(model_dir_factory(method, **options))
    t, y, u = _trials(obs.system)
    reference = obs.simulate(t, y, u).xhat
    compiler = Compiler(cache_dir=tmp_path, postprocess=getattr(codegen, kernels))
    fast = observer_estimator(obs, compiler=compiler)(t, y, u)
    tol = 0.0 if kernels == "axpy_matvec" else codegen.FUSED_TOLERANCE
    assert np.max(np.abs(fast - reference) / (1 + np.abs(reference))) <= tol
    with pytest.raises(TypeError, match="source: expected the C source as str"):
        getattr(codegen, kernels)(b"int x;")


def _shared_trials(plant, n=40, seed=0):
    """Nine seeded trials: four pairs that share their inputs (a zero input, a constant, a square wave
    whose windows repeat between its edges, a random input) with distinct measurements, and one
    unpaired random input."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.05
    inputs = np.stack([np.zeros(n), np.full(n, 0.7), 0.5 * np.sign(np.sin(2.0 * t + 0.3)), rng.uniform(-1, 1, n)])
    u = np.repeat(inputs[:, :, None], plant.nu, axis=2)
    u = np.concatenate([u, u, rng.uniform(-1, 1, (1, n, plant.nu))])
    return t, rng.normal(size=(9, n, plant.ny)), u


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_trials_that_share_their_inputs_share_work_and_keep_every_value(model_dir_factory, tmp_path, variant):
    """Grouped by their inputs (pairs here), memoised, injection skipped at u = 0: bitwise ``simulate``."""
    method, options = VARIANTS[variant]
    obs = load_observer(model_dir_factory(method, **options))
    t, y, u = _shared_trials(obs.system)
    reference = obs.simulate(t, y, u).xhat
    vm = observer_estimator(obs, compiler=None)
    assert vm.shares_inputs == (variant in SHARING)
    assert vm.carries == (variant in ("inject", "obs-inject"))       # the estimate read back by the next step
    assert not observer_estimator(obs, compiler=None, shortcuts=False).carries
    groups = vm._grouped(u)
    if vm.shares_inputs:
        assert [g.tolist() for g in groups] == [[[8]], [[0, 4], [1, 5], [2, 6], [3, 7]]]
    else:
        assert [g.tolist() for g in groups] == [[[i] for i in range(9)]]
    np.testing.assert_array_equal(vm(t, y, u), reference)
    if variant in ("obs-inject", "dyn", "obs_stream") and shutil.which("gcc"):   # in C: switches, LoRA inlined, stream
        compiled = observer_estimator(obs, compiler=Compiler(cache_dir=tmp_path))
        np.testing.assert_array_equal(compiled(t, y, u), reference)
    alone = observer_estimator(obs, compiler=None, group=1)          # no groups: the memo alone
    assert [g.shape for g in alone._grouped(u)] == [(9, 1)]
    np.testing.assert_array_equal(alone(t, y, u), reference)


def test_trials_group_by_the_bits_of_their_inputs(model_dir_factory):
    """Groups of at most ``group`` trials with bitwise equal inputs, by group size, in the trials' order."""
    est = observer_estimator(load_observer(model_dir_factory("obs")), compiler=None, group=3)
    u = np.zeros((7, 4, 1))
    u[3, 1] = -0.0                                                 # equal to 0.0 but not bitwise: its own group
    u[5:] = 1.0
    assert [g.tolist() for g in est._grouped(u)] == [[[4], [3]], [[5, 6]], [[0, 1, 2]]]
    assert est._grouped(u[:0]) == []
    plain = ekf_estimator(EKF(kc.systems.get("duffing"), 0.05), compiler=None)
    assert not plain.shares_inputs and [g.tolist() for g in plain._grouped(u[:3])] == [[[0], [1], [2]]]


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_the_split_step_is_bitwise_the_step(model_dir_factory, variant):
    method, options = VARIANTS[variant]
    obs = load_observer(model_dir_factory(method, **options))
    split = split_step(obs.step)
    if variant not in SHARING:
        assert split is None
        return
    rng = np.random.default_rng(3)
    for _ in range(5):
        z, w, y, y_next, u_next = (rng.normal(size=obs.step.size_in(i)) for i in range(5))
        z_next, w_next, xhat_next = obs.step(z, w, y, y_next, u_next)
        s = split.shared(w, u_next)
        core = split.core(z, w, y, y_next, u_next, s)
        np.testing.assert_array_equal(np.asarray(core[0]), np.asarray(z_next))
        np.testing.assert_array_equal(np.asarray(core[1]), np.asarray(xhat_next))
        np.testing.assert_array_equal(np.asarray(split.w_next(ca.DM(s), obs.memory_shape)), np.asarray(w_next))


def test_the_shared_part_is_reused_while_its_key_repeats(model_dir_factory):
    obs = load_observer(model_dir_factory("obs"))
    est = observer_estimator(obs, compiler=None)
    step = est._group_step(2)
    rng = np.random.default_rng(0)
    Z, Y, Y_next = rng.normal(size=(obs.nz, 2)), rng.normal(size=(1, 2)), rng.normal(size=(1, 2))
    w, u_next = rng.normal(size=obs.memory_shape), np.array([0.3])
    key = np.concatenate([w.ravel(order="F"), u_next])
    stale = rng.normal(size=est.split.shared.size1_out(0))          # not what shared(w, u_next) gives
    kept = step(Z, w, key, stale, Y, Y_next, u_next)
    np.testing.assert_array_equal(np.asarray(kept[3]).ravel(), stale)   # same key: reused as it is
    fresh = step(Z, w, key + 1.0, stale, Y, Y_next, u_next)
    np.testing.assert_array_equal(np.asarray(fresh[3]), np.asarray(est.split.shared(w, u_next)))
    np.testing.assert_array_equal(np.asarray(fresh[2]).ravel(), key)


def test_an_injection_is_skipped_exactly_where_the_input_is_zero():
    z, u = ca.MX.sym("z", 2), ca.MX.sym("u")
    injection = ca.Function("injection", [z, u], [z + 1 + u])      # not 0 at u = 0: shows the skip
    step = ca.Function("step", [z, u], [2 * injection(injection(z, u), u)], ["z", "u"], ["z_next"])
    skipped = skip_at_zero_input(step, injection)
    assert skipped.name() == "step" and skipped.name_in() == ["z", "u"]
    np.testing.assert_array_equal(np.asarray(skipped([1.0, 2.0], 0.0)), 0.0)
    np.testing.assert_array_equal(np.asarray(skipped([1.0, 2.0], 0.5)), np.asarray(step([1.0, 2.0], 0.5)))
    other = ca.Function("other", [z, u], [z * u])
    assert skip_at_zero_input(step, other) is step


def test_the_estimate_of_the_previous_step_stands_in_for_decoding_the_step_s_own_z():
    z, u, w = ca.MX.sym("z", 2), ca.MX.sym("u"), ca.MX.sym("w")
    a, b = ca.MX.sym("a", 2), ca.MX.sym("b")
    decoder = ca.Function("decoder", [a, b], [ca.tanh(a) * 3])        # reads its first argument only
    decode = ca.Function("decode", [z, w], [decoder(z, w)], ["z", "w"], ["xhat"])
    c = ca.MX.sym("c")
    injection = ca.Function("injection", [a, c], [decoder(a, 0) * c])   # own symbols: a call in the step
    y, y_next = ca.MX.sym("y"), ca.MX.sym("y_next")
    z_next = z + injection(z, u) + injection(z + 1, u)               # the second stage decodes z + 1 itself
    step = ca.Function("step", [z, w, y, y_next, u], [z_next, u, decode(z_next, u)],
                       ["z", "w", "y", "y_next", "u_next"], ["z_next", "w_next", "xhat_next"])
    reused, of_xhat = reuse_decoded(step, injection, decode)
    assert reused.name_in() == ["z", "w", "xhat", "y", "y_next", "u_next"] and of_xhat.name_in() == ["xhat", "u"]
    zv = np.array([0.3, -0.2])
    xhat = np.asarray(decode(zv, 0.0))
    for out, ref in zip(reused(zv, 0.0, xhat, 0.0, 0.0, 0.7), step(zv, 0.0, 0.0, 0.0, 0.7)):
        np.testing.assert_array_equal(np.asarray(out), np.asarray(ref))
    np.testing.assert_array_equal(np.asarray(reused(zv, 0.0, 0 * xhat, 0.0, 0.0, 0.7)[0]),   # it reads xhat
                                  zv[:, None] + np.asarray(injection(zv + 1, 0.7)))
    assert reuse_decoded(step, ca.Function("other", [z, u], [z * u]), decode) is None
    assert reuse_decoded(step, injection, ca.Function("d", [z, w], [z * w], ["z", "w"], ["xhat"])) is None


@needs_gcc
def test_precompile_runs_the_compilers_beside_other_work(model_dir_factory, tmp_path):
    obs = load_observer(model_dir_factory("obs"))
    profile = Profile()
    estimators = [observer_estimator(obs, compiler=Compiler(cache_dir=tmp_path), profile=profile),
                  ekf_estimator(EKF(obs.system, 0.05), compiler=Compiler(cache_dir=tmp_path), profile=profile),
                  observer_estimator(obs, compiler=None)]
    assert precompile(estimators, 25, groups=(2,), meanwhile=lambda: "trials") == "trials"
    assert sorted(estimators[0]._functions) == [(25, 2)] and sorted(estimators[1]._functions) == [(25, 1)]
    assert not estimators[2]._functions and profile.wall["compile"] > 0 and profile.cpu["compile"] > 0
    assert len(list(tmp_path.glob("*.so"))) == 2
    t, y, u = _shared_trials(obs.system, n=25)
    np.testing.assert_array_equal(estimators[0](t, y[:8], u[:8]), obs.simulate(t, y[:8], u[:8]).xhat)
    assert sorted(estimators[0]._functions) == [(25, 2)]           # every trial in a pair: nothing new built


def test_profile_phases_nest_without_counting_twice():
    profile = Profile()
    with profile.phase("estimate"):
        with profile.phase("compile"):
            sum(range(200000))
        profile.add("compile", 1.0, 2.0)
    assert set(profile.wall) == {"estimate", "compile"} and profile.cpu["compile"] >= 2.0
    assert profile.wall["compile"] >= 1.0 and profile.wall["estimate"] < profile.wall["compile"]
    table = profile.table(10.0, 4.0)
    assert "| estimate |" in table and table.endswith("| total | 10.0 | 4.0 | 0.40 |")


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
def test_bench_protocol_times_each_method_cold_and_warm_against_the_plain_step_and_the_vm(model_dir_factory,
                                                                                          tmp_path):
    from kklcasadi.evaluation.bench.protocol import bench_protocol
    from kklcasadi.model.shipped import shipped_models

    counting = shutil.which("valgrind") is not None
    models = [model_dir_factory("autonomous"), model_dir_factory("obs")]
    result = bench_protocol("duffing", models=models, n_trials=2, vm_trials=1, plain_trials=1, kinds=("square",),
                            cache_dir=tmp_path, progress=False, instructions=counting)
    assert result.cells == 2 and [m.label for m in result.methods] == ["autonomous", "obs", "EKF"]
    assert all(m.max_diff <= 1e-14 and m.trials == 4 and m.vm_trials == 2 for m in result.methods)
    obs, ekf = result.methods[1], result.methods[2]
    assert obs.plain_trials == 2 and obs.plain_s > 0 and ekf.plain_s is None
    assert {"simulate", "compile", "estimate", "score"} <= set(result.cold_profile.wall)
    assert "read" in result.warm_profile.wall and "simulate" not in result.warm_profile.wall
    assert len(result.load) == 3 and result.warm_s > 0
    if counting:                                   # square-wave windows repeat: the memo saves work
        assert obs.instructions < obs.plain_instructions and ekf.instructions > 0 and ekf.plain_instructions is None
    table = result.table()
    assert "| obs |" in table and "warm caches (read + load, then score)" in table and "| total |" in table
    blocks = [[line for line in block.splitlines() if line.startswith("|")] for block in table.split("\n\n")]
    blocks = [b for b in blocks if b]                   # the methods, the cold run's and the warm run's phases
    assert len(blocks) == 3 and all(len({line.count("|") for line in b}) == 1 for b in blocks)   # rows as headers
    assert [p.name for p in shipped_models("duffing")][:3] == ["autonomous", "inject", "obs"]
    with pytest.raises(ValueError, match="vm_trials: expected an int in"):
        bench_protocol("duffing", n_trials=2, vm_trials=3)
    with pytest.raises(ValueError, match="plain_trials: expected an int in"):
        bench_protocol("duffing", n_trials=2, vm_trials=1, plain_trials=3)


def _has_avx2_fma() -> bool:
    try:
        flags = open("/proc/cpuinfo").read()
    except OSError:
        return False
    return " avx2" in flags and " fma" in flags


@needs_gcc
@pytest.mark.skipif(not _has_avx2_fma(), reason="the fused kernels run where the CPU has AVX2 and FMA")
@pytest.mark.parametrize("shape", [(32, 9), (20, 150), (7, 5)])
def test_the_fused_kernels_round_each_multiply_add_once(tmp_path, shape):
    """fast_kernels' mat-vec, against an exact rational reference: each vector row is summed over k in
    ascending order, ``v = round(v + x_jk y_k)`` (one rounding per multiply-add, FMA); the rows that a block
    leaves to scalars (7 rows: 4 in a vector, 3 scalars) as ``round(v + round(x_jk y_k))``; the bitwise kernels
    (axpy_matvec) as the VM."""
    from fractions import Fraction

    from kklcasadi.observer.codegen import axpy_matvec, fast_kernels

    nrow, ncol = shape
    rng = np.random.default_rng(7)
    W, b = rng.normal(size=(nrow, ncol)), rng.normal(size=nrow)
    y = ca.MX.sym("y", ncol)
    f = ca.Function("mv", [y], [ca.mtimes(ca.DM(W), y) + ca.DM(b)])
    yv = rng.normal(size=ncol)
    vm = np.asarray(f(yv)).ravel()
    fused = np.asarray(Compiler(cache_dir=tmp_path, postprocess=fast_kernels).compile(f)(yv)).ravel()
    plain = np.asarray(Compiler(cache_dir=tmp_path, postprocess=axpy_matvec).compile(f)(yv)).ravel()
    np.testing.assert_array_equal(plain, vm)
    block = min(16, nrow)                                    # the kernels' register blocks of outputs
    full, tail = (nrow // block) * block, nrow % block
    expected = np.empty(nrow)
    for j in range(nrow):
        in_vector = j % block < block // 4 * 4 if j < full else j - full < tail // 4 * 4
        v = 0.0
        for k in range(ncol):
            if in_vector:
                v = float(Fraction(v) + Fraction(W[j, k]) * Fraction(yv[k]))
            else:
                v = v + W[j, k] * yv[k]
        expected[j] = v + b[j]
    np.testing.assert_array_equal(fused, expected)
    assert np.max(np.abs(fused - vm) / (1 + np.abs(vm))) <= 1e-14         # one wide sum: far inside the tolerance
    if ncol > 50:
        assert np.any(fused != vm)       # the fused kernel ran: long sums round differently


@needs_gcc
@pytest.mark.skipif(not _has_avx2_fma(), reason="the fused kernels run where the CPU has AVX2 and FMA")
def test_the_fused_exp_and_tanh_keep_their_ulp_bounds(tmp_path):
    """fast_kernels' exp and tanh, whose polynomials fuse their multiply-adds in the AVX2 version: within 1 ulp
    (exp) and 3 ulp (tanh) of numpy, NaN and infinities as the C library (the unfused bounds, docs/design.md)."""
    from kklcasadi.observer.codegen import fast_kernels

    x = ca.MX.sym("x", 64)
    f = ca.Function("vmath", [x], [ca.vertcat(ca.exp(x), ca.tanh(x))])
    compiler = Compiler(cache_dir=tmp_path, postprocess=fast_kernels)
    assert "fma(q, r, " in compiler.source(f)
    rng = np.random.default_rng(0)
    special = [0.0, -0.0, np.inf, -np.inf, np.nan, 709.78, 709.79, 710.0, -707.0, -708.5, -745.0,
               -745.2, -746.0, 5e-324, 1e-300, -1e-300, 19.06, 19.1, 20.0, -20.0, 0.3465, -0.3466]
    points = np.concatenate([rng.uniform(-1, 1, 6000), rng.uniform(-30, 30, 6000), rng.uniform(-750, 750, 6000),
                             rng.choice([-1, 1], 1960) * 10.0 ** rng.uniform(-320, 0, 1960), special, [0.5] * 50])
    X = points.reshape(-1, 64).T
    out = np.asarray(compiler.compile(f.map(X.shape[1]))(X))
    got_exp, got_tanh = out[:64].T.ravel(), out[64:].T.ravel()
    assert_exp_tanh_ulps(points, got_exp, got_tanh)


@needs_gcc
@pytest.mark.parametrize("variant", ["obs", "inject", "bank"])
def test_a_warm_library_cache_skips_building_the_trajectory(model_dir_factory, tmp_path, monkeypatch, variant):
    """A second estimator of the same observer finds its library through the index without building the trajectory
    (what a warm kklcasadi evaluate's compile phase spent its seconds on), bitwise the first's estimates; another
    observer, other options, other package code or a vanished library build their own."""
    from kklcasadi.evaluation.compiled import estimators as module
    from kklcasadi.observer.codegen import fast_kernels

    method, options = VARIANTS[variant]
    path = model_dir_factory(method, **options)
    compiler = Compiler(cache_dir=tmp_path, postprocess=fast_kernels)
    t, y, u = _trials(load_observer(path).system)
    first = observer_estimator(load_observer(path), compiler=compiler)
    expected = first(t, y, u)
    assert len(list((tmp_path / "index").iterdir())) == 1

    def refuse(self, n, group=1):
        raise AssertionError("the trajectory was built although its library is cached")

    with monkeypatch.context() as patch:
        patch.setattr(module.CompiledObserver, "trajectory", refuse)
        again = observer_estimator(load_observer(path), compiler=compiler)
        np.testing.assert_array_equal(again(t, y, u), expected)
        precompile([observer_estimator(load_observer(path), compiler=compiler)], t.size)   # precompile too
        for other in (observer_estimator(load_observer(path), compiler=compiler, shortcuts=False),
                      observer_estimator(load_observer(model_dir_factory(method, seed=1, **options)),
                                         compiler=compiler)):
            with pytest.raises(AssertionError, match="was built"):
                other(t, y, u)
        patch.setattr(module, "code_digest", lambda: "another package")
        with pytest.raises(AssertionError, match="was built"):
            observer_estimator(load_observer(path), compiler=compiler)(t, y, u)
    for library in tmp_path.glob("*.so"):
        library.unlink()                                       # the index names a library that is gone
    np.testing.assert_array_equal(observer_estimator(load_observer(path), compiler=compiler)(t, y, u), expected)


@needs_gcc
def test_no_index_for_a_hook_that_no_name_identifies(model_dir_factory, tmp_path):
    """A lambda as postprocess (two lambdas share a name): every estimator builds from the source, no index."""
    from kklcasadi.observer.codegen import fast_kernels

    obs = load_observer(model_dir_factory("inject", base=True))
    t, y, u = _trials(obs.system)
    compiler = Compiler(cache_dir=tmp_path, postprocess=lambda source: fast_kernels(source))
    observer_estimator(obs, compiler=compiler)(t, y, u)
    assert not (tmp_path / "index").exists() and len(list(tmp_path.glob("*.so"))) == 1
    with pytest.raises(TypeError, match="identity: expected a str"):
        compiler.build_known(42, lambda: obs.step)
    with pytest.raises(TypeError, match="make: expected a callable"):
        compiler.build_known("x", obs.step.name())


@needs_gcc
@pytest.mark.parametrize("model", ["duffing/compact", "duffing/bank"])
def test_the_shipped_observers_keep_the_fused_tolerance(tmp_path, model):
    """The evaluation path (fast_kernels) on the shipped Duffing compact and bank, two protocol trials: within
    FUSED_TOLERANCE (1 + |VM|) of the VM (the 256-wide layers put these farthest from it: 2.0e-14 and 1.1e-14 over
    the whole protocol)."""
    from kklcasadi.evaluation.protocol import Protocol
    from kklcasadi.observer.codegen import FUSED_TOLERANCE, fast_kernels

    obs = load_observer(model)
    batch = Protocol(n_trials=2).trials(obs.system, "sinusoid")
    fast = observer_estimator(obs, compiler=Compiler(cache_dir=tmp_path, postprocess=fast_kernels))(batch.t, batch.y,
                                                                                                     batch.u)
    vm = observer_estimator(obs, compiler=None)(batch.t, batch.y, batch.u)
    assert np.max(np.abs(fast - vm) / (1 + np.abs(vm))) <= FUSED_TOLERANCE
