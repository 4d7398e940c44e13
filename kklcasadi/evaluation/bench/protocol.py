"""Benchmark of the full docs/protocol.md run of one system: every shipped method, every cell, fast path vs VM.

``kklcasadi bench protocol --system duffing`` times, in one run:

- the trials of every cell (4 input regimes x noise-free/noisy) simulated and written to an empty
  trial cache (cold), then read back from it (warm);
- per method (the shipped models of the system and the EKF): building and compiling its
  trajectory into an empty library cache, then scoring every cell with the compiled trajectory
  mapped over the trials;
- the same estimator in the CasADi VM on the first ``vm_trials`` trials of every cell, and
  how far the compiled estimates are from the VM's there (0 with ``axpy_matvec``: bitwise).

Wall times on a shared machine vary with the load; CPU times (all threads of this process) are
printed beside them. Nothing here asserts a speed.
"""

from __future__ import annotations

import os
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
from ...validation import error, positive_int
from ..compiled import CompiledEstimator, Compiler, ekf_estimator, observer_estimator
from ..protocol import Protocol, evaluate
from ..trialcache import TrialCache

__all__ = ["MethodTiming", "ProtocolBench", "bench_protocol", "TARGET_SECONDS"]

#: Issue 9's target for the full protocol of one system (warm trial cache, 2 cores).
TARGET_SECONDS = 300.0

PathLike = Union[str, os.PathLike]


@dataclass(frozen=True)
class MethodTiming:
    """One method's timings (seconds; ``*_cpu_s`` summed over the process's threads).

    Attributes
    ----------
    label : str
    compile_s : float
        Building and compiling the trajectory (empty library cache).
    run_s, run_cpu_s : float
        Scoring every cell with the compiled trajectory.
    trials : int
        Trials scored (all cells).
    vm_s, vm_cpu_s : float
        The VM on the first ``vm_trials`` trials of every cell.
    vm_trials : int
    max_diff : float
        ``max |compiled - VM| / (1 + |VM|)`` over those trials (0: bitwise equal).
    """

    label: str
    compile_s: float
    run_s: float
    run_cpu_s: float
    trials: int
    vm_s: float
    vm_cpu_s: float
    vm_trials: int
    max_diff: float

    @property
    def per_trial_s(self) -> float:
        return self.run_s / self.trials

    @property
    def vm_per_trial_s(self) -> float:
        return self.vm_s / self.vm_trials

    @property
    def cpu_per_trial_s(self) -> float:
        return self.run_cpu_s / self.trials

    @property
    def vm_cpu_per_trial_s(self) -> float:
        return self.vm_cpu_s / self.vm_trials

    @property
    def speedup(self) -> float:
        """VM wall time per trial over the compiled one."""
        return self.vm_per_trial_s / self.per_trial_s

    @property
    def cpu_speedup(self) -> float:
        """VM CPU time per trial over the compiled one (less sensitive to the machine's load)."""
        return self.vm_cpu_per_trial_s / self.cpu_per_trial_s


@dataclass(frozen=True)
class ProtocolBench:
    """The timings of one system's full protocol.

    Attributes
    ----------
    system : str
    n_trials, cells : int
        Trials per cell and cells (regimes x noise settings).
    simulate_s : float
        Simulating every cell into an empty trial cache.
    load_s : float
        Reading every cell back from it.
    methods : tuple of MethodTiming
    """

    system: str
    n_trials: int
    cells: int
    simulate_s: float
    load_s: float
    methods: tuple

    @property
    def warm_s(self) -> float:
        """The full protocol with warm caches: read the trials, run every method."""
        return self.load_s + sum(m.run_s for m in self.methods)

    @property
    def warm_cpu_s(self) -> float:
        """CPU time (all threads) of running every method; the load of the machine inflates wall time only."""
        return sum(m.run_cpu_s for m in self.methods)

    @property
    def cold_s(self) -> float:
        """The full protocol from empty caches: simulate, compile, run."""
        return self.simulate_s + sum(m.compile_s + m.run_s for m in self.methods)

    @property
    def vm_estimate_s(self) -> float:
        """The VM path (cold trial cache), extrapolated from its per-trial cost."""
        return self.simulate_s + sum(m.vm_per_trial_s * m.trials for m in self.methods)

    def table(self) -> str:
        """A markdown table of the per-method timings and the totals."""
        lines = ["| method | compile (s) | run (s) | trials | per trial, compiled: wall / cpu (ms) | "
                 "per trial, VM: wall / cpu (ms) | VM / compiled: wall / cpu | max diff vs VM |",
                 "|---|---|---|---|---|---|---|---|"]
        for m in self.methods:
            lines.append(f"| {m.label} | {m.compile_s:.1f} | {m.run_s:.1f} | {m.trials} | "
                         f"{m.per_trial_s * 1e3:.1f} / {m.cpu_per_trial_s * 1e3:.1f} | "
                         f"{m.vm_per_trial_s * 1e3:.1f} / {m.vm_cpu_per_trial_s * 1e3:.1f} | "
                         f"{m.speedup:.2f}x / {m.cpu_speedup:.2f}x | {m.max_diff:.1e} |")
        verdict = "meets" if self.warm_s < TARGET_SECONDS else "misses"
        lines += ["",
                  f"{self.system}: {len(self.methods)} methods x {self.cells} cells x {self.n_trials} trials",
                  f"- trials: simulate {self.simulate_s:.1f} s (cold), read {self.load_s:.2f} s (warm)",
                  f"- full protocol, warm caches: {self.warm_s:.1f} s ({verdict} the {TARGET_SECONDS:.0f} s target); "
                  f"CPU {self.warm_cpu_s:.1f} s, over 2 cores {self.warm_cpu_s / 2:.1f} s",
                  f"- full protocol, cold caches (simulate + compile + run): {self.cold_s:.1f} s",
                  f"- VM path, cold trial cache (extrapolated from the VM trials): {self.vm_estimate_s:.1f} s"]
        return "\n".join(lines)


