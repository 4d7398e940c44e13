"""C code of the observer step: compiles with gcc -std=c99 -Wall -Wextra -Werror at -O2 and at the
default flags (and -march=native where gcc has it), has no dynamic allocation, and matches the
CasADi VM through ca.external: bitwise with the axpy mat-vec kernels and the C library's exp/tanh,
within VECTOR_MATH_TOLERANCE with the vectorisable exp/tanh; the vector exp/tanh against numpy;
the mat-vec kernels' fallback for overlapping arrays; argument errors. The C main over CSV logs:
tests/test_c_main.py. Speed lives in kklcasadi.evaluation.bench.observer_step."""

import ctypes
import re
import shutil
import subprocess
import time

import casadi as ca
import numpy as np
import pytest
from conftest import assert_exp_tanh_ulps, write_signed_card

from kklcasadi.model import variants
from kklcasadi.model.files import load_model
from kklcasadi.observer.codegen import (
    C_FLAGS,
    DEFAULT_FLAGS,
    NATIVE_FLAGS,
    VECTOR_MATH_TOLERANCE,
    check_c_name,
    generate_c,
    vector_math_c,
)
from kklcasadi.observer.kkl import load_observer

GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc is not installed")
DT = 0.05
WARNINGS = ("-Wall", "-Wextra", "-Werror")
METHODS = variants.names()            # every registered variant, read from the table


