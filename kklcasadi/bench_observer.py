"""Benchmark of one observer step: generated C, the CasADi VM and torch eager, in one run.

:func:`bench_observer_step` times :attr:`KKLObserver.step` (one sample interval: latent update
and decoder) on the same inputs as

* compiled C (:meth:`KKLObserver.generate_c`, ``gcc -O2``): a standalone C loop (the deployment
  cost) and the shared library through ``ca.external`` (adds the Python call overhead),
* the CasADi virtual machine (``Function.call``),
* torch eager (float64, batch 1, no autograd): the same networks from
  :mod:`kklcasadi.train.nets` (``from_arrays``) and the same exact/RK4 update written in torch,

checks that every implementation returns the CasADi VM's result, and prints absolute times and
ratios. Nothing here asserts a speed. Torch is imported inside the function only.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import casadi as ca
import numpy as np

from .architecture import DECODER, HYPER, lora_target_shapes
from .bench import Timing, time_call
from .codegen import C_FLAGS
from .observer import KKLObserver, load_observer
from .rk4 import rk4_step
from .systems import System

__all__ = ["bench_observer_step"]

_NAME = "kkl_bench"
_LOOP = r"""#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "__NAME__.h"

static casadi_real z[__MACRO___NZ], z_next[__MACRO___NZ];
static casadi_real win[__MACRO___WINDOW * __MACRO___NU], win_next[__MACRO___WINDOW * __MACRO___NU];
static casadi_real y[__MACRO___NY], y_next[__MACRO___NY], u_next[__MACRO___NU], xhat[__MACRO___NX];
static const casadi_real* arg[__MACRO___SZ_ARG];
static casadi_real* res[__MACRO___SZ_RES];
static casadi_int iw[__MACRO___SZ_IW + 1];
static casadi_real work[__MACRO___SZ_W + 1];

