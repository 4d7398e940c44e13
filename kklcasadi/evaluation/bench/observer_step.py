"""Benchmark of one observer step: generated C, a hand-written C limit, the CasADi VM and torch.

:func:`bench_observer_step` times :attr:`KKLObserver.step` (one sample interval: latent update
and decoder) on the same inputs as

* the generated C (:func:`kklcasadi.observer.codegen.generate_c`) in a standalone C loop (the deployment
  cost): the default code (axpy kernels, vector exp/tanh, AVX2 dispatch) at the default flags
  and at ``-march=native``; the portable version alone (``-DKKLC_NO_DISPATCH``), also with the
  C library's exp/tanh (``math="libm"``, bitwise the VM); and CasADi's own code at ``-O2``
  (what ``generate_c`` wrote before). The default build also through ``ca.external`` (adds the
  Python call overhead);
* for the linear observers (``autonomous``, ``curriculum``: the exact step plus the decoder), a
  hand-written dense C loop of the same network (the limit: column order, ``restrict``),
  compiled with the same flags and instruction set and with the same ``tanh`` as the
  generated build it is compared with;
* the CasADi virtual machine (``Function.call``);
* torch (float64, batch 1, no autograd) at its best: eager at 1 thread and at torch's default
  thread count, the same step traced with TorchScript (``torch.jit.trace``), and optionally
  ``torch.compile``; the window GRU of ``obs`` and ``dyn`` is a plain ``torch.nn.GRU`` with the
  model's bias-free weights (not the Python loop over the window that training uses);

checks that every implementation returns the CasADi VM's result, and prints absolute times, the
``valgrind --tool=callgrind`` instruction counts of the C loops (repeatable on a loaded machine;
not for ``-march=native`` builds, which valgrind may not decode) and ratios. A time is the best
of ``repeat`` short runs (about 2 ms each), the implementations taking turns, so that on a
shared machine every one gets its share of undisturbed runs; torch at more than one thread runs
last, alone (its idle workers spin and would slow what follows). Nothing here asserts a speed.
Torch is imported inside the functions only.

Over 600 lines: one benchmark; its C builds (generated and hand-written), timed loops, torch cases and
table share the cases, the interleaved timing and the checks against the VM. The hand-written C limit
(``_hand_written`` and the loop source) is the part that could leave for a module of its own.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import tempfile
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import casadi as ca
import numpy as np

from ...nets.specs import DECODER
from ...observer.codegen import (
    DEFAULT_FLAGS,
    NATIVE_FLAGS,
    VECTOR_MATH_TOLERANCE,
    check_flags,
    generate_c,
    vector_math_c,
)
from ...observer.kkl import KKLObserver, load_observer
from ...plant.systems import System
from . import Timing

__all__ = ["bench_observer_step", "card_digest", "step_table", "STEP_COLUMNS"]

_NAME = "kkl_bench"
#: Turns the C loops take (each with ``repeat // _ROUNDS`` runs).
_ROUNDS = 5
#: Length of one timed run when ``n_calls`` is not given: short, so that on a loaded machine some
#: runs of every implementation fall between interruptions.
_RUN_SECONDS = 0.002
#: The timing loop of a CasADi-style ``NAME_step``: ``__DECLS__`` its buffers, ``__INIT__`` their
#: values and ``arg``/``res``, ``__FEEDBACK__`` the copies of outputs back to inputs after each step,
#: ``__STATE__`` the buffer summed into the checksum (:func:`loop_source`).
_LOOP = r"""#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "__NAME__.h"

__DECLS__
static const casadi_real* arg[__MACRO___SZ_ARG + 1];
static casadi_real* res[__MACRO___SZ_RES + 1];
static casadi_int iw[__MACRO___SZ_IW + 1];
static casadi_real work[__MACRO___SZ_W + 1];