def compile_c(sources, output, *extra, flags=C_FLAGS):
    """Compile with warnings as errors; return the wall time. Fails the test with gcc's output."""
    start = time.perf_counter()
    result = subprocess.run([GCC, *flags, *WARNINGS, *extra, *map(str, sources), "-o",
                             str(output), "-lm"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    return time.perf_counter() - start


def shared_library(files, tmp_path, flags=C_FLAGS):
    library = tmp_path / f"lib{files[0].stem}.so"
    return library, compile_c([files[0]], library, "-fPIC", "-shared", flags=flags)


def native_supported():
    result = subprocess.run([GCC, *NATIVE_FLAGS, "-x", "c", "-c", "-", "-o", "/dev/null"],
                            input="int x;\n", capture_output=True, text=True)
    return result.returncode == 0


def cpu_has_avx2(tmp_path):
    """Whether gcc targets x86 and this CPU has AVX2 (so the dispatched kernels run)."""
    probe = tmp_path / "probe.c"
    probe.write_text('#include <stdio.h>\nint main(void) {\n#if defined(__x86_64__)\n'
                     '  printf("%d", __builtin_cpu_supports("avx2") != 0);\n#else\n'
                     '  printf("0");\n#endif\n  return 0;\n}\n')
    compile_c([probe], tmp_path / "probe")
    return subprocess.run([str(tmp_path / "probe")], capture_output=True, text=True,
                          check=True).stdout == "1"


def c_work_sizes(library, function):
    """``(sz_arg, sz_res, sz_iw, sz_w)`` as the compiled ``<function>_work`` reports them."""
    lib = ctypes.CDLL(str(library))
    sizes = [ctypes.c_longlong() for _ in range(4)]
    assert getattr(lib, f"{function}_work")(*map(ctypes.byref, sizes)) == 0
    return [s.value for s in sizes]


def model(model_dir_factory, method, **kwargs):
    """A small random model; hidden widths 37 and 20 exercise full and partial output blocks."""
    kwargs.setdefault("window", 4)
    kwargs.setdefault("hidden", (37, 20))
    return load_observer(model_dir_factory(method, base=method == "curriculum", **kwargs))


def step_inputs(obs, rng, n=6):
    """Random step arguments, the later ones large enough to saturate tanh and the GRU gates."""
    for i in range(n):
        scale = (0.5, 3.0, 40.0)[i % 3]
        yield [scale * rng.normal(size=obs.step.size_in(k)) for k in range(obs.step.n_in())]


def assert_matches_vm(obs, library, name, tol):
    """The compiled step and decode against the CasADi VM: bitwise (tol=0) or within tol."""
    step = ca.external(f"{name}_step", str(library))
    decode = ca.external(f"{name}_decode", str(library))
    rng = np.random.default_rng(3)
    for args in step_inputs(obs, rng):
        pairs = list(zip(step(*args), obs.step(*args)))
        pairs.append((decode(*args[:2]), obs.decode(*args[:2])))
        for c_out, vm_out in pairs:
            c_out, vm_out = np.array(c_out), np.array(vm_out)
            if tol == 0:
                assert np.array_equal(c_out, vm_out), np.max(np.abs(c_out - vm_out))
            else:
                np.testing.assert_allclose(c_out, vm_out, rtol=tol, atol=tol)


# ----------------------------------------------------------------------------- the step in C

@needs_gcc
@pytest.mark.parametrize("method", METHODS)
def test_axpy_kernels_are_bitwise_the_vm(model_dir_factory, tmp_path, method):
    """matvec="axpy" (the default) with the C library's exp/tanh, at -O2 -Werror."""
    obs = model(model_dir_factory, method)
    files = generate_c(obs, tmp_path / "build", "kkl_obs", math="libm")
    assert [f.name for f in files] == ["kkl_obs.c", "kkl_obs.h", "kkl_obs_main.c"]
    source = files[0].read_text()
    assert not re.search(r"\b(malloc|calloc|realloc|alloca)\b", source)
    assert re.search(r"kklc_mv_37x\d+x1\(", source) and not re.search(r"\bkklc_v?tanh\(", source)
    assert not re.search(r"casadi_mtimes_dense\((?!x, )\w+, \d", source)  # only the fallbacks
    macros = dict(re.findall(r"#define KKL_OBS_(\w+) (\S+)\n", files[1].read_text()))
    assert {k: macros[k] for k in ("NX", "NU", "NY", "NZ", "WINDOW", "DT")} == {
        "NX": "2", "NU": "1", "NY": "1", "NZ": "5", "WINDOW": "4" if obs.variant.windowed else "1", "DT": "0.05"}
    library, _ = shared_library(files, tmp_path)
    assert [int(macros[k]) for k in ("SZ_ARG", "SZ_RES", "SZ_IW", "SZ_W")] == [
        max(a, b) for a, b in zip(c_work_sizes(library, "kkl_obs_step"),
                                  c_work_sizes(library, "kkl_obs_decode"))]
    step = ca.external("kkl_obs_step", str(library))
    assert step.name_in() == obs.step.name_in() and step.name_out() == obs.step.name_out()
    assert_matches_vm(obs, library, "kkl_obs", tol=0)


@needs_gcc
@pytest.mark.parametrize("method", METHODS)
def test_default_code_is_within_the_vector_math_tolerance(model_dir_factory, tmp_path, method):
    """The defaults (axpy kernels, vector exp/tanh) at DEFAULT_FLAGS -Werror."""
    obs = model(model_dir_factory, method)
    files = generate_c(obs, tmp_path, name="fast")
    code, libm = (re.sub(r"/\*.*?\*/", "", f.read_text(), flags=re.DOTALL)    # without comments
                  for f in (files[0], generate_c(obs, tmp_path / "libm", name="fast", math="libm")[0]))
    assert re.search(r"\btanh\(", libm)                  # the activations
    if method.startswith(("obs", "dyn")):                  # the GRU gates
        assert re.search(r"\bexp\(", libm)
    for function in ("tanh", "exp"):                       # every call of the libm build is vectorised
        called = re.search(rf"\b{function}\(", libm) is not None
        assert bool(re.search(rf"\bkklc_v{function}\(", code)) == called
        assert not re.search(rf"\b{function}\(", code)
    library, _ = shared_library(files, tmp_path, flags=DEFAULT_FLAGS)
    assert_matches_vm(obs, library, "fast", tol=VECTOR_MATH_TOLERANCE)


@needs_gcc
@pytest.mark.parametrize("method", ["obs", "dyn"])
def test_portable_version_is_bitwise_too(model_dir_factory, tmp_path, method):
    """-DKKLC_NO_DISPATCH (the C99 kernels only) and dispatch=False (no gcc extensions)."""
    obs = model(model_dir_factory, method)
    files = generate_c(obs, tmp_path / "a", "kkl_obs", math="libm")
    assert "KKLC_HAS_AVX2" in files[0].read_text()
    library, _ = shared_library(files, tmp_path, flags=(*DEFAULT_FLAGS, "-DKKLC_NO_DISPATCH"))
    assert_matches_vm(obs, library, "kkl_obs", tol=0)
    files = generate_c(obs, tmp_path / "b", "plain", dispatch=False)
    code = re.sub(r"/\*.*?\*/", "", files[0].read_text(), flags=re.DOTALL)
    assert "kklc_mv_" in code and not re.search(r"KKLC_DISPATCH|__builtin|avx2|kklc_v4", code)
    library, _ = shared_library(files, tmp_path, flags=DEFAULT_FLAGS)
    assert_matches_vm(obs, library, "plain", tol=VECTOR_MATH_TOLERANCE)


@needs_gcc
@pytest.mark.parametrize("options", [{"matvec": "casadi", "math": "libm"},
                                     {"matvec": "casadi", "math": "vector"}])
def test_casadi_loops_remain_available(model_dir_factory, tmp_path, options):
    obs = model(model_dir_factory, "obs")
    files = generate_c(obs, tmp_path, "ref", **options)
    assert "kklc_mv_" not in files[0].read_text()
    library, _ = shared_library(files, tmp_path, flags=DEFAULT_FLAGS)
    assert_matches_vm(obs, library, "ref", tol=0 if options["math"] == "libm"
                      else VECTOR_MATH_TOLERANCE)


@needs_gcc
@pytest.mark.parametrize("method", METHODS)
def test_native_build_is_still_bitwise(model_dir_factory, tmp_path, method):
    """-march=native (AVX2/AVX-512 where present) with -std=c99: no contraction, same bits."""
    if not native_supported():
        pytest.skip("gcc has no -march=native here")
    obs = model(model_dir_factory, method)
    files = generate_c(obs, tmp_path, "native", math="libm", flags=NATIVE_FLAGS)
    assert "gcc -std=c99 -O3 -march=native native.c native_main.c" in files[1].read_text()
    library, _ = shared_library(files, tmp_path, flags=NATIVE_FLAGS)
    assert_matches_vm(obs, library, "native", tol=0)


@needs_gcc
def test_kernels_fall_back_to_casadi_for_overlapping_arrays(model_dir_factory, tmp_path):
    """A kernel called with z overlapping x or y gives what CasADi's loops give (in place)."""
    obs = model(model_dir_factory, "autonomous")
    files = generate_c(obs, tmp_path, "ovl", math="libm")
    kernel = re.search(r"static void (kklc_mv_(\d+)x(\d+)x1)\(", files[0].read_text())
    name, nrow, ncol = kernel.group(1), int(kernel.group(2)), int(kernel.group(3))
    (tmp_path / "overlap.c").write_text(f"""#include <stdio.h>
#include <string.h>
#include "ovl.c"
#define NR {nrow}
#define NC {ncol}
int main(void) {{
  static double a[NR * NC + NR + NC], b[NR * NC + NR + NC];
  int i, offset, failures = 0;
  for (offset = 0; offset <= NR * NC + NC; offset += 7) {{
    for (i = 0; i < NR * NC + NR + NC; i++) a[i] = b[i] = 0.1 * ((i * 37) % 23) - 1.0;
    /* x = buffer, y right after it, z at offset: overlapping x, y or neither */
    {name}(a, a + NR * NC, a + offset);
    casadi_mtimes_dense(b, NR, NC, b + NR * NC, 1, b + offset, 0);
    failures += memcmp(a, b, sizeof a) != 0;
  }}
  printf("%d\\n", failures);
  return 0;
}}
""")
    binary = tmp_path / "overlap"
    compile_c([tmp_path / "overlap.c"], binary, f"-I{tmp_path}", flags=DEFAULT_FLAGS)
    assert subprocess.run([str(binary)], capture_output=True, text=True,
                          check=True).stdout.strip() == "0"


@needs_gcc
@pytest.mark.parametrize("isa", ["portable", "avx2"])
def test_vector_exp_and_tanh_against_numpy(tmp_path, isa):
    """Within 1 ulp (exp) and 3 ulp (tanh), NaN and infinities as the C library, every length;
    compiled for the baseline and (where the CPU has it) for AVX2, as the dispatch does."""
    if isa == "avx2" and not cpu_has_avx2(tmp_path):
        pytest.skip("no AVX2 here")
    (tmp_path / "vmath.c").write_text(
        "#include <math.h>\n#include <stdint.h>\n#include <stdio.h>\n#include <stdlib.h>\n"
        "#include <string.h>\n#define casadi_real double\n#define casadi_int long long int\n"
        + vector_math_c() + """
int main(int argc, char** argv) {
  long n = atol(argv[1]), i, j;
  double *x = malloc(n * sizeof *x), *e = malloc(n * sizeof *e), *t = malloc(n * sizeof *t);
  (void) argc;
  if (fread(x, sizeof *x, n, stdin) != (size_t) n) return 1;
  for (i = 0, j = 1; i < n; i += j, j = j % 67 + 1) {       /* runs of every length 1..67 */
    if (j > n - i) j = n - i;
    kklc_vexp(x + i, j, e + i);
    memcpy(t + i, x + i, j * sizeof *t);
    kklc_vtanh(t + i, j, t + i);                              /* in place */
  }
  fwrite(e, sizeof *e, n, stdout);
  fwrite(t, sizeof *t, n, stdout);
  return 0;
}
""")
    binary = tmp_path / "vmath"
    compile_c([tmp_path / "vmath.c"], binary,
              flags=(*DEFAULT_FLAGS, "-mavx2") if isa == "avx2" else DEFAULT_FLAGS)
    rng = np.random.default_rng(0)
    special = [0.0, -0.0, np.inf, -np.inf, np.nan, 709.78, 709.79, 710.0, -707.0, -708.5, -745.0,
               -745.2, -746.0, 5e-324, 1e-300, -1e-300, 19.06, 19.1, 20.0, -20.0, 0.3465, -0.3466]
    x = np.concatenate([rng.uniform(-1, 1, 20000), rng.uniform(-30, 30, 20000),
                        rng.uniform(-750, 750, 20000), rng.choice([-1, 1], 5000)
                        * 10.0 ** rng.uniform(-320, 0, 5000), special])
    out = subprocess.run([str(binary), str(x.size)], input=x.tobytes(), capture_output=True,
                         check=True).stdout
    got_exp, got_tanh = np.frombuffer(out, dtype=float).reshape(2, -1)
    assert_exp_tanh_ulps(x, got_exp, got_tanh)


# ----------------------------------------------------------------------------- sizes

@needs_gcc
def test_duffing_sized_decoder_keeps_its_weights_as_constant_arrays(model_dir_factory, tmp_path):
    """2-5-150-150-150-5/2 maps (the paper's Duffing size): MX layers with DM constants keep the
    C small (docs/design.md: SX scalarisation makes compile time explode). Measured: 648 C
    statements and 25.8 bytes of C per decoder weight; the same step expanded to SX writes
    139 183 statements, 71 bytes per weight. The compile time is printed (pytest -s), not asserted."""
    path = model_dir_factory("autonomous", hidden=(150, 150, 150))
    obs = load_observer(path)
    weights = sum(v.size for k, v in load_model(path).arrays.items() if k.startswith("decoder/"))
    files = generate_c(obs, tmp_path, name="duffing_obs")
    source = files[0].read_text()
    assert weights == 46516
    assert source.count(";") < 2000 and len(source) < 30 * weights
    library, seconds = shared_library(files, tmp_path, flags=DEFAULT_FLAGS)
    print(f"\ngcc {' '.join(DEFAULT_FLAGS)} of the step with a 150-unit 3-layer decoder: "
          f"{seconds:.2f} s, {files[0].stat().st_size / 1e6:.1f} MB of C")
    step = ca.external("duffing_obs_step", str(library))
    args = [np.full(obs.step.size_in(i), 0.3) for i in range(obs.step.n_in())]
    np.testing.assert_allclose(np.array(step(*args)[2]), np.array(obs.step(*args)[2]),
                               rtol=0, atol=VECTOR_MATH_TOLERANCE)


# ----------------------------------------------------------------------------- float32

# A floating constant of C without the float suffix (CasADi writes 2., 0.5, 5.0000000000000000e-01).
DOUBLE_LITERAL = re.compile(r"(?<![\w.])(?:\d+\.\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?|\d+[eE][+-]?\d+)(?![\w.f])")


@needs_gcc
@pytest.mark.parametrize("method", METHODS)
def test_float32_code_computes_in_single_precision(model_dir_factory, tmp_path, method):
    """precision="float32": float values, float constants and the C library's float functions, so that gcc's
    -Wdouble-promotion (a float promoted to double anywhere) finds nothing; the main example then gives the
    float64 estimates to float's rounding, not bitwise."""
    obs = model(model_dir_factory, method)
    files = generate_c(obs, tmp_path, "f32", precision="float32")
    code = re.sub(r"/\*.*?\*/", "", files[0].read_text(), flags=re.DOTALL)
    assert "#define casadi_real float" in code and "#define casadi_int int" in code
    assert not DOUBLE_LITERAL.search(code), DOUBLE_LITERAL.search(code)
    assert re.search(r"\btanhf\(", code) and not re.search(r"\b(tanh|exp|sqrt|fmax|fmin)\(", code)
    assert "precision='float32'" in files[1].read_text()
    binary = tmp_path / "f32"
    compile_c([files[0], files[2]], binary, "-Wdouble-promotion", flags=DEFAULT_FLAGS)
    rng = np.random.default_rng(0)
    t = 1000.0 + np.arange(60) * 0.05                               # late times: float would round them
    y = np.sin(1.3 * t)[:, None] + 0.1 * rng.normal(size=(60, 1))
    u = 0.8 * np.sign(np.sin(2.0 * t + 0.4))[:, None]
    text = "time,y1,u1\n" + "".join(",".join(repr(float(v)) for v in row) + "\n" for row in np.column_stack([t, y, u]))
    lines = subprocess.run([str(binary)], input=text, capture_output=True, text=True, check=True).stdout.splitlines()
    assert lines[0] == "time,x1,x2,status"
    out = np.loadtxt(lines[1:], delimiter=",")
    expected = obs.simulate(t, y, u).xhat
    np.testing.assert_array_equal(out[:, 0], t)                    # the times stay double
    assert np.all(out[:, 3] == 0)
    error = np.max(np.abs(out[:, 1:3] - expected))
    assert 0 < error <= 1e-4 * (1 + np.max(np.abs(expected))), error


def test_float32_refuses_the_double_only_options(model_dir_factory, tmp_path):
    obs = load_observer(model_dir_factory("autonomous"))
    for options, message in [({"precision": "float16"}, r"precision: expected one of \['float64', 'float32'\]"),
                             ({"precision": "float32", "math": "vector"}, r"math: expected 'libm' with precision"),
                             ({"precision": "float32", "dispatch": True}, r"dispatch: expected False with precision")]:
        with pytest.raises(ValueError, match=message):
            generate_c(obs, tmp_path, **options)
    assert not any(tmp_path.iterdir())


# ----------------------------------------------------------------------------- arguments

def test_refuses_to_overwrite_unless_asked(model_dir_factory, tmp_path):
    obs = load_observer(model_dir_factory("autonomous"))
    first = generate_c(obs, tmp_path)
    first[1].write_text("edited")
    with pytest.raises(FileExistsError, match=r"kkl_obs\.c: already exists; pass overwrite=True"):
        generate_c(obs, tmp_path)
    assert first[1].read_text() == "edited"
    assert generate_c(obs, tmp_path, overwrite=True) == first
    assert first[1].read_text() != "edited"


@pytest.mark.parametrize("name", ["1obs", "kkl-obs", "kkl obs", "int", "a__b", "obs_", "_obs",
                                  "", "ö"])
def test_rejects_names_that_are_not_c_identifiers(model_dir_factory, tmp_path, name):
    obs = load_observer(model_dir_factory("autonomous"))
    with pytest.raises(ValueError, match=r"name: expected a C identifier.*received"):
        generate_c(obs, tmp_path, name=name)
    assert not any(tmp_path.iterdir())


def test_rejects_a_file_as_out_dir_and_bad_argument_types(model_dir_factory, tmp_path):
    obs = load_observer(model_dir_factory("autonomous"))
    target = tmp_path / "file.txt"
    target.write_text("")
    with pytest.raises(ValueError, match=r"out_dir: expected a directory.*file\.txt.*is a file"):
        generate_c(obs, target)
    with pytest.raises(TypeError, match="name: expected a string"):
        generate_c(obs, tmp_path, name=3)
    with pytest.raises(TypeError, match="out_dir: expected a path"):
        generate_c(obs, None)
    assert check_c_name("kkl_obs2") == "kkl_obs2"


@pytest.mark.parametrize("options, error, message", [
    ({"matvec": "fast"}, ValueError, r"matvec: expected one of \['axpy', 'casadi'\], received 'fast'"),
    ({"matvec": None}, ValueError, r"matvec: expected one of .*received None"),
    ({"math": "fast"}, ValueError, r"math: expected one of \['vector', 'libm'\], received 'fast'"),
    ({"dispatch": "yes"}, TypeError, r"dispatch: expected a bool, received str"),
    ({"flags": "-O3"}, TypeError, r"flags: expected a sequence of strings.*received str"),
    ({"flags": 3}, TypeError, r"flags: expected a sequence of strings.*received int"),
    ({"flags": ["O3"]}, ValueError, r"flags: expected compiler options .*received 'O3'"),
    ({"flags": ["-O3", "-march=native -g"]}, ValueError, r"flags: .*received '-march=native -g'"),
    ({"flags": ["-O3", 2]}, ValueError, r"flags: .*received 2"),
    ({"y_cols": "y"}, TypeError, r"^y_cols: expected a sequence of 1 column names, received str"),
    ({"y_cols": ("a", "b")}, ValueError, r"^y_cols: expected 1 column names, received \['a', 'b'\]"),
    ({"u_cols": ("a,b",)}, ValueError, r"^u_cols: expected names of printable ASCII characters without commas"),
    ({"time_col": "t\"s"}, ValueError, r"^time_col: expected names of printable ASCII"),
    ({"time_col": " t"}, ValueError, r"^time_col: expected names .* no blanks at either end"),
    ({"state_names": ("a", "\u00e9")}, ValueError, r"^state_names: expected names of printable ASCII"),
    ({"state_names": ("x", "x")}, ValueError, r"^state_names: expected distinct names other than 'time'"),
    ({"state_names": ("x", "status")}, ValueError, r"^state_names: expected distinct names other than"),
    ({"y_cols": ("time",)}, ValueError, r"^time_col, y_cols, u_cols: expected distinct column names, received "
                                        r"\['time', 'time', 'u1'\]"),
    ({"u_cols": ("a??/",)}, ValueError, r"^u_cols: expected names .* or '\?\?'"),
    ({"y_cols": ("#y",)}, ValueError, r"^y_cols: expected names .* no '#' first"),
])
def test_rejects_bad_code_options(model_dir_factory, tmp_path, options, error, message):
    obs = load_observer(model_dir_factory("autonomous"))
    with pytest.raises(error, match=message):
        generate_c(obs, tmp_path / "out", **options)
    assert not (tmp_path / "out").exists()


def test_vector_math_c_rejects_unknown_functions():
    assert "kklc_vtanh" in vector_math_c(["tanh"]) and "kklc_vexp" not in vector_math_c(["tanh"])
    with pytest.raises(ValueError, match=r"functions: expected one of \['exp', 'tanh'\], "
                                         r"received 'log'"):
        vector_math_c(["log"])
    with pytest.raises(TypeError, match="functions: expected a sequence.*received str"):
        vector_math_c("tanh")


def test_flags_go_into_the_build_lines(model_dir_factory, tmp_path):
    obs = load_observer(model_dir_factory("autonomous"))
    files = generate_c(obs, tmp_path, "flagged", flags=["-std=c99", "-O2", "-funroll-loops"])
    build = "gcc -std=c99 -O2 -funroll-loops flagged.c flagged_main.c -lm -o flagged"
    assert build in files[1].read_text() and build in files[2].read_text()
    assert "matvec='axpy', math='vector', dispatch=True" in files[1].read_text()


def _printed_ratios(out, runs):
    """``(printed, recomputed)`` for every ratio line of the observer-step benchmark."""
    per_step = {t.label: t.seconds / t.items for t in runs}
    pairs = []
    for base, ratio, label in re.findall(r"^(.+?) is ([\d.]+)x as fast as .+? \((.+)\)$", out, re.M):
        pairs.append((float(ratio), per_step[label] / per_step[base]))
    for c_label, ratio, hand in re.findall(r"^(.+?) takes ([\d.]+)x the time of (.+)$", out, re.M):
        pairs.append((float(ratio), per_step[c_label] / per_step[hand]))
    return pairs


@needs_gcc
def test_bench_observer_step_checks_every_implementation_and_prints_their_ratios(model_dir_factory, capsys):
    """Every implementation is timed and checked against the VM (C within the vector-math
    tolerance, torch within 1e-9); the printed ratios are those of the returned times."""
    pytest.importorskip("torch")
    from kklcasadi.evaluation.bench.observer_step import bench_observer_step

    timings = bench_observer_step(model_dir_factory("autonomous", window=4), n_calls=3, repeat=1,
                                  callgrind=False)
    compile_time, runs = timings[0], timings[1:]
    assert compile_time.label.startswith("gcc ") and compile_time.items == 1
    labels = [t.label for t in runs]
    for prefix in ("C default, -std=c99 -O3", "C portable", "C math=libm (bitwise)", "C as CasADi writes it",
                   "hand-written dense C, vector tanh", "hand-written dense C, libm tanh",
                   "C default via ca.external", "CasADi VM", "torch eager (1 thread)", "torch.jit.trace"):
        assert any(label.startswith(prefix) for label in labels), prefix
    c_loops = [t for t in runs if t.label.startswith(("C default,", "C portable", "C math", "C as", "hand"))]
    assert all(t.items == 3 for t in c_loops) and all(t.items == 3 for t in runs)
    out = capsys.readouterr().out
    checks = dict(re.findall(r"^(.+?) +max \|difference\| from the CasADi VM: (\S+)$", out, re.M))
    assert sorted(checks) == ["C default (ca.external)", "torch eager", "torch.jit.trace"]
    assert float(checks["C default (ca.external)"]) <= VECTOR_MATH_TOLERANCE
    assert float(checks["torch eager"]) <= 1e-9 and float(checks["torch.jit.trace"]) <= 1e-9
    pairs = _printed_ratios(out, runs)
    assert len(pairs) == 2 + (3 if native_supported() else 2)    # 2 torch summaries, the hand-written limits
    for printed, recomputed in pairs:
        assert printed == pytest.approx(recomputed, abs=0.005 + 1e-12)


@needs_gcc
def test_bench_observer_step_refuses_an_implementation_that_disagrees(model_dir_factory, monkeypatch):
    """A torch step that is off by 1e-6 is not timed: the timings would compare different functions."""
    pytest.importorskip("torch")
    from kklcasadi.evaluation.bench import observer_step
    from kklcasadi.evaluation.bench.observer_step import bench_observer_step
    from kklcasadi.train import step as torch_steps

    exact = torch_steps.torch_step

    def off_by_a_little(obs):
        step = exact(obs)
        return lambda *args: tuple(out + 1e-6 if i == 2 else out for i, out in enumerate(step(*args)))

    monkeypatch.setattr(torch_steps, "torch_step", off_by_a_little)
    monkeypatch.setattr(observer_step.shutil, "which", lambda name: None)     # no gcc: straight to torch
    with pytest.raises(RuntimeError, match=r"torch eager: the step differs from the CasADi VM by 1e-06"):
        bench_observer_step(model_dir_factory("autonomous", window=4), n_calls=1, repeat=1, callgrind=False)


@needs_gcc
@pytest.mark.parametrize("method", ["obs_stream", "dyn_stream", "bank"])
def test_bench_observer_step_takes_every_memory_shape(model_dir_factory, capsys, method):
    """Streaming and feedthrough memories (not a window) are benchmarked and checked like windows."""
    pytest.importorskip("torch")
    from kklcasadi.evaluation.bench.observer_step import bench_observer_step

    runs = bench_observer_step(model_dir_factory(method), n_calls=2, repeat=1, callgrind=False)[1:]
    assert any(t.label.startswith("C default") for t in runs)
    out = capsys.readouterr().out
    checks = dict(re.findall(r"^(.+?) +max \|difference\| from the CasADi VM: (\S+)$", out, re.M))
    assert float(checks["C default (ca.external)"]) <= VECTOR_MATH_TOLERANCE
    if method == "bank":
        assert "torch: skipped (the 'bank' variant has no torch step)" in out
        assert sorted(checks) == ["C default (ca.external)"]
    else:
        assert float(checks["torch eager"]) <= 1e-9 and float(checks["torch.jit.trace"]) <= 1e-9
    pairs = _printed_ratios(out, runs)
    assert len(pairs) == (0 if method == "bank" else 2)         # no hand-written limit for these
    for printed, recomputed in pairs:
        assert printed == pytest.approx(recomputed, abs=0.005 + 1e-12)


# ----------------------------------------------------------------------------- domain monitor in C

@needs_gcc
def test_the_domain_monitor_is_an_optional_c_function(model_dir_factory, tmp_path, rng):
    """A model that records its training domain gets ``name_in_domain`` (and ``NAME_HAS_DOMAIN``),
    equal to the observer's ``domain_check`` inside, outside and on the widened edges."""
    import json

    path = model_dir_factory("autonomous")
    plain = generate_c(load_observer(path), tmp_path / "plain", "plain")
    assert "plain_in_domain" not in plain[0].read_text() and "HAS_DOMAIN" not in plain[1].read_text()
    card = json.loads((path / "card.json").read_text())
    card["domain"] = {"x_lo": [-1, -2], "x_hi": [1, 2], "z_lo": [-3] * 5, "z_hi": [3] * 5}
    write_signed_card(path, card)
    obs = load_observer(path)
    files = generate_c(obs, tmp_path / "build", "mon")
    assert "#define MON_HAS_DOMAIN 1" in files[1].read_text()
    library, _ = shared_library(files, tmp_path)
    check = ca.external("mon_in_domain", str(library))
    points = [(rng.uniform(-1.5, 1.5, 2) * [1, 2], rng.uniform(-4, 4, 5)) for _ in range(200)]
    points += [(np.array([1.19, 0.0]), np.zeros(5)), (np.array([1.21, 0.0]), np.zeros(5))]
    w = np.zeros(obs.memory_shape)
    flags = [float(check(z, w, x)) for x, z in points]
    assert flags == [float(obs.domain_check(z, w, x)) for x, z in points]
    assert flags[-2:] == [1.0, 0.0] and 0 < sum(flags) < len(points) - 1


@needs_gcc
def test_float32_benchmark_writes_its_report_whole_and_never_over_a_file(model_dir_factory, tmp_path, monkeypatch,
                                                                         capsys):
    """benchmarks/float32_c.py on one trial per regime: the report (float32 within 1e-5 of a state's range), a
    second run to the same --out refused before any work, a write that fails leaves no file, not even a part."""
    import os
    import runpy
    import sys
    from pathlib import Path

    from kklcasadi import provenance

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "float32_c.py"
    model = model_dir_factory("inject")

    def run(out):
        monkeypatch.setattr(sys, "argv", [str(script), str(model), "--trials", "1", "--out", str(out)])
        runpy.run_path(str(script), run_name="__main__")

    out = tmp_path / "f32.md"
    run(out)
    text = provenance.strip_markdown(out.read_text())
    assert [line.split(" |")[0] for line in text.splitlines() if line.startswith("| ") and "regime" not in line] \
        == ["| zero", "| constant", "| sinusoid", "| square"]
    assert float(re.search(r"Largest difference over a state's range: (\S+)\.", text).group(1)) < 1e-5
    assert provenance.read(out).seeds == {"protocol": 2026}
    first = out.read_bytes()
    capsys.readouterr()
    with pytest.raises(FileExistsError, match="^--out: .*f32.md exists and this command does not overwrite"):
        run(out)
    assert capsys.readouterr().out == "" and out.read_bytes() == first          # refused before any trial

    def failing(fd):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", failing)
    with pytest.raises(OSError, match="disk full"):
        run(tmp_path / "again.md")
    assert [p.name for p in tmp_path.iterdir()] == ["f32.md"]
