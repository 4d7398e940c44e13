"""Model-based estimators and controllers beside the learned observer: the EKF (:mod:`.ekf`), the
moving-horizon estimators (:mod:`.mhe`) and output-feedback NMPC (:mod:`.nmpc`)."""

from .ekf import EKF
from .mhe import MHE, KKLPrimedMHE
from .nmpc import NMPC

__all__ = ["EKF", "MHE", "KKLPrimedMHE", "NMPC"]
