"""Model-based estimators and controllers beside the learned observer: the EKF (:mod:`.ekf`), the
bootstrap particle filter (:mod:`.pf`, the near-optimal reference), the moving-horizon estimators
(:mod:`.mhe`) and output-feedback NMPC (:mod:`.nmpc`)."""

from .ekf import EKF
from .mhe import MHE, KKLPrimedMHE
from .nmpc import NMPC
from .pf import ParticleFilter

__all__ = ["EKF", "ParticleFilter", "MHE", "KKLPrimedMHE", "NMPC"]
