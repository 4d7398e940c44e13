"""The autonomous observer and the curriculum baseline: ``zdot = A z + B y``, ``xhat = T*(z)``."""

from __future__ import annotations

from .base import Variant

__all__ = ["Autonomous", "Curriculum"]


class Autonomous(Variant):
    """Phase 1: T and T* trained on ``u = 0`` (the paper's autonomous baseline)."""

    name = "autonomous"
    summary = "Phase 1: zdot = A z + B y, xhat = T*(z); T, T* trained at u = 0"
    needs_base = False
    input_free = True
    trains = True


class Curriculum(Variant):
    """The curriculum baseline: T and T* fine-tuned on staged input-driven data, run as autonomous."""

    name = "curriculum"
    summary = "baseline: T, T* fine-tuned on staged non-autonomous data, run as autonomous"
    input_free = True
    trains = True