/* Usage: loop STEPS RUNS. Prints the fastest run's seconds per step and a checksum. */
int main(int argc, char** argv) {
  long i, r, n = argc > 1 ? atol(argv[1]) : 1000, runs = argc > 2 ? atol(argv[2]) : 1;
  struct timespec t0, t1;
  double checksum = 0, best = -1, seconds;
__INIT__
  for (r = 0; r < runs; r++) {
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (i = 0; i < n; i++) {
      if (__NAME___step(arg, res, iw, work, 0)) return 1;
__FEEDBACK__
      checksum += __STATE__[0];
    }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    seconds = ((t1.tv_sec - t0.tv_sec) + 1e-9 * (t1.tv_nsec - t0.tv_nsec)) / n;
    if (best < 0 || seconds < best) best = seconds;
  }
  printf("%.9e %.17g\n", best, checksum);
  return 0;
}
"""
#: The observer step's buffers: ``(z, w, y, y_next, u_next) -> (z_next, w_next, xhat)`` (and the covariance ``P``
#: where the model has a covariance head, and its inflation's state ``m`` where it has one), the latent and the window
#: (and ``m``) fed back.
_OBSERVER_DECLS = ("static casadi_real z[__MACRO___NZ], z_next[__MACRO___NZ];",
                   "static casadi_real win[__MACRO___NW], win_next[__MACRO___NW];",
                   "static casadi_real y[__MACRO___NY], y_next[__MACRO___NY], u_next[__MACRO___NU],",
                   "                   xhat[__MACRO___NX];",
                   "#ifdef __MACRO___HAS_COVARIANCE",
                   "static casadi_real P[__MACRO___NX * __MACRO___NX];    /* the step's covariance output */",
                   "#endif",
                   "#ifdef __MACRO___HAS_INFLATION",
                   "static casadi_real m[__MACRO___NM] = __MACRO___M0, m_next[__MACRO___NM];  /* inflation's state */",
                   "#endif")
_OBSERVER_INIT = ("  for (i = 0; i < __MACRO___NW; i++) win[i] = 0.3 * ((i % 7) - 3) / 3.0;",
                  "  for (i = 0; i < __MACRO___NY; i++) { y[i] = 0.2; y_next[i] = 0.25; }",
                  "  for (i = 0; i < __MACRO___NU; i++) u_next[i] = -0.4;",
                  "  arg[0] = z; arg[1] = win; arg[2] = y; arg[3] = y_next; arg[4] = u_next;",
                  "  res[0] = z_next; res[1] = win_next; res[2] = xhat;",
                  "#ifdef __MACRO___HAS_COVARIANCE",
                  "  res[3] = P;",
                  "#endif",
                  "#ifdef __MACRO___HAS_INFLATION",
                  "  arg[5] = m; res[4] = m_next;",
                  "#endif")
_OBSERVER_FEEDBACK = ("      memcpy(z, z_next, sizeof z);", "      memcpy(win, win_next, sizeof win);",
                      "#ifdef __MACRO___HAS_INFLATION",
                      "      memcpy(m, m_next, sizeof m);",
                      "#endif")


def loop_source(name: str, decls: Sequence[str] = _OBSERVER_DECLS, init: Sequence[str] = _OBSERVER_INIT,
                feedback: Sequence[str] = _OBSERVER_FEEDBACK, state: str = "xhat") -> str:
    """The C timing loop (:data:`_LOOP`) of ``name_step`` with these buffers; the defaults time an
    observer step (``name.h`` defines ``NAME_NZ``, ``NAME_NW``, ``NAME_NY``, ``NAME_NU``, ``NAME_NX``)."""
    return (_LOOP.replace("__DECLS__", "\n".join(decls)).replace("__INIT__", "\n".join(init))
            .replace("__FEEDBACK__", "\n".join(feedback)).replace("__STATE__", state)
            .replace("__NAME__", name).replace("__MACRO__", name.upper()))


# The hand-written limit for the linear observers: z_next = Ad z + Gy y + Gy_next y_next, the
# window shifted by one, xhat = decoder(z_next); dense layers in column (axpy) order.
_HAND = r"""#include <math.h>
#include <stdint.h>
#include <string.h>

