"""C code of the observer step: the generator (:mod:`.generator`), the speed rewrites of CasADi's C
(:mod:`.kernels`) and the C text they use (``templates/*.c``)."""

from .generator import (
    C_FLAGS,
    DEFAULT_FLAGS,
    MATHS,
    MATVECS,
    NATIVE_FLAGS,
    c_targets,
    casadi_source,
    check_c_name,
    check_flags,
    generate_c,
    renamed,
)
from .kernels import FUSED_TOLERANCE, VECTOR_MATH_TOLERANCE, axpy_matvec, fast_kernels, vector_math_c

__all__ = ["generate_c", "c_targets", "casadi_source", "renamed", "check_c_name", "check_flags", "axpy_matvec",
           "fast_kernels", "vector_math_c", "C_FLAGS", "DEFAULT_FLAGS", "NATIVE_FLAGS", "MATVECS", "MATHS",
           "VECTOR_MATH_TOLERANCE", "FUSED_TOLERANCE"]