int main(int argc, char** argv) {
  long i, n = argc > 1 ? atol(argv[1]) : 1000;
  struct timespec t0, t1;
  double checksum = 0;
  for (i = 0; i < __MACRO___WINDOW * __MACRO___NU; i++) win[i] = 0.3 * ((i % 7) - 3) / 3.0;
  for (i = 0; i < __MACRO___NY; i++) { y[i] = 0.2; y_next[i] = 0.25; }
  for (i = 0; i < __MACRO___NU; i++) u_next[i] = -0.4;
  arg[0] = z; arg[1] = win; arg[2] = y; arg[3] = y_next; arg[4] = u_next;
  res[0] = z_next; res[1] = win_next; res[2] = xhat;
  clock_gettime(CLOCK_MONOTONIC, &t0);
  for (i = 0; i < n; i++) {
    if (__NAME___step(arg, res, iw, work, 0)) return 1;
    memcpy(z, z_next, sizeof z);
    memcpy(win, win_next, sizeof win);
    checksum += xhat[0];
  }
  clock_gettime(CLOCK_MONOTONIC, &t1);
  printf("%.9e %.17g\n", ((t1.tv_sec - t0.tv_sec) + 1e-9 * (t1.tv_nsec - t0.tv_nsec)) / n,
         checksum);
  return 0;
}
"""


def _torch_step(observer: KKLObserver) -> Optional[Callable[..., tuple[Any, Any, Any]]]:
    """The observer step in torch eager, or None for a model-based term (the plant is CasADi)."""
    import torch

    from .train.nets import MLP, LoRAHyperNet, ObsInjection, mlp_forward_lora

    if observer.model_based_injection:
        return None
    # writable copies: the loaded arrays are read-only, which torch.as_tensor warns about
    arrays = {name: np.array(value) for name, value in observer.model.arrays.items()}
    arch = observer.model.spec.architecture
    decoder = MLP.from_arrays(arrays, DECODER, arch.decoder)
    if observer.method == "dyn":
        hyper = LoRAHyperNet.from_arrays(arrays, HYPER, arch.hyper,
                                         lora_target_shapes(arch.encoder, arch.decoder), nu=observer.nu)
        n_encoder = len(arch.encoder.layer_shapes)

        def decode(z: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
            factors = hyper(w[None])[n_encoder:]
            return mlp_forward_lora(decoder, z[None], factors, hyper.scale)[0]
    else:
        def decode(z: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
            return decoder(z)

    if observer.foh_matrices is not None:
        ad, gy, gy_next = (torch.as_tensor(m) for m in observer.foh_matrices)

        def advance(z: torch.Tensor, w: torch.Tensor, y: torch.Tensor,
                    y_next: torch.Tensor) -> torch.Tensor:
            return ad @ z + gy @ y + gy_next @ y_next
    else:
        a, b = torch.as_tensor(np.array(observer.A)), torch.as_tensor(np.array(observer.B))
        injection = (ObsInjection.from_arrays(arrays, "", arch.obs) if observer.method == "obs"
                     else None)

        def advance(z: torch.Tensor, w: torch.Tensor, y: torch.Tensor,
                    y_next: torch.Tensor) -> torch.Tensor:
            u = w[-1]
            if injection is not None:                       # the context once per step
                context = injection.proj(injection.context(w[None]))

            def field(s: float, zz: torch.Tensor) -> torch.Tensor:
                zdot = a @ zz + b @ (y + s * (y_next - y))
                if injection is not None:
                    gain = injection.gain_net(torch.cat([zz[None], context], dim=-1))
                    zdot = zdot + gain.view(observer.nz, observer.nu) @ u
                return zdot

            return rk4_step(field, z, observer.dt, observer.substeps)

    def step(z: torch.Tensor, w: torch.Tensor, y: torch.Tensor, y_next: torch.Tensor,
             u_next: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        with torch.inference_mode():
            z_next = advance(z, w, y, y_next)
            w_next = torch.cat([w[1:], u_next[None]])
            return z_next, w_next, decode(z_next, w_next)

    return step


def _check(label: str, outputs: Sequence[Any], reference: Sequence[np.ndarray],
           tol: float = 1e-9) -> float:
    error = max(float(np.max(np.abs(np.asarray(out, dtype=float).reshape(ref.shape) - ref)))
                for out, ref in zip(outputs, reference))
    if not error <= tol:
        raise RuntimeError(f"{label}: the step differs from the CasADi VM by {error:.3g} (> {tol});"
                           " the implementations disagree, so the timings would be meaningless.")
    return error


def _compile(gcc: str, sources: Sequence[Path], output: Path, *extra: str) -> float:
    start = time.perf_counter()
    result = subprocess.run([gcc, *C_FLAGS, *extra, *map(str, sources), "-o", str(output), "-lm"],
                            capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"gcc failed on the generated code:\n{result.stderr}")
    return time.perf_counter() - start


def bench_observer_step(model_dir: str | os.PathLike, *, system: Optional[System] = None,
                        n_calls: int = 1000, repeat: int = 5) -> list[Timing]:
    """Time one observer step in C, in the CasADi VM and in torch eager; print times and ratios.

    Parameters
    ----------
    model_dir : str or path-like
        A model directory (any method; torch eager is skipped for a model-based injection term,
        whose plant exists in CasADi only).
    system : System, optional
        The plant, as for :func:`kklcasadi.load_observer`.
    n_calls : int
        Steps per timed run.
    repeat : int
        Timed runs per implementation; the fastest is kept.

    Returns
    -------
    list of Timing
        ``items`` = steps in the run, so ``seconds / items`` is the time per step; the gcc
        compile (``items = 1``) comes first when gcc is installed.
    """
    obs = load_observer(model_dir, system=system)
    rng = np.random.default_rng(0)
    args = [0.5 * rng.normal(size=size) for size in
            (obs.nz, (obs.window, obs.nu), obs.ny, obs.ny, obs.nu)]   # z, w, y, y_next, u_next
    dm_args = [ca.DM(a) for a in args]
    reference = [np.array(v) for v in obs.step.call(dm_args)]
    checks: dict[str, float] = {}
    timings: list[Timing] = []
    runs: list[Timing] = []
    print(f"observer step: {obs!r}")

    gcc = shutil.which("gcc")
    if gcc is None:
        print("gcc not found: skipping the compiled C timings")
    else:
        with tempfile.TemporaryDirectory() as tmp:
            build = Path(tmp)
            files = obs.generate_c(build, _NAME)
            library = build / f"lib{_NAME}.so"
            timings.append(Timing(f"gcc {' '.join(C_FLAGS[-1:])} compile (shared library)",
                                  _compile(gcc, files[:1], library, "-fPIC", "-shared"), 1))
            external = ca.external(f"{_NAME}_step", str(library))
            checks["C (ca.external)"] = _check("C", external.call(dm_args), reference, 1e-12)
            runs.append(time_call("C via ca.external (Function.call)",
                                  lambda: [external.call(dm_args) for _ in range(n_calls)],
                                  n_calls, repeat))
            loop = build / "loop.c"
            loop.write_text(_LOOP.replace("__NAME__", _NAME).replace("__MACRO__", _NAME.upper()))
            _compile(gcc, [files[0], loop], build / "loop")
            per_step = min(float(subprocess.run([str(build / "loop"), str(n_calls)],
                                                capture_output=True, text=True,
                                                check=True).stdout.split()[0])
                           for _ in range(repeat))
            runs.insert(0, Timing("C standalone loop", per_step * n_calls, n_calls))

    runs.append(time_call("CasADi VM (Function.call)",
                          lambda: [obs.step.call(dm_args) for _ in range(n_calls)], n_calls,
                          repeat))

    step = _torch_step(obs)
    if step is None:
        print("torch eager: skipped (the model-based term needs the CasADi plant)")
    else:
        import torch

        tensors = [torch.as_tensor(a) for a in args]
        checks["torch eager"] = _check("torch eager", [t.numpy() for t in step(*tensors)],
                                       reference)
        runs.append(time_call(f"torch eager ({torch.get_num_threads()} threads)",
                              lambda: [step(*tensors) for _ in range(n_calls)], n_calls, repeat))

    for label, error in checks.items():
        print(f"{label:<44s} max |difference| from the CasADi VM: {error:.2e}")
    for timing in timings:
        print(f"{timing.label:<44s} {timing.seconds:10.2f} s")
    base = runs[0]
    for run in runs:
        print(f"{run.label:<44s} {run.seconds / run.items * 1e6:10.2f} us/step   "
              f"ratio to {base.label}: {run.seconds / run.items / (base.seconds / base.items):8.2f}")
    return timings + runs
