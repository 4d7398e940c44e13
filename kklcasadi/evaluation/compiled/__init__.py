"""Compiled trajectories: observers, the EKF and the particle filter as C, mapped over trials.

The room: :mod:`.shortcuts` (the work a step's inputs alone decide, done once per group of trials that share
them; the injection skipped at ``u = 0``), :mod:`.estimators` (the compiled estimators of the benchmarks, each
bitwise its reference path, the observer's record of estimates, latents and covariances, and :func:`precompile`);
the compiler itself is :mod:`kklcasadi.compiler` (any CasADi Function as a shared library, built once with gcc,
cached on disk, bitwise the VM; below the observer, which compiles its own trajectories). Every public name is
here.
"""

from ...compiler import DEFAULT_FLAGS, Build, Compiler, CompilerWarning, compile_function
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
