"""C code of the observer step: compiles with gcc -std=c99 -Wall -Wextra -Werror -O2, has no
dynamic allocation, matches the in-memory Functions through ca.external (1e-12), and the
standalone main example reproduces KKLObserver.simulate from a CSV; argument errors."""

import ctypes
import re
import shutil
import subprocess
import time

import casadi as ca
import numpy as np
import pytest

from kklcasadi.codegen import C_FLAGS, check_c_name
from kklcasadi.observer import load_observer

GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc is not installed")
DT = 0.05


def compile_c(sources, output, *extra):
    """Compile with the tested flags; return the wall time. Fails the test with gcc's output."""
    start = time.perf_counter()
    result = subprocess.run([GCC, *C_FLAGS, *extra, *map(str, sources), "-o", str(output), "-lm"],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    return time.perf_counter() - start


def shared_library(files, tmp_path):
    library = tmp_path / "libobs.so"
    return library, compile_c([files[0]], library, "-fPIC", "-shared")


def c_work_sizes(library, function):
    """``(sz_arg, sz_res, sz_iw, sz_w)`` as the compiled ``<function>_work`` reports them."""
    lib = ctypes.CDLL(str(library))
    sizes = [ctypes.c_longlong() for _ in range(4)]
    assert getattr(lib, f"{function}_work")(*map(ctypes.byref, sizes)) == 0
    return [s.value for s in sizes]


def trajectory(n=40, trials=1, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    y = np.sin(1.3 * t)[:, None] + 0.1 * rng.normal(size=(n, 1))
    u = 0.8 * np.sign(np.sin(2.0 * t + 0.4))[:, None]
    return t, y, u


@needs_gcc
@pytest.mark.parametrize("method", ["autonomous", "obs", "dyn", "inject"])
def test_generated_c_compiles_and_matches_the_functions(model_dir_factory, tmp_path, method):
    obs = load_observer(model_dir_factory(method, window=4))
    files = obs.generate_c(tmp_path / "build", name="kkl_obs")
    assert [f.name for f in files] == ["kkl_obs.c", "kkl_obs.h", "kkl_obs_main.c"]
    source = files[0].read_text()
    assert not re.search(r"\b(malloc|calloc|realloc|alloca)\b", source)
    macros = dict(re.findall(r"#define KKL_OBS_(\w+) (\S+)\n", files[1].read_text()))
    assert {k: macros[k] for k in ("NX", "NU", "NY", "NZ", "WINDOW", "DT")} == {
        "NX": "2", "NU": "1", "NY": "1", "NZ": "5", "WINDOW": "4", "DT": "0.05"}
    library, _ = shared_library(files, tmp_path)
    step = ca.external("kkl_obs_step", str(library))
    decode = ca.external("kkl_obs_decode", str(library))
    assert [int(macros[k]) for k in ("SZ_ARG", "SZ_RES", "SZ_IW", "SZ_W")] == [
        max(a, b) for a, b in zip(c_work_sizes(library, "kkl_obs_step"),
                                  c_work_sizes(library, "kkl_obs_decode"))]
    assert step.name_in() == obs.step.name_in() and step.name_out() == obs.step.name_out()
    rng = np.random.default_rng(3)
    for _ in range(3):
        args = [rng.normal(size=obs.step.size_in(i)) for i in range(obs.step.n_in())]
        for c_out, vm_out in zip(step(*args), obs.step(*args)):
            np.testing.assert_allclose(np.array(c_out), np.array(vm_out), rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.array(decode(*args[:2])), np.array(obs.decode(*args[:2])),
                                   rtol=0, atol=1e-12)


@needs_gcc
@pytest.mark.parametrize("method", ["obs", "inject"])
def test_main_example_reproduces_simulate(model_dir_factory, tmp_path, method):
    obs = load_observer(model_dir_factory(method, window=4))
    files = obs.generate_c(tmp_path, name="observer")
    binary = tmp_path / "observer"
    compile_c([files[0], files[2]], binary)
    t, y, u = trajectory()
    expected = obs.simulate(t, y, u)
    rows = np.column_stack([t, y, u])
    csv = tmp_path / "samples.csv"
    csv.write_text("t,y0,u0\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in rows) + "\n")
    from_file = subprocess.run([str(binary), str(csv)], capture_output=True, text=True, check=True)
    from_stdin = subprocess.run([str(binary)], input=csv.read_text(), capture_output=True,
                                text=True, check=True)
    assert from_file.stdout == from_stdin.stdout
    out = np.loadtxt(from_file.stdout.splitlines(), delimiter=",")
    assert out.shape == (t.size, 3)
    np.testing.assert_array_equal(out[:, 0], t)
    np.testing.assert_allclose(out[:, 1:], expected.xhat, rtol=0, atol=1e-12)


@needs_gcc
def test_two_inputs_and_outputs(model_dir_factory, mimo_plant, tmp_path):
    obs = load_observer(model_dir_factory("obs", system=mimo_plant, window=3), system=mimo_plant)
    files = obs.generate_c(tmp_path, name="mimo")
    binary = tmp_path / "mimo"
    compile_c([files[0], files[2]], binary)
    rng = np.random.default_rng(2)
    t, y, u = np.arange(20) * DT, rng.normal(size=(20, 2)), rng.normal(size=(20, 2))
    text = "\n".join(" ".join(repr(float(v)) for v in row) for row in np.column_stack([t, y, u]))
    result = subprocess.run([str(binary)], input=text, capture_output=True, text=True, check=True)
    out = np.loadtxt(result.stdout.splitlines(), delimiter=",")
    np.testing.assert_allclose(out[:, 1:], obs.simulate(t, y, u).xhat, rtol=0, atol=1e-12)


@needs_gcc
def test_main_example_rejects_bad_lines(model_dir_factory, tmp_path):
    files = load_observer(model_dir_factory("autonomous")).generate_c(tmp_path, name="obs")
    binary = tmp_path / "obs"
    compile_c([files[0], files[2]], binary)
    for text, message in [("0,0.1,0\n0.05,nan,0\n", "line 2 (sample 1): value 2 is not finite"),
                          ("0,0.1\n", "line 1: expected 3 numbers"),
                          ("0,0.1,0,4\n", "line 1: expected 3 numbers"),
                          ("0,0.1,0\n0.05,abc,0\n", "line 2: expected 3 numbers")]:
        result = subprocess.run([str(binary)], input=text, capture_output=True, text=True)
        assert result.returncode == 1 and message in result.stderr, (text, result.stderr)


@needs_gcc
def test_duffing_sized_decoder_compiles_in_seconds(model_dir_factory, tmp_path):
    """2-5-150-150-150-5/2 maps (the paper's Duffing size): MX layers with DM constants keep the
    C small; the compile time is printed (run pytest -s to see it), not asserted."""
    obs = load_observer(model_dir_factory("autonomous", hidden=(150, 150, 150)))
    files = obs.generate_c(tmp_path, name="duffing_obs")
    library, seconds = shared_library(files, tmp_path)
    print(f"\ngcc -O2 of the step with a 150-unit 3-layer decoder: {seconds:.2f} s, "
          f"{files[0].stat().st_size / 1e6:.1f} MB of C")
    step = ca.external("duffing_obs_step", str(library))
    args = [np.full(obs.step.size_in(i), 0.3) for i in range(obs.step.n_in())]
    np.testing.assert_allclose(np.array(step(*args)[2]), np.array(obs.step(*args)[2]),
                               rtol=0, atol=1e-12)


def test_refuses_to_overwrite_unless_asked(model_dir_factory, tmp_path):
    obs = load_observer(model_dir_factory("autonomous"))
    first = obs.generate_c(tmp_path)
    first[1].write_text("edited")
    with pytest.raises(FileExistsError, match=r"kkl_obs\.c: already exists; pass overwrite=True"):
        obs.generate_c(tmp_path)
    assert first[1].read_text() == "edited"
    assert obs.generate_c(tmp_path, overwrite=True) == first
    assert first[1].read_text() != "edited"


@pytest.mark.parametrize("name", ["1obs", "kkl-obs", "kkl obs", "int", "a__b", "obs_", "_obs",
                                  "", "ö"])
def test_rejects_names_that_are_not_c_identifiers(model_dir_factory, tmp_path, name):
    obs = load_observer(model_dir_factory("autonomous"))
    with pytest.raises(ValueError, match=r"name: expected a C identifier.*received"):
        obs.generate_c(tmp_path, name=name)
    assert not any(tmp_path.iterdir())


def test_rejects_a_file_as_out_dir_and_bad_argument_types(model_dir_factory, tmp_path):
    obs = load_observer(model_dir_factory("autonomous"))
    target = tmp_path / "file.txt"
    target.write_text("")
    with pytest.raises(ValueError, match=r"out_dir: expected a directory.*file\.txt.*is a file"):
        obs.generate_c(target)
    with pytest.raises(TypeError, match="name: expected a string"):
        obs.generate_c(tmp_path, name=3)
    with pytest.raises(TypeError, match="out_dir: expected a path"):
        obs.generate_c(None)
    assert check_c_name("kkl_obs2") == "kkl_obs2"


@needs_gcc
def test_bench_observer_step_runs_once(model_dir_factory, capsys):
    pytest.importorskip("torch")
    from kklcasadi.bench_observer import bench_observer_step

    timings = bench_observer_step(model_dir_factory("obs", window=4), n_calls=20, repeat=1)
    labels = [t.label for t in timings]
    assert any("C" in label for label in labels) and any("torch" in label for label in labels)
    assert all(t.seconds > 0 for t in timings)
    assert "ratio" in capsys.readouterr().out