def _clock(fn: Callable[[], object]) -> tuple[object, float, float]:
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def bench_protocol(system: str = "duffing", *, models: Optional[Sequence[PathLike]] = None, n_trials: int = 100,
                   vm_trials: int = 4, ekf: bool = True, kinds: Sequence[str] = sig.BENCHMARK_KINDS,
                   compiler: Optional[Compiler] = None, n_threads: Optional[int] = None,
                   cache_dir: Optional[PathLike] = None, progress: bool = True) -> ProtocolBench:
    """Time the full protocol of ``system``: cold/warm trial cache, compiled methods, the VM beside them.

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
    ekf : bool
        Also time the EKF.
    kinds : sequence of str
        Input regimes; every regime is run noise-free and noisy.
    compiler : Compiler, optional
        Flags and post-processing hook; its ``cache_dir`` is replaced by an empty one.
    n_threads : int, optional
        Worker threads over trials (default: the CPU count).
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
    plant = systems.get(system)
    models = [Path(m) for m in (shipped_models(system) if models is None else models)]
    base = compiler if compiler is not None else Compiler(postprocess=fast_kernels)
    with tempfile.TemporaryDirectory(prefix="kklcasadi-bench-") as tmp:
        root = Path(cache_dir) if cache_dir is not None else Path(tmp)
        trial_cache = TrialCache(root / "trials")
        compiler = Compiler(base.command, base.flags, root / "compiled", base.postprocess)
        protocols = [Protocol(n_trials=n_trials).noise_free(), Protocol(n_trials=n_trials)]
        cells = [(p, kind) for p in protocols for kind in kinds]

        def log(text: str) -> None:
            if progress:
                print(text, file=sys.stderr, flush=True)

        _, simulate_s, _ = _clock(lambda: [trial_cache.trials(plant, p.cell(kind)) for p, kind in cells])
        log(f"simulated {len(cells)} cells x {n_trials} trials in {simulate_s:.1f} s")
        warm = TrialCache(trial_cache.directory)                         # a new cache: read from disk
        batches, load_s, _ = _clock(lambda: {(p, kind): warm.trials(plant, p.cell(kind)) for p, kind in cells})
        estimators: list[tuple[str, Callable[[Optional[Compiler]], CompiledEstimator]]] = []
        for model in models:
            obs = load_observer(model)
            if obs.system.name != plant.name:
                raise ValueError(f"models: {model} is for {obs.system.name!r}, expected {plant.name!r}.")
            estimators.append((model.name, lambda c, obs=obs: observer_estimator(obs, compiler=c,
                                                                                  n_threads=n_threads)))
        if ekf:
            filt = EKF(plant, Protocol().dt)
            estimators.append(("EKF", lambda c: ekf_estimator(filt, compiler=c, n_threads=n_threads)))
        timings = []
        n = next(iter(batches.values())).t.size
        for label, make in estimators:
            fast = make(compiler)
            _, compile_s, _ = _clock(lambda: fast.function(n))
            results, run_s, run_cpu_s = _clock(lambda: [
                evaluate(fast, plant, p, (kind,), trials=warm)[0]
                for p, kind in _bar(cells, label, progress)])
            subsets = [batches[cell] for cell in cells]
            vm = make(None)
            vm_out, vm_s, vm_cpu_s = _clock(lambda: [vm(b.t, b.y[:vm_trials], b.u[:vm_trials]) for b in subsets])
            fast_out = [fast(b.t, b.y[:vm_trials], b.u[:vm_trials]) for b in subsets]
            timing = MethodTiming(label, compile_s, run_s, run_cpu_s, sum(r.smape.size for r in results), vm_s,
                                  vm_cpu_s, vm_trials * len(cells),
                                  max(float(np.max(np.abs(a - b) / (1 + np.abs(b)))) for a, b in zip(fast_out, vm_out)))
            timings.append(timing)
            log(f"{label}: compile {compile_s:.1f} s, run {run_s:.1f} s, {timing.per_trial_s * 1e3:.1f} ms/trial "
                f"(cpu {timing.cpu_per_trial_s * 1e3:.1f}; VM {timing.vm_per_trial_s * 1e3:.1f}, cpu "
                f"{timing.vm_cpu_per_trial_s * 1e3:.1f}), max diff vs VM {timing.max_diff:.1e}")
    return ProtocolBench(plant.name, n_trials, len(cells), simulate_s, load_s, tuple(timings))


def _bar(items: list, label: str, progress: bool):
    from tqdm.auto import tqdm

    return tqdm(items, desc=label, unit="cell", disable=not progress, leave=False)
