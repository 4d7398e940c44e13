"""kklcasadi: learned KKL observers for controlled nonlinear systems, exported to CasADi and C.

The deploy side (systems, signals, simulation, model files, export, observer) needs casadi, numpy,
scipy and python-control only; torch is imported by :mod:`kklcasadi.train` alone.
"""

__version__ = "0.1.0"

from . import data, metrics, signals, systems
from .design import Design
from .observer import Estimate, KKLObserver, load_observer
from .simulate import Trajectory, TrajectoryBatch, simulate, simulate_batch
from .systems import System

__all__ = ["System", "Design", "Trajectory", "TrajectoryBatch", "simulate", "simulate_batch",
           "KKLObserver", "Estimate", "load_observer",
           "systems", "signals", "data", "metrics", "__version__"]
