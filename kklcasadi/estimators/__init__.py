"""Model-based estimators and controllers beside the learned observer: the EKF (:mod:`.ekf`), the
bootstrap particle filter (:mod:`.pf`, the near-optimal reference), the moving-horizon estimators
(:mod:`.mhe`), output-feedback NMPC (:mod:`.nmpc`), and the baselines where the model is off: the
EKF tuned on tuning trials (:mod:`.tuned`), the augmented EKF and the particle filter over states and
parameters (:mod:`.augmented`)."""

from .augmented import AugmentedEKF, ParameterPF
from .ekf import EKF
from .mhe import MHE, KKLPrimedMHE
from .nmpc import NMPC
from .pf import ParticleFilter
from .tuned import TunedEKF

__all__ = ["EKF", "ParticleFilter", "MHE", "KKLPrimedMHE", "NMPC", "TunedEKF", "AugmentedEKF", "ParameterPF"]
