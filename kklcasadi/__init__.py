"""kklcasadi: learned KKL observers for controlled nonlinear systems, exported to CasADi and C.

The front door names what a user calls; everything else is reachable by its subpackage, which
follow the data flow (docs/architecture.md):

``plant`` (systems, signals, simulation, design, training data) -> ``train`` (torch) -> ``model``
(files, variants) -> ``nets`` (CasADi networks) -> ``observer`` (observer, C code, interop,
certificate) -> ``estimators`` (EKF, MHE, NMPC) -> ``evaluation`` (protocol, reports, benchmarks)
-> ``cli``.

The deploy side needs casadi, numpy, scipy and python-control only; ``kc.train`` (torch) is
imported on first use, so ``import kklcasadi`` stays torch-free.
"""

from __future__ import annotations

import importlib
from typing import Any

from . import metrics
from .estimate import Estimate
from .estimators import EKF, MHE, NMPC
from .observer import KKLObserver, load_observer
from .observer.codegen import generate_c
from .plant import signals, systems
from .plant.design import Design
from .plant.simulate import Trajectory, TrajectoryBatch, simulate, simulate_batch
from .plant.systems import System
from .version import __version__

__all__ = ["System", "Design", "simulate", "simulate_batch", "Trajectory", "TrajectoryBatch",
           "load_observer", "KKLObserver", "Estimate", "generate_c", "EKF", "MHE", "NMPC",
           "systems", "signals", "metrics", "train", "__version__"]


def __getattr__(name: str) -> Any:
    if name == "train":                       # torch: imported when first used
        return importlib.import_module(".train", __name__)
    raise AttributeError(f"module 'kklcasadi' has no attribute {name!r}")
