"""Rewriting CasADi's generated C for speed: the dense mat-vec products as fixed-size kernels in column
(axpy) order (bitwise CasADi's sums), exp and tanh as branch-free C99 that vectorises (within 3 ulp),
and AVX2 versions of both picked at run time on x86 (see :func:`kklcasadi.observer.codegen.generate_c`).

The C helpers are the files of ``templates/``; the kernels are written per matrix shape here.
Used by :func:`~kklcasadi.observer.codegen.generate_c` and by the compiled evaluation path
(:class:`kklcasadi.evaluation.compiled.Compiler`'s ``postprocess``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Callable, Sequence

import casadi as ca
import numpy as np

from ...validation import one_of

__all__ = ["axpy_matvec", "fast_kernels", "vector_math_c", "rewrite", "single_precision", "template",
           "VECTOR_MATH_TOLERANCE", "FUSED_TOLERANCE"]

#: With ``math="vector"`` the C step and the CasADi VM agree to
#: ``|C - VM| <= VECTOR_MATH_TOLERANCE * (1 + |VM|)`` (tested on every method).
VECTOR_MATH_TOLERANCE = 1e-14
#: With :func:`fast_kernels` (the evaluation path: the vector exp/tanh and, where the CPU has AVX2 and FMA,
#: fused multiply-adds) the estimates and the VM's agree to ``|C - VM| <= FUSED_TOLERANCE * (1 + |VM|)``: each
#: fused multiply-add rounds once where the VM rounds twice, and over a 256-wide layer the sums differ by more than
#: the vector exp/tanh alone (the Duffing protocol's largest difference 2.0e-14, ``kklcasadi bench protocol``).
FUSED_TOLERANCE = 1e-12

_TEMPLATES = Path(__file__).resolve().parent / "templates"


def template(name: str) -> str:
    """The C text of ``templates/<name>.c``."""
    return (_TEMPLATES / f"{name}.c").read_text()


# CasADi 3.x writes every dense matrix-vector product as this call (sizes as literals, tr = 0).
_MTIMES_CALL = re.compile(r"casadi_mtimes_dense\(([^,();]+), (\d+), (\d+), ([^,();]+), (\d+), "
                          r"([^,();]+), 0\);")
_MTIMES_DEF = re.compile(r"^void casadi_mtimes_dense\(.*?^}\n", re.MULTILINE | re.DOTALL)
# ... and an element-wise exp or tanh of a vector as this loop; scalars as plain calls (the
# generated comments show the operands as "@3", which the last pattern skips).
_MATH_LOOP = re.compile(r"for \(i=0, rr=([^,();]+), cs=([^,();]+); i<(\d+); \+\+i\) "
                        r"\*rr\+\+ = (exp|tanh)\( \*cs\+\+ \);")
_MATH_CALL = re.compile(r"\b(exp|tanh)\((?!@)")
# The C library's double functions that CasADi's C may call, each with a float version named <name>f.
_LIBM = ("exp", "expm1", "log", "log1p", "log10", "sqrt", "cbrt", "pow", "fabs", "fmin", "fmax", "fmod", "floor",
         "ceil", "copysign", "erf", "sin", "cos", "tan", "asin", "acos", "atan", "atan2", "sinh", "cosh", "tanh",
         "asinh", "acosh", "atanh")
_LIBM_CALL = re.compile(rf"\b({'|'.join(_LIBM)})\((?!@)")
# A C floating constant as CasADi writes them (no sign, no suffix): 2., 0.5, 5.0000000000000000e-01, 1e-05.
_FLOAT_LITERAL = re.compile(r"(?<![\w.])(?:\d+\.\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?|\d+[eE][+-]?\d+)(?![\w.])")
_REAL_DOUBLE, _INT_LONG = "#define casadi_real double\n", "#define casadi_int long long int\n"
_COMMENT = re.compile(r"(/\*.*?\*/|//[^\n]*)", re.DOTALL)
_INT_TYPE = re.compile(r"^#ifndef casadi_int\n#define casadi_int [^\n]*\n#endif\n", re.MULTILINE)
_MATH_INCLUDE = "#include <math.h>\n"

#: Outputs per register block of the axpy kernels (8 SSE2 or 4 AVX2 registers).
_BLOCK = 16


# The helpers of templates/ are C text. Functions named KKLCV_* come in versions: portable (kklc_c_*)
# and, under KKLC_DISPATCH, an AVX2 copy (kklc_avx2_*); the kklc_* entry points pick one.


def _accumulators(rows: int, width: int) -> tuple[int, range]:
    """The vector accumulators (count) and the rows summed in scalars of a block of ``rows``."""
    vectors = rows // width if width > 1 else 0
    return vectors, range(vectors * width, rows)


def vector_math_c(functions: Sequence[str] = ("exp", "tanh")) -> str:
    """The portable C99 source of kklcasadi's vectorisable exp and tanh, for use in other C.

    It defines ``static void kklc_vexp(const casadi_real* x, casadi_int n, casadi_real* y)``
    and ``kklc_vtanh`` (same signature): ``y[i] = exp(x[i])`` or ``tanh(x[i])`` for ``i < n``,
    where ``y`` is ``x`` or does not overlap it. Include ``<math.h>``, ``<stdint.h>`` and
    ``<string.h>`` and define ``casadi_real`` as ``double`` and ``casadi_int`` before it.

    Parameters
    ----------
    functions : sequence of {"exp", "tanh"}
        The functions to define (others would be unused static functions).

    Returns
    -------
    str
    """
    if isinstance(functions, str) or not isinstance(functions, Sequence):
        raise TypeError(f"functions: expected a sequence such as ('exp', 'tanh'), received "
                        f"{type(functions).__name__}.")
    for function in functions:
        one_of(function, "functions", ("exp", "tanh"))
    code = template("math_core") + "".join(text for function, text in
                                (("exp", template("vector_exp")), ("tanh", template("vector_tanh")))
                                if function in functions)
    return template("math_constants") + code.replace("KKLCV_", "kklc_")


def _block_code(rows: int, ncol: int, nrow: int, width: int, indent: str, fused: bool = False) -> list[str]:
    """``z[j..j+rows-1] += x[j.., :] y``, with ``rows // width`` vector accumulators of
    ``width`` doubles (``kklc_v4``, when ``width`` is 4) and scalars for the rest (``j``,
    ``x``, ``y``, ``z``, ``xk``, ``k`` in scope). Every sum runs over ``k`` in ascending order
    from ``z``'s value, as casadi_mtimes_dense's does: the same results bit for bit, unless
    ``fused``, where the vector accumulators take each product and sum in one fused
    multiply-add (one rounding instead of two: within :data:`FUSED_TOLERANCE`, not bitwise)."""
    vectors, scalars = _accumulators(rows, width)
    lines = [f"{indent}memcpy(&v{r}, z + j + {r * width}, sizeof yv);" for r in range(vectors)]
    lines += [f"{indent}a{r} = z[j + {r}];" for r in scalars]
    lines.append(f"{indent}for (k = 0, xk = x + j; k < {ncol}; ++k, xk += {nrow}) {{")
    lines.append(f"{indent}  yk = y[k];")
    if vectors:
        lines.append(f"{indent}  yv = (kklc_v4) {{yk, yk, yk, yk}};")
    for r in range(vectors):
        lines += [f"{indent}  memcpy(&w{r}, xk + {r * width}, sizeof yv);",
                  f"{indent}  v{r} = kklc_fma4(w{r}, yv, v{r});" if fused else f"{indent}  v{r} += w{r} * yv;"]
    lines += [f"{indent}  a{r} += xk[{r}] * yk;" for r in scalars]
    lines.append(f"{indent}}}")
    lines += [f"{indent}memcpy(z + j + {r * width}, &v{r}, sizeof yv);" for r in range(vectors)]
    lines += [f"{indent}z[j + {r}] = a{r};" for r in scalars]
    return lines


def _matvec_kernel(name: str, nrow: int, ncol: int, ncol_y: int, version: str) -> str:
    """C source of ``KKLCV_<name>(x, y, z)``: ``z += x y`` for a dense ``nrow``-by-``ncol``
    ``x`` (column-major), exactly as ``casadi_mtimes_dense(x, nrow, ncol, y, ncol_y, z, 0)``
    when ``z`` overlaps neither ``x`` nor ``y``. A block of outputs is summed in registers:
    scalars that compilers pair into SSE2 vectors in the portable version (``"c"``), explicit
    AVX2 vectors (gcc vector extensions) in the ``"avx2"`` version, and the same with fused
    multiply-adds in the ``"fma"`` version (not bitwise: see :func:`_block_code`)."""
    width = 1 if version == "c" else 4
    fused = version == "fma"
    block = min(_BLOCK, nrow)
    tail = nrow % block
    n_vectors, scalars = _accumulators(block, width)
    if tail:
        scalars = sorted(set(scalars) | set(_accumulators(tail, width)[1]))
    declarations = [f"  casadi_real yk{''.join(f', a{r}' for r in scalars)};"]
    if n_vectors:
        vectors = ", ".join(f"v{r}, w{r}" for r in range(n_vectors))
        declarations.append(f"  kklc_v4 yv, {vectors};")
    lines = [f"/* z += x*y, x {nrow}x{ncol} dense column-major, y {ncol}x{ncol_y}: every output "
             "summed over k in",
             " * ascending order (casadi_mtimes_dense's), a block of outputs in registers */",
             f"static void KKLCV_{name}(const casadi_real* x, const casadi_real* y, "
             "casadi_real* z) {",
             "  casadi_int i, j, k;",
             "  const casadi_real* xk;",
             *declarations,
             f"  for (i = 0; i < {ncol_y}; ++i, y += {ncol}, z += {nrow}) {{",
             f"    for (j = 0; j + {block} <= {nrow}; j += {block}) {{",
             *_block_code(block, ncol, nrow, width, "      ", fused),
             "    }"]
    if tail:
        lines += [f"    j = {nrow - tail};", *_block_code(tail, ncol, nrow, width, "    ", fused)]
    lines += ["  }", "}"]
    return "\n".join(lines) + "\n"


def _entry(name: str, params: str, args: str, dispatch: bool, guard: str = "") -> str:
    """The kklc_<name> entry point: the AVX2 version where the CPU has it, else the portable."""
    avx2 = (f"#ifdef KKLC_DISPATCH\n  if (KKLC_HAS_AVX2) {{\n"
            f"    kklc_avx2_{name}({args});\n    return;\n  }}\n#endif\n") if dispatch else ""
    return (f"\nstatic void kklc_{name}({params}) {{\n{guard}{avx2}"
            f"  kklc_c_{name}({args});\n}}\n")


def _versions(code: Callable[[str], str], dispatch: bool, fused: bool) -> str:
    """``code(version)``'s KKLCV_ functions as the portable kklc_c_ and, under KKLC_DISPATCH, as
    the AVX2 kklc_avx2_ functions (where ``fused``, the mat-vec kernels' and the exp/tanh polynomials'
    multiply-adds fused: ``KKLC_MADD(a, b, c)``, ``a * b + c`` elsewhere, as C99's ``fma``)."""
    portable = code("c").replace("KKLCV_", "kklc_c_")
    if not dispatch:
        return portable
    avx2 = code("fma" if fused else "avx2")
    if fused:
        avx2 = avx2.replace("KKLC_MADD(", "fma(")
    avx2 = (avx2.replace("KKLCV_", "kklc_avx2_")
            .replace("\nstatic ", "\nKKLC_AVX2 static "))
    return f"{portable}\n#ifdef KKLC_DISPATCH\n{avx2}#endif\n"


def rewrite(source: str, matvec: bool, math: bool, dispatch: bool, *, fused: bool = False) -> str:
    """Replace the dense mat-vec calls by axpy kernels (``matvec``, bitwise equal) and the C
    library's exp and tanh by vectorisable ones (``math``, within 3 ulp); ``dispatch`` adds the
    AVX2 versions, ``fused`` (with ``dispatch``) makes their mat-vec kernels sum with fused
    multiply-adds, used where the CPU has AVX2 and FMA (within :data:`VECTOR_MATH_TOLERANCE`, not
    bitwise). Returns ``source`` unchanged when there is nothing to replace."""
    shapes: dict[tuple[int, int, int], str] = {}
    used: set[str] = set()
    scalar: set[str] = set()

    def mtimes(match: re.Match) -> str:
        x, nrow, ncol, y, ncol_y, z = match.groups()
        shape = (int(nrow), int(ncol), int(ncol_y))
        name = shapes.setdefault(shape, "mv_" + "x".join(map(str, shape)))
        return f"kklc_{name}({x}, {y}, {z});"

    def loop(match: re.Match) -> str:
        rr, cs, n, function = match.groups()
        used.add(function)
        return f"kklc_v{function}({cs}, {n}, {rr});"

    def call(match: re.Match) -> str:
        used.add(match.group(1))
        scalar.add(match.group(1))
        return f"kklc_{match.group(1)}("

    if matvec:
        source = _MTIMES_CALL.sub(mtimes, source)
    if math:
        source = _MATH_CALL.sub(call, _MATH_LOOP.sub(loop, source))
    if not (shapes or used):
        return source
    # after CasADi's runtime functions (the kernels fall back to casadi_mtimes_dense)
    anchor = _MTIMES_DEF.search(source) if shapes else _INT_TYPE.search(source)
    if anchor is None or _MATH_INCLUDE not in source:
        raise RuntimeError(f"CasADi {ca.__version__} wrote a source that kklcasadi.observer.codegen does "
                           "not recognise (its preamble or casadi_mtimes_dense); it needs "
                           "updating for it.")
    math_code, entries = "", ""
    if used:
        math_code += template("math_core")
        vector = "const casadi_real* x, casadi_int n, casadi_real* y"
        for function, text in (("exp", template("vector_exp")), ("tanh", template("vector_tanh"))):
            if function in used:
                math_code += text
                entries += _entry(f"v{function}", vector, "x, n, y", dispatch)
            if function in scalar:
                entries += template("vector_scalar").replace("FUNCTION", function)
    for (nrow, ncol, ncol_y), name in sorted(shapes.items()):
        guard = (f"  if (kklc_overlap(z, {nrow * ncol_y}, x, {nrow * ncol}) "
                 f"|| kklc_overlap(z, {nrow * ncol_y}, y, {ncol * ncol_y})) {{\n"
                 f"    casadi_mtimes_dense(x, {nrow}, {ncol}, y, {ncol_y}, z, 0);\n"
                 "    return;\n  }\n")
        entries += _entry(name, "const casadi_real* x, const casadi_real* y, casadi_real* z",
                          "x, y, z", dispatch, guard)

    def code(version: str) -> str:
        return math_code + "".join("\n" + _matvec_kernel(name, *shape, version)
                                   for shape, name in sorted(shapes.items()))

    fuse = "#define KKLC_FUSED 1\n" if fused and dispatch else ""
    helpers = (fuse + (template("dispatch") if dispatch else "") + (template("overlap") if shapes else "")
               + (template("math_constants") if used else "") + _versions(code, dispatch, fused) + entries)
    source = source[:anchor.end()] + helpers + source[anchor.end():]
    return source.replace(_MATH_INCLUDE, _MATH_INCLUDE + "#include <stdint.h>\n"
                          "#include <string.h>\n", 1)


def _float_literal(match: re.Match) -> str:
    """A double constant as the float constant it rounds to (shortest digits that give it back)."""
    value = np.float32(float(match.group(0)))
    if np.isinf(value):
        return "HUGE_VALF"
    return np.format_float_scientific(value, unique=True, trim="0") + "f"


def single_precision(source: str) -> str:
    """``source`` (C or a header written by ``ca.CodeGenerator``) with every computation in single precision:
    ``casadi_real`` defined as ``float`` and ``casadi_int`` as ``int`` (what CasADi's own options of those
    names write; nothing else of its code differs), each constant written as the float it rounds to
    (``0.5f``: without the suffix C computes ``2.*a`` in double), each call of the C library's double
    functions as its float version (``tanhf``, ``expf``, ``sqrtf``, ``fmaxf``, ...). Comments are left as
    they are.

    A core with a single-precision FPU (Cortex-M4F, M33, M7 without its double unit) then runs the
    step without software double arithmetic.
    """
    parts = _COMMENT.split(_source(source))
    for i in range(0, len(parts), 2):                    # the code between comments
        parts[i] = _LIBM_CALL.sub(r"\1f(", _FLOAT_LITERAL.sub(_float_literal, parts[i]))
    return "".join(parts).replace(_REAL_DOUBLE, "#define casadi_real float\n").replace(
        _INT_LONG, "#define casadi_int int\n")


def axpy_matvec(source: str) -> str:
    """``source`` (C from ``ca.CodeGenerator``) with every dense mat-vec in axpy order.

    The kernels keep each output's summation order, so results are bitwise CasADi's; for
    :class:`kklcasadi.evaluation.compiled.Compiler`'s ``postprocess`` (the evaluation path of
    ``kklcasadi evaluate``).
    """
    return rewrite(_source(source), matvec=True, math=False, dispatch=False)


def fast_kernels(source: str) -> str:
    """``source`` with the axpy mat-vec kernels, the vectorisable exp/tanh and their AVX2 versions, whose
    mat-vec kernels sum with fused multiply-adds where the CPU has FMA.

    The compiled evaluation path's default (``kklcasadi evaluate``, ``estimate``'s long logs, the protocol
    benchmark): within :data:`FUSED_TOLERANCE` of CasADi's values (the exp/tanh within 3 ulp, each
    fused multiply-add rounded once) rather than bitwise; ``--math libm`` keeps it bitwise. Unlike
    :func:`generate_c`'s defaults, whose AVX2 kernels sum as the portable ones do, the fused kernels
    run the 150-wide mat-vecs of the protocol's observers at about twice the multiply-adds per cycle.
    """
    return rewrite(_source(source), matvec=True, math=True, dispatch=True, fused=True)



def _source(source: object) -> str:
    if not isinstance(source, str):
        raise TypeError(f"source: expected the C source as str (ca.CodeGenerator output), received "
                        f"{type(source).__name__}.")
    return source
