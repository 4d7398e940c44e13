"""Compiled trajectories: a CasADi Function as C, built once with gcc and loaded with ``ca.external``.

:class:`Compiler` turns any :class:`casadi.Function` into a shared library: the C source from
:class:`casadi.CodeGenerator`, an optional source post-processing hook, then the C compiler. The
library is cached on disk under the SHA-256 of the source, the compiler and its flags, so a
Function is compiled once per machine; an unchanged Function loads in milliseconds. Without the
compiler the Function runs in the CasADi VM, with a :class:`CompilerWarning`. :meth:`Compiler.build`
separates the CasADi part (the source) from the C compiler's run, so that :func:`precompile` runs
several compilers at once while the caller's thread does other work (simulating trials).

The default flags are portable (``-O3 -ffp-contract=off``, no ``-march=native``): with the same
expression graph the compiled Function returns bitwise the VM's values (``-ffp-contract=off``
keeps compilers from fusing multiply-adds on targets that have FMA).

:class:`CompiledEstimator` is the estimator protocol of the fast benchmark path: an estimator
that gives one trial's estimate as a CasADi Function ``(y (ny, N), u (nu, N), s0) -> xhat (nx, N)``
and its initial state ``s0``; calling it compiles that Function and maps it over the trials on
threads. :func:`observer_estimator` and :func:`ekf_estimator` adapt a
:class:`~kklcasadi.observer.kkl.KKLObserver` and an :class:`~kklcasadi.estimators.ekf.EKF`;
each is bitwise its reference path (``obs.simulate``, ``ekf.simulate``).

The observer's trajectory does only the work that its inputs require (:func:`split_step`): the part
of a step that depends on the input memory alone (the window GRU of ``obs`` and ``dyn`` with the
LoRA factors, the streaming context cell) is evaluated once per sample for every group of trials
that share their inputs (the noise-free and noisy cells of the benchmark, or the trials of the
zero-input regime), and reused while the memory does not change (a constant input, a square wave
between its edges); the model-based injection is skipped where the input is exactly 0, where it
is exactly 0. Every estimate is bitwise what the plain step gives (the same operations on the same
values, in the same order).

The room: :mod:`.compiler` (the compiler and its cache), :mod:`.shortcuts` (the step-graph shortcuts),
:mod:`.estimators` (the observer, the EKF and the particle filter as compiled estimators, and the observer's
record of estimates, latents and covariances).
"""

from .compiler import DEFAULT_FLAGS, Build, Compiler, CompilerWarning, compile_function
from .estimators import (
    GROUP,
    CompiledEKF,
    CompiledEstimator,
    CompiledObserver,
    CompiledRecord,
    ekf_estimator,
    observer_estimator,
    pf_estimator,
    precompile,
)
from .shortcuts import SplitStep, reuse_decoded, skip_at_zero_input, split_step

__all__ = ["Compiler", "CompilerWarning", "Build", "compile_function", "CompiledEstimator", "CompiledObserver",
           "CompiledEKF", "CompiledRecord", "SplitStep", "split_step", "skip_at_zero_input", "reuse_decoded",
           "observer_estimator", "ekf_estimator", "pf_estimator", "precompile", "DEFAULT_FLAGS", "GROUP"]
