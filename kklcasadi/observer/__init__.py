"""The observer built from a model file (:mod:`.kkl`), its C code (:mod:`.codegen`), python-control
interop (:mod:`.interop`) and Proposition 1 of the paper as a certificate (:mod:`.certificate`)."""

from .kkl import Estimate, KKLObserver, load_observer

__all__ = ["KKLObserver", "Estimate", "load_observer"]
