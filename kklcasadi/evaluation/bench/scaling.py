"""The cost as the plant grows (``kklcasadi bench scaling``): a chain of ``n`` coupled nonlinear
oscillators, ``nx = 2n`` states, a few positions measured, and per size

* the training time of the recommended observer (``bank``: the recipe's filter bank and decoder, a
  small budget), per simulated second of its training runs;
* the observer's C step (:func:`kklcasadi.generate_c`, the default build), beside the work of its
  networks (multiply-adds of the latent update and the decoder);
* the EKF's C step (:meth:`kklcasadi.EKF.generate_c`) in both forms: CasADi's SX scalar code (the
  step the benchmark runs) and the dense form (the covariance by matrix products, the axpy kernels),
  with their compile times;
* the MHE's solve time per sample (``kc.MHE``, ipopt);
* the accuracy of the observer against the EKF (mean SMAPE on the same noisy trials);

and the growth exponents of each against ``nx`` (least squares on the log-log points). A C step is
the fastest of several short runs, the implementations taking turns, with ``valgrind
--tool=callgrind``'s instructions per step beside it where valgrind is installed (they do not
depend on the machine's load). Nothing here asserts a speed; torch is imported by training only.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Optional, Sequence

import casadi as ca
import numpy as np

from ... import metrics, provenance
from ...estimators.ekf import EKF, EKF_FORMS
from ...estimators.mhe import MHE
from ...observer.codegen import DEFAULT_FLAGS, check_flags, generate_c
from ...observer.kkl import KKLObserver, load_observer
from ...plant import signals as sig
from ...plant.simulate import simulate_batch
from ...plant.systems import System
from ...validation import error, positive_int
from ...writes import refuse_existing, staged
from .observer_step import _callgrind, _compile, _run_loop, loop_source

__all__ = ["oscillator_chain", "ScalingRow", "ScalingResult", "bench_scaling", "EKF_FLAGS"]

#: Build flags of the EKF's C: its SX form is one straight-line function (no loop to vectorise), for
#: which ``-O1`` runs within 8 % of ``-O3`` and compiles 10x faster (nx = 32: 11.9 against 11.0 us per
#: step, 8 s against 83 s to compile).
EKF_FLAGS = ("-std=c99", "-O1")
#: Length of one timed C run (short, so that on a loaded machine some runs fall between interruptions).
_RUN_SECONDS = 0.002


def oscillator_chain(n: int, *, coupling: float = 1.0, damping: float = 0.1, cubic: float = 1.0,
                     every: int = 8) -> System:
    """A chain of ``n`` Duffing oscillators coupled by springs to their neighbours (fixed ends).

    ``q_i' = p_i``, ``p_i' = -q_i - cubic q_i^3 - damping p_i + coupling (q_{i-1} - 2 q_i + q_{i+1})
    (+ u on the first mass)``, ``q_0 = q_{n+1} = 0``; the measured outputs are the positions of
    masses 1, 1 + every, 1 + 2 every, ...; states ``[q; p]``, box ``[-1, 1]^(2n)``.
    """
    n = positive_int(n, "n")
    every = positive_int(every, "every")
    q, p, u = ca.SX.sym("q", n), ca.SX.sym("p", n), ca.SX.sym("u", 1)
    wall = ca.vertcat(0, q, 0)
    acc = [-q[i] - cubic * q[i] ** 3 - damping * p[i] + coupling * (wall[i] - 2 * q[i] + wall[i + 2])
           + (u[0] if i == 0 else 0) for i in range(n)]
    y = ca.vertcat(*[q[i] for i in range(0, n, every)])
    return System(f"chain{n}", ca.vertcat(q, p), u, ca.vertcat(p, *acc), y, [[-1.0, 1.0]] * (2 * n),
                  description=f"{n} coupled Duffing oscillators, positions {list(range(1, n + 1, every))} measured")


@dataclass(frozen=True)
class ScalingRow:
    """One plant size. Times in seconds unless named ``_us`` (microseconds) or ``_ms``."""

    n: int
    nx: int
    ny: int
    nz: int
    train_s: float
    simulated_s: float
    observer_us: float
    observer_instructions: Optional[float]
    observer_work: int
    observer_compile_s: float
    ekf_us: dict
    ekf_instructions: dict
    ekf_compile_s: dict
    mhe_ms: float
    mhe_failed: int
    smape_observer: float
    smape_ekf: float

    @property
    def train_per_simulated_s(self) -> float:
        """Training wall time per simulated second of the training runs."""
        return self.train_s / self.simulated_s

    @property
    def ekf_best_us(self) -> float:
        return min(self.ekf_us.values())


#: The quantities whose growth :meth:`ScalingResult.exponents` fits: label -> value of a row (None: not
#: measured).
_GROWTH = {
    "training per simulated second": lambda r: r.train_per_simulated_s,
    "observer C step": lambda r: r.observer_us,
    "observer C instructions": lambda r: r.observer_instructions,
    "observer network work (multiply-adds)": lambda r: float(r.observer_work),
    **{f"EKF C step ({form})": (lambda r, f=form: r.ekf_us[f]) for form in EKF_FORMS},
    **{f"EKF C instructions ({form})": (lambda r, f=form: r.ekf_instructions.get(f)) for form in EKF_FORMS},
    "MHE solve": lambda r: r.mhe_ms,
}


@dataclass(frozen=True)
class ScalingResult:
    """The rows of :func:`bench_scaling` and its settings."""

    rows: list
    settings: dict = field(default_factory=dict)

    def exponents(self, min_nx: int = 4) -> dict:
        """The slope of ``log(value)`` against ``log(nx)`` (least squares over the sizes with
        ``nx >= min_nx``; all sizes where fewer than two are that large)."""
        rows = [r for r in self.rows if r.nx >= min_nx]
        rows = rows if len(rows) >= 2 else self.rows
        if len(rows) < 2:
            return {}
        lx = np.log([r.nx for r in rows])
        slopes = {}
        for label, value in _GROWTH.items():
            values = [value(r) for r in rows]
            if all(v is not None and v > 0 for v in values):
                slopes[label] = float(np.polyfit(lx, np.log(values), 1)[0])
        return slopes

    def crossover(self) -> Optional[int]:
        """The smallest ``nx`` from which on the observer's C step is cheaper than the faster EKF's."""
        cheaper = [r.observer_us < r.ekf_best_us for r in self.rows]
        for i, row in enumerate(self.rows):
            if all(cheaper[i:]):
                return row.nx
        return None

    def table(self) -> str:
        """Markdown: one row per size, then the growth exponents and the crossover."""
        forms = list(EKF_FORMS)
        head = ("| nx | ny | nz | training (s) | per simulated s (ms) | observer C step (us) | observer instr. | "
                "network MACs | " + " | ".join(f"EKF C {f} (us) | EKF {f} instr. | EKF {f} compile (s)"
                                               for f in forms)
                + " | MHE solve (ms) | SMAPE observer / EKF |")
        lines = [head, "|---" * (head.count("|") - 1) + "|"]

        def count(value: Optional[float]) -> str:
            return "-" if value is None else (f"{value / 1e3:.0f}k" if value < 1e6 else f"{value / 1e6:.2f}M")

        def us(value: float) -> str:
            return f"{value:.3g}" if value < 100 else f"{value:.0f}"

        for r in self.rows:
            ekf = " | ".join(f"{us(r.ekf_us[f])} | {count(r.ekf_instructions.get(f))} | {r.ekf_compile_s[f]:.1f}"
                             for f in forms)
            lines.append(f"| {r.nx} | {r.ny} | {r.nz} | {r.train_s:.1f} | {1e3 * r.train_per_simulated_s:.3f} | "
                         f"{us(r.observer_us)} | {count(r.observer_instructions)} | {r.observer_work} | {ekf} | "
                         f"{r.mhe_ms:.1f}{f' ({r.mhe_failed} failed)' if r.mhe_failed else ''} | "
                         f"{r.smape_observer:.2f} / {r.smape_ekf:.2f} ({r.smape_observer / r.smape_ekf:.2f}x) |")
        lines.append("")
        lines += [f"- growth exponent of {label} against nx: {slope:.2f}" for label, slope in self.exponents().items()]
        cross = self.crossover()
        lines.append("- the observer's C step is cheaper than the EKF's (the faster form) "
                     + ("at no size measured" if cross is None else f"from nx = {cross} on"))
        return "\n".join(lines)

    def plot(self, path: Path, *, stamp: Optional[provenance.Stamp] = None) -> Path:
        """Log-log PNG of the costs against nx, and the accuracy ratio."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        nx = np.array([r.nx for r in self.rows], dtype=float)
        fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.5))
        series = {"observer C step (us)": [r.observer_us for r in self.rows],
                  **{f"EKF C step, {f} (us)": [r.ekf_us[f] for r in self.rows] for f in EKF_FORMS},
                  "MHE solve (us)": [1e3 * r.mhe_ms for r in self.rows],
                  "training per simulated s (us)": [1e6 * r.train_per_simulated_s for r in self.rows]}
        slopes = self.exponents()
        for (label, values), slope in zip(series.items(), [slopes.get(k) for k in ("observer C step",
                                          *(f"EKF C step ({f})" for f in EKF_FORMS), "MHE solve",
                                          "training per simulated second")]):
            ax.loglog(nx, values, "o-", label=label + ("" if slope is None else f", slope {slope:.2f}"))
        ax.set(xlabel="nx (states)", ylabel="time", title="cost against plant size (log-log)")
        ax.legend(fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
        bx.semilogx(nx, [r.smape_observer / r.smape_ekf for r in self.rows], "o-")
        bx.axhline(1.0, color="gray", ls=":")
        bx.set(xlabel="nx (states)", ylabel="SMAPE observer / EKF", title="accuracy against the EKF")
        for axis in (ax, bx):
            axis.set_xticks(nx, [str(int(v)) for v in nx])
            axis.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        fig.tight_layout()
        fig.savefig(path, dpi=110, metadata=provenance.png_metadata(stamp or provenance.stamp()))
        plt.close(fig)
        return path


def _bank_config(system: System, runs: int, epochs: int, T: float):
    from ...train import default_config

    config = default_config(system.name, "bank")
    return replace(config, rollouts=replace(config.rollouts, n_traj=runs, T=T),
                   decoder=replace(config.decoder, loop=replace(config.decoder.loop, epochs=epochs)))


def _network_work(obs: KKLObserver) -> int:
    """Multiply-adds of one observer step: the latent update (dense, as the exact discretisation
    writes it) and the decoder's layers."""
    sizes = obs.model.spec.architecture.decoder.sizes
    return obs.nz * (obs.nz + 2 * obs.ny + obs.nu + 1) + sum(a * b for a, b in zip(sizes, sizes[1:]))


def _loop_source(name: str, inputs: Sequence[int], outputs: Sequence[int], feedback: Sequence[tuple[int, int]],
                 start: Optional[int]) -> str:
    """A timing loop of ``name_step``: inputs filled with small values (or input 0 from ``name_start``
    of a zero ``y``, of size ``start``), the outputs in ``feedback`` copied back to their inputs."""
    decls = [f"static casadi_real a{i}[{n}];" for i, n in enumerate(inputs)]
    decls += [f"static casadi_real r{j}[{n}];" for j, n in enumerate(outputs)]
    init = [f"  for (i = 0; i < {n}; i++) a{k}[i] = 0.1 * ((i % 5) - 2) / 2.0;" for k, n in enumerate(inputs)]
    if start is not None:
        decls.append(f"static casadi_real y0[{start}];")
        init += ["  arg[0] = y0; res[0] = a0;", f"  if ({name}_start(arg, res, iw, work, 0)) return 1;"]
    init += [f"  arg[{k}] = a{k};" for k in range(len(inputs))] + [f"  res[{j}] = r{j};" for j in range(len(outputs))]
    back = [f"      memcpy(a{k}, r{j}, sizeof a{k});" for j, k in feedback]
    return loop_source(name, decls, init, back, "a0")


@dataclass(frozen=True)
class _Loop:
    label: str
    binary: Path
    compile_s: float


def _time_loops(loops: Sequence[_Loop], repeat: int, valgrind: Optional[str]) -> tuple[dict, dict]:
    """Seconds per step (the fastest of ``repeat`` runs of about 2 ms, the loops taking turns) and
    callgrind's instructions per step."""
    steps = {loop.label: max(1, round(_RUN_SECONDS / max(_run_loop(loop.binary, 1, 3)[0], 1e-9))) for loop in loops}
    best: dict = {}
    for _ in range(5):
        for loop in loops:
            seconds = _run_loop(loop.binary, steps[loop.label], max(1, repeat // 5))[0]
            best[loop.label] = min(best.get(loop.label, seconds), seconds)
    counts = {loop.label: _callgrind(valgrind, loop.binary, 5) for loop in loops} if valgrind else {}
    return best, counts


def _c_steps(obs: KKLObserver, ekf: EKF, build: Path, gcc: str, flags: tuple, ekf_flags: tuple, repeat: int,
             valgrind: Optional[str]) -> tuple[dict, dict, dict]:
    loops = []
    files = generate_c(obs, build / "observer", "obs_bench")
    rows, cols = obs.memory_shape
    loop_c = build / "observer" / "loop.c"
    loop_c.write_text(_loop_source("obs_bench", [obs.nz, rows * cols, obs.ny, obs.ny, obs.nu],
                                   [obs.nz, rows * cols, obs.nx], [(0, 0), (1, 1)], None))
    seconds = _compile(gcc, [files[0], loop_c], build / "observer" / "loop", flags)
    loops.append(_Loop("observer", build / "observer" / "loop", seconds))
    ns = ekf.system.nx * (ekf.system.nx + 1)
    for form in EKF_FORMS:
        folder = build / f"ekf_{form}"
        files = ekf.generate_c(folder, "ekf_bench", form=form)
        loop_c = folder / "loop.c"
        loop_c.write_text(_loop_source("ekf_bench", [ns, ekf.system.nu + ekf.system.ny], [ns], [(0, 0)],
                                       ekf.system.ny))
        seconds = _compile(gcc, [files[0], loop_c], folder / "loop", ekf_flags)
        loops.append(_Loop(form, folder / "loop", seconds))
    best, counts = _time_loops(loops, repeat, valgrind)
    return best, counts, {loop.label: loop.compile_s for loop in loops}


def bench_scaling(sizes: Sequence[int] = (1, 2, 4, 8, 16, 32), *, runs: int = 200, epochs: int = 10,
                  T: float = 50.0, trials: int = 10, mhe_steps: int = 40, mhe_horizon: int = 10,
                  repeat: int = 50, flags: Sequence[str] = DEFAULT_FLAGS, ekf_flags: Sequence[str] = EKF_FLAGS,
                  callgrind: Optional[bool] = None, threads: int = 1, seed: int = 0, out: Optional[Path] = None,
                  progress: bool = True, stamp: Optional[provenance.Stamp] = None, overwrite: bool = False,
                  argument: str = "out") -> ScalingResult:
    """Measure the costs and the accuracy on chains of ``n`` oscillators for every ``n`` in ``sizes``.

    Parameters
    ----------
    sizes : sequence of int
        Chain lengths ``n`` (``nx = 2 n``).
    runs, epochs, T : int, int, float
        The observer's training budget: ``runs`` noisy runs of ``T`` seconds, ``epochs`` epochs
        (the recipe's filter bank and decoder otherwise).
    trials : int
        Noisy trials (docs/protocol.md noise, 50 s, square inputs of the ``id`` ranges, another seed
        than the protocol's) on which the observer and the EKF are scored (CasADi VM both).
    mhe_steps, mhe_horizon : int
        Samples of the first trial the MHE estimates (its solve time is their mean), and its window.
    repeat : int
        Timed runs per C step.
    flags, ekf_flags : sequence of str
        gcc flags of the observer's C (default :data:`kklcasadi.observer.codegen.DEFAULT_FLAGS`)
        and of the EKF's (:data:`EKF_FLAGS`).
    callgrind : bool, optional
        Count instructions with valgrind (default: when it is installed).
    threads : int
        Torch threads of the training.
    out : Path, optional
        Write ``scaling.md``, ``scaling.json`` (the rows) and ``scaling.png`` there, as one; where one of them
        exists it is refused before any work (:class:`FileExistsError` naming ``argument``), unless ``overwrite``.
    progress : bool
        Print each size's row as it is measured.
    stamp : kklcasadi.provenance.Stamp, optional
        The provenance of the files in ``out`` (default: this process's, with ``seed``).
    overwrite : bool
        Replace the files of an earlier run in ``out``.
    argument : str
        Named in the errors about ``out`` (the command line's ``--out``).

    Returns
    -------
    ScalingResult
    """
    from ...train import train_observer

    flags, ekf_flags = check_flags(flags), check_flags(ekf_flags)
    if positive_int(mhe_steps, "mhe_steps") <= positive_int(mhe_horizon, "mhe_horizon"):
        raise error("mhe_steps", f"more samples than the MHE's horizon ({mhe_horizon}): its solve time is timed "
                    "once the window is full", mhe_steps)
    gcc = shutil.which("gcc")
    if gcc is None:
        raise RuntimeError("bench scaling times C steps and needs gcc, which is not on PATH")
    valgrind = shutil.which("valgrind") if callgrind is not False else None
    if out is not None and not overwrite:    # before any training: the files are never written over
        refuse_existing({Path(out) / f"scaling.{ext}": argument for ext in ("md", "json", "png")})
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        # a first, untimed training: torch's and CasADi's one-off start-up costs stay out of the first size
        train_observer(oscillator_chain(1), "bank", Path(tmp) / "warm-up",
                       config=_bank_config(oscillator_chain(1), 8, 1, 50.0), progress=False, threads=threads)
        for n in sizes:
            plant = oscillator_chain(n)
            work = Path(tmp) / plant.name
            t0 = time.perf_counter()
            train_observer(plant, "bank", work / "bank", config=_bank_config(plant, runs, epochs, T), seed=seed,
                           progress=False, threads=threads)
            train_s = time.perf_counter() - t0
            obs = load_observer(work / "bank", system=plant)
            ekf = EKF(plant, obs.dt)
            best, counts, compile_s = _c_steps(obs, ekf, work / "c", gcc, flags, ekf_flags, repeat, valgrind)
            rng = np.random.default_rng([seed, 77, n])
            batch = simulate_batch(plant, plant.sample_box(trials, rng), [sig.sample("square", rng, "id")
                                                                         for _ in range(trials)], 50.0, obs.dt,
                                   process_std=0.1, measurement_std=0.1,
                                   seed=np.random.SeedSequence([seed, 78, n]).spawn(trials))
            ok = batch.ok
            smape_obs = float(np.mean(metrics.smape(batch.x[ok], obs.simulate(batch.t, batch.y[ok], batch.u[ok]).xhat)))
            smape_ekf = float(np.mean(metrics.smape(batch.x[ok], ekf.simulate(batch.t, batch.y[ok], batch.u[ok]).xhat)))
            mhe = MHE(plant, obs.dt, horizon=mhe_horizon)
            k = min(mhe_steps, batch.t.size)
            run = mhe.simulate(batch.t[:k], batch.y[ok][0, :k], batch.u[ok][0, :k])
            row = ScalingRow(n, plant.nx, plant.ny, obs.nz, train_s, runs * T, 1e6 * best["observer"],
                             counts.get("observer"), _network_work(obs), compile_s["observer"],
                             {f: 1e6 * best[f] for f in EKF_FORMS}, {f: counts.get(f) for f in EKF_FORMS},
                             {f: compile_s[f] for f in EKF_FORMS},
                             1e3 * float(np.mean(run.stats.solve_time[:, mhe_horizon:])), run.stats.n_failed,
                             smape_obs, smape_ekf)
            rows.append(row)
            if progress:                    # the header with the first row, then a row per size
                lines = ScalingResult([row]).table().split("\n\n")[0].splitlines()
                print("\n".join(lines if len(rows) == 1 else lines[2:]), flush=True)
    result = ScalingResult(rows, {"runs": runs, "epochs": epochs, "T": T, "trials": trials, "mhe_steps": mhe_steps,
                                  "mhe_horizon": mhe_horizon, "flags": list(flags), "ekf_flags": list(ekf_flags)})
    if out is not None:
        stamp = stamp or provenance.stamp(seeds={"training_and_trials": seed})
        with staged(out, overwrite=overwrite, argument=argument) as stage:  # the table, the record and the plot as one
            (stage / "scaling.md").write_text(provenance.markdown(result.table() + "\n", stamp))
            (stage / "scaling.json").write_text(json.dumps(provenance.json_record(
                {"settings": result.settings, "rows": [asdict(r) for r in rows]}, stamp), indent=1) + "\n")
            result.plot(stage / "scaling.png", stamp=stamp)
    return result
