"""What a training hook returns: everything the model file needs besides the plant and paths."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from ..model.card import Domain
from ..model.monitor import MonitorSpec
from ..plant.data import LabelReport
from ..plant.design import Design

__all__ = ["Trained"]


@dataclass(frozen=True, eq=False)
class Trained:
    """The outcome of one variant's training hook.

    Attributes
    ----------
    arrays : dict[str, numpy.ndarray]
        Every array of the model file (float64).
    spec
        The variant's typed architecture spec.
    design : Design
        The latent pair ``(A, B)`` the model uses.
    training : dict
        The card's training record (configuration, data sizes, fit summaries).
    histories : dict[str, dict[str, list[float]]]
        Loss histories per stage (written to ``history.json`` / ``history.png``).
    window : int
        Input-window length of the card.
    measurement_std : float
        The noise level the decoder was fit for.
    domain : Domain or None
        Where the maps were trained (states and latents of the training data).
    coverage : LabelReport or None
        How the Phase-1 labels were made and how well they cover the box (methods with Phase-1 labels).
    monitor : MonitorSpec or None
        The decoder-input monitor's card entry (its arrays are in ``arrays``).
    fit_families : dict or None
        The input families the maps were fit on, ``{family: {parameter: (lo, hi)}}``.
    process_std : tuple of float (nx,) or None
        The process-noise std of each state in the training data, where the hook knows it per
        state (else the configuration's ``process_std`` is recorded).
    """

    arrays: dict
    spec: Any
    design: Design
    training: dict
    histories: dict = field(default_factory=dict)
    window: int = 1
    measurement_std: float = 0.0
    domain: Optional[Domain] = None
    coverage: Optional[LabelReport] = None
    monitor: Optional[MonitorSpec] = None
    fit_families: Optional[dict] = None
    process_std: Optional[tuple] = None