#include "__NAME__.h"
__MATH__
__CONSTANTS__
static void dense(const double* restrict w, const double* restrict b, const double* restrict v,
                  double* restrict out, int n_out, int n_in, int act) {
  int j, k;
  for (j = 0; j < n_out; j++) out[j] = 0;
  for (k = 0; k < n_in; k++) {
    const double vk = v[k];
    const double* restrict wk = w + k * n_out;
    for (j = 0; j < n_out; j++) out[j] += wk[j] * vk;
  }
  for (j = 0; j < n_out; j++) out[j] += b[j];
  if (act) __TANH__
}

int __NAME___step(const double** arg, double** res, long long* iw, double* w, int mem) {
  static double v0[__WIDTH__], v1[__WIDTH__];
  const double *z = arg[0], *win = arg[1], *y = arg[2], *y_next = arg[3], *u_next = arg[4];
  double *z_next = res[0], *win_next = res[1];
  int i, j;
  (void) iw; (void) w; (void) mem;
  for (i = 0; i < __NZ__; i++) {
    double s = 0;
    for (j = 0; j < __NZ__; j++) s += AD[i + j * __NZ__] * z[j];
    for (j = 0; j < __NY__; j++) s += GY[i + j * __NZ__] * y[j];
    for (j = 0; j < __NY__; j++) s += GYN[i + j * __NZ__] * y_next[j];
    z_next[i] = s;
  }
  for (j = 0; j < __NU__; j++) {
    for (i = 0; i + 1 < __WINDOW__; i++) win_next[i + j * __WINDOW__] = win[i + 1 + j * __WINDOW__];
    win_next[__WINDOW__ - 1 + j * __WINDOW__] = u_next[j];
  }
__LAYERS__  return 0;
}
"""


@dataclass(frozen=True)
class _CBuild:
    """One C implementation to time: its label, sources and flags."""

    label: str
    sources: tuple[Path, ...]
    flags: tuple[str, ...]


def _c_array(name: str, values: np.ndarray) -> str:
    flat = ", ".join(repr(float(v)) for v in np.asarray(values, dtype=float).ravel(order="F"))
    return f"static const double {name}[{max(values.size, 1)}] = {{{flat}}};\n"


def _decoder_layers(arrays: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """The decoder's ``(W, b)`` with the input and output normalisation folded in, as the export
    folds them (``docs/model-format.md`` names)."""
    def array(name: str) -> np.ndarray:
        return np.asarray(arrays[f"{DECODER}/{name}"], dtype=np.float64)

    n_layers = sum(1 for key in arrays if re.fullmatch(rf"{DECODER}/W\d+", key))
    weights = [array(f"W{i}") for i in range(n_layers)]
    biases = [array(f"b{i}") for i in range(n_layers)]
    in_std, out_std = array("in_std"), array("out_std")
    biases[0] = biases[0] - weights[0] @ (array("in_mean") / in_std)
    weights[0] = weights[0] / in_std[None, :]
    weights[-1] = out_std[:, None] * weights[-1]
    biases[-1] = out_std * biases[-1] + array("out_mean")
    return list(zip(weights, biases))


def _hand_written(observer: KKLObserver, build: Path, math: str) -> Optional[tuple[Path, Path]]:
    """Write the hand-written dense C step of a linear observer with a tanh decoder without a skip path
    (None for other observers)."""
    decoder = observer.model.spec.architecture.decoder
    if (not observer.variant.input_free or observer.foh_matrices is None or decoder.activation != "tanh"
            or decoder.skip):
        return None
    layers = _decoder_layers(observer.model.arrays)
    m = observer.foh_matrices
    ad, gy, gy_next = m.Ad, m.Gy, m.Gy_next
    constants = [_c_array("AD", ad), _c_array("GY", gy), _c_array("GYN", gy_next)]
    calls, source = [], "z_next"
    for i, (weight, bias) in enumerate(layers):
        constants += [_c_array(f"W{i}", weight), _c_array(f"B{i}", bias)]
        target = "res[2]" if i == len(layers) - 1 else ("v0", "v1")[i % 2]
        calls.append(f"  dense(W{i}, B{i}, {source}, {target}, {weight.shape[0]}, "
                     f"{weight.shape[1]}, {int(i < len(layers) - 1)});\n")
        source = target
    if math == "vector":
        math_code, tanh = vector_math_c(["tanh"]), "kklc_vtanh(out, n_out, out);"
    else:
        math_code, tanh = "", "for (j = 0; j < n_out; j++) out[j] = tanh(out[j]);"
    name = f"{_NAME}_hand_{math}"
    sizes = {"NZ": observer.nz, "NY": observer.ny, "NU": observer.nu, "NX": observer.nx,
             "WINDOW": observer.window, "NW": observer.window * observer.nu}
    source_code = (_HAND.replace("__MATH__", math_code)
                   .replace("__CONSTANTS__", "".join(constants)).replace("__TANH__", tanh)
                   .replace("__LAYERS__", "".join(calls))
                   .replace("__WIDTH__", str(max(w.shape[0] for w, _ in layers))))
    for key, value in sizes.items():
        source_code = source_code.replace(f"__{key}__", str(value))
    source_code = source_code.replace("__NAME__", name)
    macro = name.upper()
    header = "".join(f"#define {macro}_{key} {value}\n" for key, value in sizes.items())
    header += "".join(f"#define {macro}_{key} {value}\n" for key, value in
                      (("SZ_ARG", 5), ("SZ_RES", 3), ("SZ_IW", 0), ("SZ_W", 0)))
    header = (f"#ifndef casadi_real\n#define casadi_real double\n#endif\n#ifndef casadi_int\n"
              f"#define casadi_int long long\n#endif\n{header}int {name}_step(const double** arg, "
              f"double** res, long long* iw, double* w, int mem);\n")
    (build / f"{name}.h").write_text(header)
    (build / f"{name}.c").write_text(source_code)
    loop = build / f"{name}_loop.c"
    loop.write_text(loop_source(name))
    return build / f"{name}.c", loop


def _check(label: str, outputs: Sequence[Any], reference: Sequence[np.ndarray],
           tol: float = 1e-9) -> float:
    error = max(float(np.max(np.abs(np.asarray(out, dtype=float).reshape(ref.shape) - ref)))
                for out, ref in zip(outputs, reference))
    if not error <= tol:
        raise RuntimeError(f"{label}: the step differs from the CasADi VM by {error:.3g} (> {tol});"
                           " the implementations disagree, so the timings would be meaningless.")
    return error


def _compile(gcc: str, sources: Sequence[Path], output: Path, flags: Sequence[str],
             *extra: str) -> float:
    start = time.perf_counter()
    result = subprocess.run([gcc, *flags, "-Wall", "-Wextra", "-Werror", *extra,
                             *map(str, sources), "-o", str(output), "-lm"],
                            capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"gcc {' '.join(flags)} failed on the generated code:\n"
                           f"{result.stderr}")
    return time.perf_counter() - start


def _run_loop(binary: Path, n_calls: int, repeat: int) -> tuple[float, float]:
    """Seconds per step (fastest of ``repeat`` runs) and the checksum the loop printed."""
    out = subprocess.run([str(binary), str(n_calls), str(repeat)], capture_output=True,
                         text=True, check=True).stdout.split()
    return float(out[0]), float(out[1])


def _callgrind(valgrind: str, binary: Path, n_calls: int) -> Optional[float]:
    """Instructions per step under ``valgrind --tool=callgrind`` (start-up subtracted)."""
    counts = []
    for n in (0, n_calls):
        result = subprocess.run([valgrind, "--tool=callgrind", "--callgrind-out-file=/dev/null",
                                 str(binary), str(n), "1"], capture_output=True, text=True)
        found = re.search(r"Collected : (\d+)", result.stderr)
        if result.returncode != 0 or found is None:
            return None
        counts.append(int(found.group(1)))
    return (counts[1] - counts[0]) / n_calls


def _native_supported(gcc: str) -> bool:
    result = subprocess.run([gcc, *NATIVE_FLAGS, "-x", "c", "-c", "-", "-o", os.devnull],
                            input="int x;\n", capture_output=True, text=True)
    return result.returncode == 0


@dataclass(frozen=True)
class _Case:
    """One Python-side implementation to time: ``setup()`` before each run, then ``n`` ``call()``
    (``threads``: the torch threads it uses)."""

    label: str
    call: Callable[[], object]
    setup: Callable[[], object] = lambda: None
    threads: int = 1


def _calls_per_run(seconds_per_call: float, n_calls: Optional[int]) -> int:
    return n_calls if n_calls is not None else max(1, round(_RUN_SECONDS / seconds_per_call))


def _time_interleaved(cases: Sequence[_Case], n_calls: Optional[int],
                      repeat: int) -> list[Timing]:
    """Fastest of ``repeat`` runs per case, the cases taking turns (see :func:`_calls_per_run`)."""
    best = {case.label: np.inf for case in cases}
    calls = {}
    for case in cases:                              # warm-up, and the calls per run
        case.setup()
        start = time.perf_counter()
        case.call()
        calls[case.label] = _calls_per_run(time.perf_counter() - start, n_calls)
    for _ in range(repeat):
        for case in cases:
            case.setup()
            start = time.perf_counter()
            for _ in range(calls[case.label]):
                case.call()
            best[case.label] = min(best[case.label], time.perf_counter() - start)
    return [Timing(case.label, best[case.label], calls[case.label]) for case in cases]


def bench_observer_step(model_dir: str | os.PathLike, *, system: Optional[System] = None,
                        n_calls: Optional[int] = None, repeat: int = 100,
                        flags: Sequence[str] = DEFAULT_FLAGS,
                        callgrind: Optional[bool] = None,
                        torch_compile: bool = False) -> list[Timing]:
    """Time one observer step in C, in the CasADi VM and in torch; print times and ratios.

    Parameters
    ----------
    model_dir : str or path-like
        A model directory (any method; torch is skipped for a model-based injection term, whose
        plant exists in CasADi only).
    system : System, optional
        The plant, as for :func:`kklcasadi.load_observer`.
    n_calls : int, optional
        Steps per timed run; default: as many as take about 2 ms (at least one), so that on a
        loaded machine some runs of every implementation fall between interruptions.
    repeat : int
        Timed runs per implementation, the implementations taking turns; the fastest is kept.
    flags : sequence of str
        The compiler flags of the default C build and of the hand-written limit (default
        :data:`kklcasadi.observer.codegen.DEFAULT_FLAGS`); the native build adds ``-march=native``.
    callgrind : bool, optional
        Count the instructions of the C loops with valgrind; default: when valgrind is installed.
    torch_compile : bool
        Also time ``torch.compile`` of the torch step (its build takes 20-60 s).

    Returns
    -------
    list of Timing
        ``items`` = steps in the run, so ``seconds / items`` is the time per step; the gcc
        compile of the default build (``items = 1``) comes first when gcc is installed.
    """
    flags = check_flags(flags)
    obs = load_observer(model_dir, system=system)
    rng = np.random.default_rng(0)
    args = [0.5 * rng.normal(size=size) for size in
            (obs.nz, obs.memory_shape, obs.ny, obs.ny, obs.nu)]   # z, w, y, y_next, u_next
    dm_args = [ca.DM(a) for a in args]
    reference = [np.array(v) for v in obs.step.call(dm_args)]
    if obs.step_covariance is not None and obs.step_covariance.n_in() == 6:   # the C step's inflation state, m_0
        c_args = [*dm_args, ca.DM(obs.inflation_start)]
    else:
        c_args = dm_args
    checks: dict[str, float] = {}
    timings: list[Timing] = []
    runs: list[Timing] = []
    counts: dict[str, float] = {}
    limits: list[tuple[str, str]] = []
    print(f"observer step: {obs!r}")

    gcc = shutil.which("gcc")
    valgrind = shutil.which("valgrind") if callgrind is not False else None
    if callgrind and valgrind is None:
        print("valgrind not found: no instruction counts")
    cases = []
    with tempfile.TemporaryDirectory() as tmp:       # holds the library ca.external loads
        if gcc is None:
            print("gcc not found: skipping the compiled C timings")
        else:
            c_runs, external = _bench_c(obs, Path(tmp), gcc, valgrind, flags, c_args,
                                        reference, n_calls, repeat, timings, checks, counts,
                                        limits)
            runs += c_runs
            cases.append(_Case("C default via ca.external (Function.call)",
                               lambda: external.call(c_args)))
        cases.append(_Case("CasADi VM (Function.call)", lambda: obs.step.call(dm_args)))
        torch_cases, restore_threads = _torch_cases(obs, args, reference, torch_compile, checks)
        try:
            # one thread each, taking turns; then torch's own thread count alone, as its idle
            # workers keep spinning for a while and would slow whatever runs next
            serial = [case for case in torch_cases if case.threads == 1]
            python_runs = _time_interleaved(cases + serial, n_calls, repeat)
            python_runs += _time_interleaved([case for case in torch_cases if case.threads > 1],
                                             n_calls, repeat)
        finally:
            restore_threads()
    runs += python_runs
    torch_runs = python_runs[len(cases):]

    for label, error in checks.items():
        print(f"{label:<48s} max |difference| from the CasADi VM: {error:.2e}")
    for timing in timings:
        print(f"{timing.label:<48s} {timing.seconds:10.2f} s")
    _print_ratios(runs, torch_runs, counts, limits)
    return timings + [replace(run, instructions=counts.get(run.label)) for run in runs]


def _c_builds(obs: KKLObserver, build: Path, gcc: str, flags: tuple[str, ...],
              files: dict[str, list[Path]], limits: list[tuple[str, str]]) -> list[_CBuild]:
    """The C loops to time: the generated code in its variants, and the hand-written limit
    (``limits`` gets the pairs of labels to compare: same math, flags and instruction set)."""

    def loop(key: str) -> tuple[Path, Path]:
        return files[key][0], build / key / "loop.c"

    default = _CBuild(f"C default, {' '.join(flags)}", loop("default"), flags)
    native = (_CBuild(f"C default, {' '.join(NATIVE_FLAGS)}", loop("default"), NATIVE_FLAGS)
              if _native_supported(gcc) else None)
    no_dispatch = (*flags, "-DKKLC_NO_DISPATCH")
    portable = _CBuild(f"C portable, {' '.join(no_dispatch)}", loop("default"), no_dispatch)
    bitwise = _CBuild(f"C math=libm (bitwise), {' '.join(no_dispatch)}", loop("libm"),
                      no_dispatch)
    builds = [b for b in (default, native, portable, bitwise) if b is not None]
    builds.append(_CBuild("C as CasADi writes it, -std=c99 -O2", loop("casadi"),
                          ("-std=c99", "-O2")))
    # the hand-written limit, each against the generated C of the same math, flags and ISA
    comparable = [("vector", flags, portable), ("libm", flags, bitwise)]
    if native is not None:
        comparable.append(("vector", NATIVE_FLAGS, native))
    for math, hand_flags, generated in comparable:
        hand = _hand_written(obs, build, math)
        if hand is not None:
            builds.append(_CBuild(f"hand-written dense C, {math} tanh, {' '.join(hand_flags)}",
                                  hand, hand_flags))
            limits.append((generated.label, builds[-1].label))
    return builds


def _bench_c(obs: KKLObserver, build: Path, gcc: str, valgrind: Optional[str],
             flags: tuple[str, ...], dm_args: list[ca.DM], reference: list[np.ndarray],
             n_calls: Optional[int], repeat: int, timings: list[Timing], checks: dict[str, float],
             counts: dict[str, float],
             limits: list[tuple[str, str]]) -> tuple[list[Timing], ca.Function]:
    """Time the C loops; fill ``timings`` (compile), ``checks``, ``counts`` (callgrind) and
    ``limits`` (pairs of labels: generated C, hand-written C of the same math and flags).

    Returns the timings and the default build loaded with ``ca.external``.
    """
    flag_text = " ".join(flags)
    variants = {"default": {}, "libm": {"math": "libm"},
                "casadi": {"matvec": "casadi", "math": "libm"}}
    files = {}
    for key, options in variants.items():
        folder = build / key
        files[key] = generate_c(obs, folder, _NAME, **options)
        (folder / "loop.c").write_text(loop_source(_NAME))
    library = build / f"lib{_NAME}.so"
    timings.append(Timing(f"gcc {flag_text} compile (shared library)",
                          _compile(gcc, files["default"][:1], library, flags, "-fPIC",
                                   "-shared"), 1))
    external = ca.external(f"{_NAME}_step", str(library))
    checks["C default (ca.external)"] = _check("C", external.call(dm_args), reference,
                                               VECTOR_MATH_TOLERANCE)
    builds = _c_builds(obs, build, gcc, flags, files, limits)
    binaries: dict = {}
    best: dict = {}
    for i, c_build in enumerate(builds):
        binaries[c_build.label] = build / f"loop{i}"
        _compile(gcc, c_build.sources, binaries[c_build.label], c_build.flags)
        if valgrind is not None and "-march=native" not in c_build.flags:
            count = _callgrind(valgrind, binaries[c_build.label], 10)
            if count is not None:
                counts[c_build.label] = count
    steps = {label: _calls_per_run(_run_loop(binary, 1, 3)[0], n_calls)
             for label, binary in binaries.items()}
    for _ in range(_ROUNDS):          # interleaved, so that a change of load hits all alike
        for label, binary in binaries.items():
            seconds = _run_loop(binary, steps[label], max(1, repeat // _ROUNDS))[0]
            best[label] = min(best.get(label, seconds), seconds)
    # the same 10 steps from the same state: every loop's checksum agrees
    checksums = {label: _run_loop(binary, 10, 1)[1] for label, binary in binaries.items()}
    runs = [Timing(label, seconds * steps[label], steps[label]) for label, seconds in best.items()]
    first = next(iter(checksums.values()))
    for label, checksum in checksums.items():
        if not abs(checksum - first) <= 1e-9 * max(1.0, abs(first)):
            raise RuntimeError(f"{label}: checksum {checksum!r} differs from {first!r}; the C "
                               "implementations disagree, so the timings would be meaningless.")
    return runs, external


def _torch_cases(obs: KKLObserver, args: list[np.ndarray], reference: list[np.ndarray],
                 torch_compile: bool,
                 checks: dict[str, float]) -> tuple[list[_Case], Callable[[], None]]:
    """Torch eager (1 thread and torch's default count), TorchScript and torch.compile.

    Returns the cases and a function that restores torch's thread count.
    """
    from ...train.step import torch_step

    step = torch_step(obs)
    if step is None:
        why = ("the model-based term needs the CasADi plant" if obs.method == "inject" or obs.model_based_injection
               else f"the {obs.method!r} variant has no torch step")
        print(f"torch: skipped ({why})")
        return [], lambda: None
    import torch

    tensors = [torch.as_tensor(a) for a in args]
    default_threads = torch.get_num_threads()
    implementations = {"torch eager": step}
    with torch.no_grad(), warnings.catch_warnings():
        # torch 2.9+ deprecates TorchScript; it is still the fastest torch here (docs/notes/speed.md)
        warnings.filterwarnings("ignore", "`torch.jit.trace` is deprecated", DeprecationWarning)
        start = time.perf_counter()
        implementations["torch.jit.trace"] = torch.jit.trace(step, tuple(tensors),
                                                             check_trace=False)
        implementations["torch.jit.trace"](*tensors)
        print(f"{'torch.jit.trace build':<48s} {time.perf_counter() - start:10.2f} s")
    if torch_compile:
        start = time.perf_counter()
        implementations["torch.compile"] = torch.compile(step, dynamic=False)
        with torch.inference_mode():
            implementations["torch.compile"](*tensors)
        print(f"{'torch.compile build':<48s} {time.perf_counter() - start:10.2f} s")
    cases = []
    for label, implementation in implementations.items():
        with torch.inference_mode():
            checks[label] = _check(label, [t.numpy() for t in implementation(*tensors)],
                                   reference)
        for threads in sorted({1, default_threads} if label == "torch eager" else {1}):
            cases.append(_Case(f"{label} ({threads} thread{'s' if threads > 1 else ''})",
                               _torch_call(implementation, tensors),
                               lambda threads=threads: torch.set_num_threads(threads), threads))
    return cases, lambda: torch.set_num_threads(default_threads)


def _torch_call(implementation: Callable[..., Any], tensors: Sequence[Any]) -> Callable[[], Any]:
    import torch

    def call() -> Any:
        with torch.inference_mode():
            return implementation(*tensors)

    return call


def _print_ratios(runs: list[Timing], torch_runs: list[Timing], counts: dict[str, float],
                  limits: list[tuple[str, str]]) -> None:
    per_step = {run.label: run.seconds / run.items for run in runs}
    base = runs[0]
    for run in runs:
        count = counts.get(run.label)
        instructions = f"{count:12,.0f} instr" if count is not None else " " * 18
        print(f"{run.label:<48s} {per_step[run.label] * 1e6:10.2f} us/step {instructions}   "
              f"x {per_step[run.label] / per_step[base.label]:7.2f} of {base.label}")
    eager = [run for run in torch_runs if run.label.startswith("torch eager")]
    summary = []
    if eager:
        best = min(eager, key=lambda run: per_step[run.label])
        summary.append(("torch eager at its best thread count", best))
    if torch_runs:
        summary.append(("the fastest torch", min(torch_runs, key=lambda r: per_step[r.label])))
    for what, run in summary:
        print(f"{base.label} is {per_step[run.label] / per_step[base.label]:.2f}x as fast as "
              f"{what} ({run.label})")
    for c_label, hand_label in limits:             # the same math, flags and instruction set
        print(f"{c_label} takes {per_step[c_label] / per_step[hand_label]:.2f}x the time of "
              f"{hand_label}")


#: The columns of :func:`step_table`: (heading, the label of the timing it shows, or its start after "...").
STEP_COLUMNS = (("C default (-O3)", f"C default, {' '.join(DEFAULT_FLAGS)}"), ("C portable", "C portable..."),
                ("C math=libm (bitwise)", "C math=libm..."), ("C via ca.external", "C default via ca.external..."),
                ("CasADi VM", "CasADi VM..."))


def card_digest(model_dir: str | os.PathLike) -> str:
    """The SHA-256 of a model directory's ``card.json`` (which holds its weights' digest): what a step figure
    was measured on."""
    return hashlib.sha256((Path(model_dir) / "card.json").read_bytes()).hexdigest()


def _column(timings: Sequence[Timing], label: str) -> Optional[Timing]:
    start = label[:-3] if label.endswith("...") else None
    return next((t for t in timings if t.items > 0 and (t.label.startswith(start) if start else t.label == label)),
                None)


def step_table(results: Sequence[tuple[str, str, Sequence[Timing]]], load: Sequence[float]) -> str:
    """The markdown table of observer steps: one row per ``(model name, card digest, timings of
    bench_observer_step)`` with the microseconds per step of :data:`STEP_COLUMNS` and the default build's
    instructions per step, and the load average (1, 5, 15 min) the runs saw."""
    rows = ["| model | card sha256 | " + " | ".join(f"{h} (us)" for h, _ in STEP_COLUMNS)
            + " | instructions (C default) |",
            "|" + "---|" * (len(STEP_COLUMNS) + 3)]
    for name, digest, timings in results:
        found = [_column(timings, label) for _, label in STEP_COLUMNS]
        us = ["" if t is None else f"{t.seconds / t.items * 1e6:.2f}" for t in found]
        count = "" if found[0] is None or found[0].instructions is None else f"{found[0].instructions:,.0f}"
        rows.append(f"| `{name}` | `{digest[:16]}` | " + " | ".join(us) + f" | {count} |")
    return ("\n".join(rows) + "\n\nOne step (latent update and decoder) per model, the best of interleaved short "
            "runs; instructions by valgrind's callgrind (repeatable on a loaded machine), times not: load average "
            f"{' / '.join(f'{v:.2f}' for v in load)} on {os.cpu_count()} CPUs.\n")
