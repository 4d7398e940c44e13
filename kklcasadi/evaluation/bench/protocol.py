"""Benchmark of the full docs/protocol.md run of one system: every shipped method, every cell, cold and warm.

``kklcasadi bench protocol --system duffing`` times, in one run, what ``kklcasadi evaluate
models/SYSTEM/* --ekf`` does (every method on the noise-free and noisy cells of every regime):

- cold: from empty trial and library caches (the trials simulated while the C compiler builds
  the estimators, then every method scored), wall and CPU time with the phases of
  :class:`~kklcasadi.evaluation.protocol.Profile`;
- warm: the same again with the caches filled (trials read from disk, libraries loaded);
- per method: the warm run's wall and CPU time per trial, beside the trajectory that folds the
  plain observer step over the samples trial by trial (``shortcuts=False``: 1000 steps per
  trial, the cost per step that ``kklcasadi bench observer`` times, on ``plain_trials`` trials
  per cell), the CasADi VM on the first ``vm_trials`` trials of every cell, and how far the
  compiled estimates are from the VM's there (0 with ``axpy_matvec``: bitwise);
- optionally (``instructions``) the instructions per trial of the compiled code under
  ``valgrind --tool=callgrind``, now and plain, one trial per regime: repeatable on a loaded machine.

Wall times on a shared machine vary with the load: the load average is printed at the start and
the end, and CPU times (all threads of this process and the C compiler) beside the wall times.
Nothing here asserts a speed.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

import numpy as np

from ...model.shipped import shipped_models
from ...observer.codegen import fast_kernels
from ...plant import signals as sig
from ...plant import systems
from ...validation import error, nonnegative_int, positive_int
from ..compiled import CompiledEstimator, Compiler, ekf_estimator, observer_estimator, precompile
from ..protocol import Profile, Protocol, read_cells
from ..report import score
from ..trialcache import TrialCache

__all__ = ["MethodTiming", "ProtocolBench", "bench_protocol", "TARGET_SECONDS", "TARGET_COLD_SECONDS"]

#: The target for the full protocol of one system, warm caches, 2 cores.
TARGET_SECONDS = 120.0
#: ... and from empty caches.
TARGET_COLD_SECONDS = 180.0

PathLike = Union[str, os.PathLike]


@dataclass(frozen=True)
class MethodTiming:
    """One method's timings (seconds; ``*_cpu_s`` summed over the process's threads).

    Attributes
    ----------
    label : str
    run_s, run_cpu_s : float
        Scoring every cell in the warm run.
    trials : int
        Trials scored (all cells).
    plain_s, plain_cpu_s : float
        The plain step folded trial by trial, on ``plain_trials`` trials (None: the method has no
        other trajectory, e.g. the EKF).
    plain_trials : int
    vm_s, vm_cpu_s : float
        The VM on the first ``vm_trials`` trials of every cell.
    vm_trials : int
    max_diff : float
        ``max |compiled - VM| / (1 + |VM|)`` over those trials (0: bitwise equal).
    instructions, plain_instructions : float or None
        Instructions per trial of the compiled code now and plain (callgrind, mean over one trial
        per regime and noise setting), where counted.
    """

    label: str
    run_s: float
    run_cpu_s: float
    trials: int
    plain_s: Optional[float]
    plain_cpu_s: Optional[float]
    plain_trials: int
    vm_s: float
    vm_cpu_s: float
    vm_trials: int
    max_diff: float
    instructions: Optional[float] = None
    plain_instructions: Optional[float] = None

    @property
    def per_trial_s(self) -> float:
        return self.run_s / self.trials

    @property
    def cpu_per_trial_s(self) -> float:
        return self.run_cpu_s / self.trials

    @property
    def plain_cpu_per_trial_s(self) -> Optional[float]:
        return None if self.plain_cpu_s is None else self.plain_cpu_s / self.plain_trials

    @property
    def vm_per_trial_s(self) -> float:
        return self.vm_s / self.vm_trials

    @property
    def vm_cpu_per_trial_s(self) -> float:
        return self.vm_cpu_s / self.vm_trials


@dataclass(frozen=True)
class ProtocolBench:
    """The timings of one system's full protocol.

    Attributes
    ----------
    system : str
    n_trials, cells : int
        Trials per cell and cells (regimes x noise settings).
    cold_s, cold_cpu_s : float
        The whole run from empty caches: simulate the trials and compile (at once), score.
    warm_s, warm_cpu_s : float
        The whole run again, the caches filled.
    cold_profile, warm_profile : Profile
        Where each run's time went.
    methods : tuple of MethodTiming
    load : tuple of float
        The 1-minute load average at the start, between the runs and at the end.
    cpus : int
        CPUs of the machine.
    """

    system: str
    n_trials: int
    cells: int
    cold_s: float
    cold_cpu_s: float
    warm_s: float
    warm_cpu_s: float
    cold_profile: Profile
    warm_profile: Profile
    methods: tuple
    load: tuple
    cpus: int

    def table(self) -> str:
        """A markdown table of the per-method timings, then the runs and their phases."""
        lines = ["| method | run, warm (s) | trials | per trial: wall / cpu (ms) | per trial, plain step: cpu (ms) | "
                 "plain / now (cpu) | instructions per trial: now / plain (M) | per trial, VM: cpu (ms) | "
                 "max diff vs VM |",
                 "|---|---|---|---|---|---|---|---|---|"]
        for m in self.methods:
            plain = m.plain_cpu_per_trial_s
            counts = ("" if m.instructions is None else
                      f"{m.instructions / 1e6:.0f} / {m.plain_instructions / 1e6:.0f}"
                      if m.plain_instructions is not None else f"{m.instructions / 1e6:.0f}")
            lines.append(f"| {m.label} | {m.run_s:.1f} | {m.trials} | "
                         f"{m.per_trial_s * 1e3:.1f} / {m.cpu_per_trial_s * 1e3:.1f} | "
                         f"{'' if plain is None else f'{plain * 1e3:.1f}'} | "
                         f"{'' if plain is None or m.cpu_per_trial_s <= 0 else f'{plain / m.cpu_per_trial_s:.2f}x'} | "
                         f"{counts} | "
                         f"{m.vm_cpu_per_trial_s * 1e3:.1f} | {m.max_diff:.1e} |")
        verdict = {True: "meets", False: "misses"}
        lines += ["",
                  f"{self.system}: {len(self.methods)} methods x {self.cells} cells x {self.n_trials} trials, "
                  f"{self.cpus} CPUs, load average {' / '.join(f'{x:.2f}' for x in self.load)} "
                  "(start / between the runs / end)",
                  f"- cold caches (simulate + compile, then score): {self.cold_s:.1f} s wall, {self.cold_cpu_s:.1f} s "
                  f"CPU ({verdict[self.cold_s < TARGET_COLD_SECONDS]} the {TARGET_COLD_SECONDS:.0f} s target)",
                  f"- warm caches (read + load, then score): {self.warm_s:.1f} s wall, {self.warm_cpu_s:.1f} s CPU, "
                  f"CPU / wall {self.warm_cpu_s / max(self.warm_s, 1e-9):.2f} "
                  f"({verdict[self.warm_s < TARGET_SECONDS]} the "
                  f"{TARGET_SECONDS:.0f} s target)",
                  "", "cold run:", self.cold_profile.table(self.cold_s, self.cold_cpu_s),
                  "", "warm run:", self.warm_profile.table(self.warm_s, self.warm_cpu_s)]
        return "\n".join(lines)


def _clock(fn: Callable[[], object]) -> tuple[object, float, float]:
    """``fn()``, its wall time and its CPU time (this process's threads and its finished child processes)."""
    wall, cpu = time.perf_counter(), _cpu()
    out = fn()
    return out, time.perf_counter() - wall, _cpu() - cpu


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def bench_protocol(system: str = "duffing", *, models: Optional[Sequence[PathLike]] = None, n_trials: int = 100,
                   vm_trials: int = 4, plain_trials: int = 10, ekf: bool = True,
                   kinds: Sequence[str] = sig.BENCHMARK_KINDS, compiler: Optional[Compiler] = None,
                   n_threads: Optional[int] = None, instructions: bool = False,
                   cache_dir: Optional[PathLike] = None, progress: bool = True) -> ProtocolBench:
    """Time the full protocol of ``system`` from empty and from filled caches, method by method.

    Parameters
    ----------
    system : str
        A registered system with shipped models.
    models : sequence of path-like, optional
        Model directories (default :func:`kklcasadi.model.shipped.shipped_models`); rows are labelled by directory name.
    n_trials : int
        Trials per cell (docs/protocol.md: 100).
    vm_trials : int
        Trials per cell run in the VM for the per-trial comparison and the bitwise check.
    plain_trials : int
        Trials per cell run with the plain step folded (0: not timed).
    ekf : bool
        Also time the EKF.
    kinds : sequence of str
        Input regimes; every regime is run noise-free and noisy.
    compiler : Compiler, optional
        Flags and post-processing hook; its ``cache_dir`` is replaced by an empty one.
    n_threads : int, optional
        Worker threads over trials and compilers at a time (default: the CPU count).
    instructions : bool
        Count the instructions per trial with valgrind (about a minute per method).
    cache_dir : path-like, optional
        An empty directory for the trial and library caches (default: a temporary one, removed).
    progress : bool
        Progress bars and a line per step on stderr.

    Returns
    -------
    ProtocolBench
    """
    from ...estimators.ekf import EKF
    from ...observer.kkl import load_observer

    n_trials = positive_int(n_trials, "n_trials")
    if positive_int(vm_trials, "vm_trials") > n_trials:
        raise error("vm_trials", f"an int in [1, n_trials = {n_trials}]", vm_trials)
    if nonnegative_int(plain_trials, "plain_trials") > n_trials:
        raise error("plain_trials", f"an int in [0, n_trials = {n_trials}]", plain_trials)
    valgrind = shutil.which("valgrind") if instructions else None
    if instructions and valgrind is None:
        raise error("instructions", "valgrind on PATH (to count instructions)", instructions,
                    "Install valgrind or pass instructions=False.")
    plant = systems.get(system)
    models = [Path(m) for m in (shipped_models(system) if models is None else models)]
    observers = []
    for model in models:
        obs = load_observer(model)
        if obs.system.name != plant.name:
            raise ValueError(f"models: {model} is for {obs.system.name!r}, expected {plant.name!r}.")
        observers.append((model.name, obs))
    filt = EKF(plant, Protocol().dt) if ekf else None
    base = compiler if compiler is not None else Compiler(postprocess=fast_kernels)
    protocol = Protocol(n_trials=n_trials)
    noise = (False, True)
    cells = [(protocol if noisy else protocol.noise_free()).cell(kind) for noisy in noise for kind in kinds]

    def log(text: str) -> None:
        if progress:
            print(text, file=sys.stderr, flush=True)

    def rows(compiler: Optional[Compiler], profile: Optional[Profile], **options: object
             ) -> list[tuple[str, CompiledEstimator]]:
        out: list[tuple[str, CompiledEstimator]] = [
            (label, observer_estimator(obs, compiler=compiler, n_threads=n_threads, profile=profile, **options))
            for label, obs in observers]
        if filt is not None and not options:
            out.append(("EKF", ekf_estimator(filt, compiler=compiler, n_threads=n_threads, profile=profile)))
        return out

    def run(trials: TrialCache, compiler: Compiler, profile: Profile) -> dict:
        estimators = rows(compiler, profile)
        precompile([est for _, est in estimators], cells[0].shape()[1], groups=(2,), jobs=n_threads,
                   meanwhile=lambda: read_cells(plant, cells, trials, profile=profile))
        times = {}
        for label, est in estimators:
            _, wall, cpu = _clock(lambda: score(label, est, plant, protocol, noise=noise, kinds=kinds, trials=trials,
                                                progress=progress, profile=profile))
            times[label] = (wall, cpu)
        return times

    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory(prefix="kklcasadi-bench-") as tmp:
        root = Path(cache_dir) if cache_dir is not None else Path(tmp)
        compiler = Compiler(base.command, base.flags, root / "compiled", base.postprocess)
        cold_profile = Profile()
        _, cold_s, cold_cpu_s = _clock(lambda: run(TrialCache(root / "trials"), compiler, cold_profile))
        log(f"cold caches: {cold_s:.1f} s wall, {cold_cpu_s:.1f} s CPU")
        load.append(os.getloadavg()[0])
        warm_profile = Profile()
        times, warm_s, warm_cpu_s = _clock(lambda: run(TrialCache(root / "trials"), compiler, warm_profile))
        log(f"warm caches: {warm_s:.1f} s wall, {warm_cpu_s:.1f} s CPU")
        batches = read_cells(plant, cells, TrialCache(root / "trials"))
        pairs = [_first(clean, noisy, vm_trials) for clean, noisy in zip(batches[:len(kinds)], batches[len(kinds):])]
        plain = dict(rows(compiler, None, shortcuts=False)) if plain_trials else {}
        precompile(list(plain.values()), cells[0].shape()[1], jobs=n_threads)   # compiled before they are timed
        vms = dict(rows(None, None))
        timings = []
        for label, fast in rows(compiler, None):
            plain_s = plain_cpu_s = None
            if label in plain:
                _, plain_s, plain_cpu_s = _clock(lambda: [plain[label](b.t, b.y[:plain_trials], b.u[:plain_trials])
                                                          for b in batches])
            vm_out, vm_s, vm_cpu_s = _clock(lambda: [vms[label](t, y, u) for t, y, u in pairs])
            fast_out = [fast(t, y, u) for t, y, u in pairs]
            counts = (_instructions(valgrind, fast, plain.get(label), batches, len(kinds), tmp)
                      if valgrind is not None else (None, None))
            wall, cpu = times[label]
            timing = MethodTiming(label, wall, cpu, len(cells) * n_trials, plain_s, plain_cpu_s,
                                  plain_trials * len(cells), vm_s, vm_cpu_s, vm_trials * len(cells),
                                  max(float(np.max(np.abs(a - b) / (1 + np.abs(b)))) for a, b in zip(fast_out, vm_out)),
                                  *counts)
            timings.append(timing)
            log(f"{label}: run {wall:.1f} s, {timing.cpu_per_trial_s * 1e3:.1f} ms CPU per trial"
                + ("" if plain_cpu_s is None else f" (plain step {timing.plain_cpu_per_trial_s * 1e3:.1f})")
                + f", max diff vs VM {timing.max_diff:.1e}")
    load.append(os.getloadavg()[0])
    return ProtocolBench(plant.name, n_trials, len(cells), cold_s, cold_cpu_s, warm_s, warm_cpu_s, cold_profile,
                         warm_profile, tuple(timings), tuple(load), os.cpu_count() or 1)


def _first(clean: object, noisy: object, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first ``m`` trials of a regime's noise-free and noisy cells (they share their inputs)."""
    return clean.t, np.concatenate([clean.y[:m], noisy.y[:m]]), np.concatenate([clean.u[:m], noisy.u[:m]])


_DRIVER = r"""#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
typedef long long casadi_int;
typedef int (*eval_t)(const double**, double**, casadi_int*, double*, int);
typedef int (*work_t)(casadi_int*, casadi_int*, casadi_int*, casadi_int*);
typedef casadi_int (*count_t)(void);
typedef const casadi_int* (*pattern_t)(casadi_int);
static void* need(void* lib, const char* name, const char* suffix) {
  char symbol[512];
  void* p;
  snprintf(symbol, sizeof symbol, "%s%s", name, suffix);
  p = dlsym(lib, symbol);
  if (!p) { fprintf(stderr, "missing %s\n", symbol); exit(2); }
  return p;
}
static casadi_int nnz(const casadi_int* sp) { return sp[2] == 1 ? sp[0] * sp[1] : sp[2 + sp[1]]; }
/* driver LIBRARY NAME INPUTS CALLS: evaluate NAME on the inputs (float64, each dense, in order) */
int main(int argc, char** argv) {
  void* lib = dlopen(argv[1], RTLD_NOW);
  const char* name = argv[2];
  casadi_int sz_arg, sz_res, sz_iw, sz_w, i;
  long c, calls = atol(argv[4]);
  FILE* in = fopen(argv[3], "rb");
  if (!lib || !in) return 2;
  eval_t f = (eval_t) need(lib, name, "");
  ((work_t) need(lib, name, "_work"))(&sz_arg, &sz_res, &sz_iw, &sz_w);
  const double** arg = calloc(sz_arg + 1, sizeof *arg);
  double** res = calloc(sz_res + 1, sizeof *res);
  casadi_int* iw = calloc(sz_iw + 1, sizeof *iw);
  double* w = calloc(sz_w + 1, sizeof *w);
  for (i = 0; i < ((count_t) need(lib, name, "_n_in"))(); i++) {
    casadi_int n = nnz(((pattern_t) need(lib, name, "_sparsity_in"))(i));
    double* a = malloc((n + 1) * sizeof *a);
    if (fread(a, sizeof *a, n, in) != (size_t) n) return 3;
    arg[i] = a;
  }
  for (i = 0; i < ((count_t) need(lib, name, "_n_out"))(); i++)
    res[i] = calloc(nnz(((pattern_t) need(lib, name, "_sparsity_out"))(i)) + 1, sizeof(double));
  for (c = 0; c < calls; c++)
    if (f(arg, res, iw, w, 0)) return 4;
  return 0;
}
"""


def _instructions(valgrind: str, fast: CompiledEstimator, plain: Optional[CompiledEstimator], batches: list,
                  n_kinds: int, tmp: str) -> tuple[Optional[float], Optional[float]]:
    """Instructions per trial under callgrind: ``fast`` on the first trials of each regime's two noise
    cells together (one group), ``plain`` on each of them alone; None where not countable."""
    folder = Path(tmp) / "callgrind"
    folder.mkdir(exist_ok=True)
    driver = folder / "driver"
    if not driver.exists():
        (folder / "driver.c").write_text(_DRIVER)
        subprocess.run([fast.compiler.command, "-O2", str(folder / "driver.c"), "-o", str(driver), "-ldl"], check=True)

    def count(est: CompiledEstimator, y: np.ndarray, u: np.ndarray) -> Optional[float]:
        """Instructions of one call of ``est``'s trajectory on the group ``y`` (K, N, ny), ``u`` (N, nu)."""
        k, n = y.shape[:2]
        f = est.trajectory(n, k)
        library = est.compiler.library(f)
        inputs = folder / f"{f.name()}.bin"
        # y (ny, K N) with column k K + j the sample k of trial j, u (nu, N), s0: column-major, in order
        np.concatenate([y.transpose(1, 0, 2).ravel(), u.ravel(), est.initial_state()]).tofile(inputs)
        found = []
        for calls in (0, 1):
            out = subprocess.run([valgrind, "--tool=callgrind", "--callgrind-out-file=/dev/null", str(driver),
                                  str(library), f.name(), str(inputs), str(calls)], capture_output=True, text=True)
            match = re.search(r"Collected : (\d+)", out.stderr)
            if out.returncode != 0 or match is None:
                return None
            found.append(int(match.group(1)))
        return (found[1] - found[0]) / k

    now, before = [], []
    for clean, noisy in zip(batches[:n_kinds], batches[n_kinds:]):
        y, u = np.stack([clean.y[0], noisy.y[0]]), clean.u[0]
        if fast.shares_inputs:
            now.append(count(fast, y, u))
        else:
            now += [count(fast, y[:1], u), count(fast, y[1:], u)]
        if plain is not None:
            before += [count(plain, y[:1], u), count(plain, y[1:], u)]
    mean = lambda values: None if not values or None in values else float(np.mean(values))  # noqa: E731
    return mean(now), mean(before)
