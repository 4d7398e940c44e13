"""kklcasadi: learned KKL observers for controlled nonlinear systems, exported to CasADi and C.

The deploy side (systems, signals, simulation, model files, CasADi networks, observer, C code,
EKF) needs casadi, numpy, scipy and python-control only; torch is imported by
:mod:`kklcasadi.train` (and the benchmarks that time torch) alone. ``kc.train`` and the other
submodules listed in :data:`_LAZY` are imported on first use, so ``import kklcasadi`` stays
torch-free.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

from . import data, metrics, signals, systems, variants
from .design import Design
from .observer import Estimate, KKLObserver, load_observer
from .simulate import Trajectory, TrajectoryBatch, simulate, simulate_batch
from .systems import System

#: Submodules reachable as attributes of the package, imported when first used.
_LAZY = ("train", "ekf", "protocol", "report", "codegen", "interop", "modelfile", "casadi_nets",
         "architecture", "mhe", "nmpc", "certificate", "pipelines", "filterbank", "compiled", "trialcache", "pf")
#: Names of those submodules reachable from the package: ``kc.MHE``, ``kc.NMPC``, ``kc.Certificate``
#: (a model's certificate: ``obs.certificate()``).
_LAZY_NAMES = {"MHE": "mhe", "KKLPrimedMHE": "mhe", "NMPC": "nmpc", "Certificate": "certificate",
               "make_inject_model": "observer"}

__all__ = ["System", "Design", "Trajectory", "TrajectoryBatch", "simulate", "simulate_batch",
           "KKLObserver", "Estimate", "load_observer",
           "systems", "signals", "data", "metrics", "variants", "__version__", *_LAZY, *_LAZY_NAMES]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return importlib.import_module(f".{name}", __name__)
    if name in _LAZY_NAMES:
        return getattr(importlib.import_module(f".{_LAZY_NAMES[name]}", __name__), name)
    raise AttributeError(f"module 'kklcasadi' has no attribute {name!r}")
