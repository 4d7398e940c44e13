"""C code for the observer step: CasADi code generation plus a header and a ``main`` example.

:func:`generate_c` writes three files into ``out_dir`` for ``name = "kkl_obs"``:

``kkl_obs.c``
    The CasADi-generated C99 source of ``kkl_obs_step(z, w, y, y_next, u_next) -> (z_next,
    w_next, xhat_next)`` and ``kkl_obs_decode(z, w) -> xhat`` (CasADi's calling convention:
    ``f(arg, res, iw, w, mem)`` with caller-provided work arrays; no dynamic allocation). The
    CasADi source is written between ``#pragma GCC diagnostic`` lines that silence
    ``-Wunused-parameter`` (CasADi's generated functions keep unused ``iw``/``mem`` arguments),
    so it compiles with ``gcc -std=c99 -Wall -Wextra -Werror``. Three rewrites make it fast
    (:func:`generate_c`'s ``matvec``, ``math`` and ``dispatch``):

    * ``matvec="axpy"``: every dense matrix-vector product ``casadi_mtimes_dense`` (about 90 %
      of a step as CasADi writes it: one serial chain of additions per output, reading the
      column-major matrix with a large stride) becomes a kernel of fixed size that walks the
      matrix in column (axpy) order and keeps a block of 16 outputs in registers. Every output
      is still summed in CasADi's order, ``((0 + x_0 y_0) + x_1 y_1) + ...``, so the result is
      bitwise the CasADi VM's (the VM evaluates ``mtimes`` in this order too); the loops
      vectorise at ``-O2`` and ``-O3``.
    * ``math="vector"``: ``exp`` and ``tanh`` (the activations and the GRU gates) become C99
      arithmetic without branches or library calls, which compilers vectorise, within 1 ulp
      (``exp``) and 3 ulp (``tanh``) of the C library; the step then differs from the CasADi VM
      by at most :data:`VECTOR_MATH_TOLERANCE` (tested). ``math="libm"`` keeps the C library
      calls and the bitwise equality.
    * ``dispatch=True``: with gcc or clang on x86, the kernels and the vector exp/tanh also
      come in an AVX2 version (gcc vector extensions, under ``#if``), used where the CPU has
      AVX2 (``__builtin_cpu_supports``, or always when the build targets AVX2). The portable
      C99 version stays the fallback, and ``-DKKLC_NO_DISPATCH`` compiles it alone; both give
      the same results bit for bit.

    Bitwise equality needs a build without floating-point contraction (no fused multiply-add
    across the products and sums): the ISO modes (``-std=c99``) of gcc and clang default to
    ``-ffp-contract=off``; ``-ffast-math`` voids it.
``kkl_obs.h``
    Declarations, the sizes ``KKL_OBS_NX``, ``_NU``, ``_NY``, ``_NZ``, ``_WINDOW``, the sample
    period ``KKL_OBS_DT`` and the work sizes ``KKL_OBS_SZ_ARG``, ``_SZ_RES``, ``_SZ_IW``,
    ``_SZ_W`` (enough for both functions).
``kkl_obs_main.c``
    An example program: reads ``t, y[0..ny-1], u[0..nu-1]`` per line from a CSV file (first
    argument) or stdin, and prints ``t, xhat[0..nx-1]`` per line, exactly as
    :meth:`KKLObserver.simulate` computes them. Build it with
    ``gcc -std=c99 -O3 kkl_obs.c kkl_obs_main.c -lm -o kkl_obs`` (the ``flags`` of
    :func:`generate_c`, written into both C files).
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence, Union

import casadi as ca

from .validation import one_of

if TYPE_CHECKING:
    from .observer import KKLObserver

__all__ = ["generate_c", "axpy_matvec", "fast_kernels", "check_c_name", "check_flags", "vector_math_c", "C_FLAGS",
           "DEFAULT_FLAGS", "NATIVE_FLAGS", "MATVECS", "MATHS", "VECTOR_MATH_TOLERANCE"]

#: The warning flags the generated code is tested with, at -O2 (it is also tested at
#: ``DEFAULT_FLAGS`` with the same warnings).
C_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-O2")
#: The default build flags written into the generated files: portable (no ``-march``, no
#: ``-ffast-math``), ISO C99 (so no floating-point contraction).
DEFAULT_FLAGS = ("-std=c99", "-O3")
#: Opt-in: also use the vector instructions of the build machine (AVX2, AVX-512); the binary
#: may not run on another CPU.
NATIVE_FLAGS = ("-std=c99", "-O3", "-march=native")
#: ``generate_c(matvec=...)``: register-blocked column (axpy) order, or CasADi's own loops.
MATVECS = ("axpy", "casadi")
#: ``generate_c(math=...)``: vectorisable exp and tanh, or the C library's.
MATHS = ("vector", "libm")
#: With ``math="vector"`` the C step and the CasADi VM agree to
#: ``|C - VM| <= VECTOR_MATH_TOLERANCE * (1 + |VM|)`` (tested on every method).
VECTOR_MATH_TOLERANCE = 1e-14

# A C identifier that CasADi also accepts as a function name: a letter first, then letters, digits
# and single underscores (CasADi reserves double underscores), not ending in an underscore.
_C_NAME = re.compile(r"^[A-Za-z](?:_?[A-Za-z0-9])*$")
_C_KEYWORDS = frozenset("""auto break case char const continue default do double else enum extern
float for goto if inline int long register restrict return short signed sizeof static struct switch
typedef union unsigned void volatile while _Bool _Complex _Imaginary""".split())


def check_c_name(name: object) -> str:
    """Return ``name`` if it can prefix the generated C symbols, else raise.

    Raises
    ------
    TypeError
        If ``name`` is not a string.
    ValueError
        If it is not a letter followed by letters, digits and single underscores, or is a C
        keyword.
    """
    if not isinstance(name, str):
        raise TypeError(f"name: expected a string, received {type(name).__name__}.")
    if not _C_NAME.match(name) or name in _C_KEYWORDS:
        raise ValueError(f"name: expected a C identifier that starts with a letter and holds "
                         f"letters, digits and single underscores (not a C keyword), received "
                         f"{name!r}. Try e.g. 'kkl_obs'.")
    return name


def _renamed(f: ca.Function, name: str, symbol: type = ca.MX) -> ca.Function:
    """``f`` under another name (a thin wrapper of ``symbol`` type, same inputs and outputs)."""
    args = [symbol.sym(f.name_in(i), f.sparsity_in(i)) for i in range(f.n_in())]
    return ca.Function(name, args, f.call(args), f.name_in(), f.name_out())


def _work_sizes(casadi_header: str, names: list[str]) -> dict[str, int]:
    """The largest work sizes of the generated functions (CasADi's ``<name>_SZ_*`` macros).

    The generated code's sizes can differ from the in-memory Function's ``sz_w()``, so they are
    read from what CasADi wrote.
    """
    sizes = {}
    for key in ("SZ_ARG", "SZ_RES", "SZ_IW", "SZ_W"):
        values = [re.search(rf"^#define {name}_{key} (\d+)$", casadi_header, re.MULTILINE)
                  for name in names]
        if not all(values):
            raise RuntimeError(f"CasADi {ca.__version__} wrote no {key} macro for "
                               f"{', '.join(names)}; kklcasadi.codegen needs updating for it.")
        sizes[key] = max(int(v.group(1)) for v in values)
    return sizes


def _header(observer: KKLObserver, name: str, casadi_header: str,
            sizes: dict[str, int], build: str, matvec: str, math: str, dispatch: bool) -> str:
    macro = name.upper()
    rows, cols = observer.memory_shape
    defines = {"NX": observer.nx, "NU": observer.nu, "NY": observer.ny, "NZ": observer.nz,
               "WINDOW": observer.window, "NW": rows * cols, **sizes}
    lines = [f"#define {macro}_{key} {value}" for key, value in defines.items()]
    lines.append(f"#define {macro}_DT {observer.dt!r}")
    if observer.domain_check is not None:
        from .observer import DOMAIN_MARGIN

        lines.append(f"#define {macro}_HAS_DOMAIN 1")
        monitor = (f"""
 * {name}_in_domain(arg, res, iw, w, mem): arg[0] z (NZ), arg[1] xhat (NX) -> res[0] 1.0 if the
 *   estimate and the latent lie in the domain the maps were trained on (the card's state and
 *   latent boxes widened by {DOMAIN_MARGIN!r} of their ranges), else 0.0: the domain
 *   monitor, to call after a step where wanted ({macro}_HAS_DOMAIN is defined).""")
    else:
        monitor = "\n * (The model records no training domain: no domain monitor.)"
    scheme = ("exact (matrix exponential, first-order hold)" if observer.discretization == "exact"
              else f"RK4 with {observer.substeps} substep(s)")
    memory = ("the input window, WINDOW x NU column-major: w[i + WINDOW*j] is input j at sample "
              "k - WINDOW + 1 + i, oldest first" if observer.memory_shape == (observer.window, observer.nu)
              else f"the streaming context h_k ({rows - observer.nu}) and the held input u_k ({observer.nu})")
    return f"""/* {name}.h -- KKL observer step generated by kklcasadi.
 *
 * Observer: method {observer.method!r}, system {observer.system.name!r}, sample period
 * {observer.dt!r} s, discretisation {scheme}.
 *
 * {name}_step(arg, res, iw, w, mem): one sample interval.
 *   arg[0] z       (NZ)               latent state z_k
 *   arg[1] w       (NW)               input memory w_k ({memory})
 *   arg[2] y       (NY)               measurement y_k
 *   arg[3] y_next  (NY)               measurement y_k+1 (y is interpolated linearly)
 *   arg[4] u_next  (NU)               input u_k+1 (u is held at u_k, which w_k holds)
 *   res[0] z_next  (NZ), res[1] w_next (NW), res[2] xhat_next (NX)
 * {name}_decode(arg, res, iw, w, mem): arg[0] z (NZ), arg[1] w -> res[0] xhat (NX).
 * {name}_init(arg, res, iw, w, mem): arg[0] y_0 (NY), arg[1] u_0 (NU) -> res[0] w_0 (NW), the
 *   memory at the start.{monitor}
 * Start: z_0 = 0, w_0 = init(u_0), xhat_0 = decode(z_0, w_0).
 * Work arrays: arg[{macro}_SZ_ARG], res[{macro}_SZ_RES], iw[{macro}_SZ_IW],
 * w[{macro}_SZ_W] (enough for both functions); outputs must not alias inputs; mem = 0.
 *
 * Code: matvec={matvec!r}, math={math!r}, dispatch={dispatch!r} (kklcasadi.codegen).
 * Build:
 *   {build}
 */
#ifndef {macro}_H
#define {macro}_H

{chr(10).join(lines)}

{casadi_header.strip()}

#endif /* {macro}_H */
"""


_MAIN = r"""/* __NAME___main.c -- run the KKL observer on a CSV of samples (generated by kklcasadi).
 *
 * Usage: __NAME__ [samples.csv]      (reads stdin without an argument)
 * Each input line: t, y[0..NY-1], u[0..NU-1] (commas or blanks). A first line that is not
 * numeric (a header) and lines starting with '#' are skipped. Each output line: t, xhat[0..NX-1].
 * Build: __BUILD__
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "__NAME__.h"

#define NCOL (1 + __MACRO___NY + __MACRO___NU)
#define LINE_LEN (64 * NCOL + 256)

static casadi_real z[__MACRO___NZ], z_next[__MACRO___NZ];
static casadi_real win[__MACRO___NW], win_next[__MACRO___NW];
static casadi_real y_prev[__MACRO___NY], xhat[__MACRO___NX];
static const casadi_real* arg[__MACRO___SZ_ARG];
static casadi_real* res[__MACRO___SZ_RES];
static casadi_int iw[__MACRO___SZ_IW + 1];
static casadi_real work[__MACRO___SZ_W + 1];

/* Parse up to NCOL numbers; return how many were read, or -1 on text that is not a number. */
static int parse_line(const char* line, casadi_real* values) {
  int n = 0;
  const char* p = line;
  char* end;
  for (;;) {
    while (*p == ' ' || *p == '\t' || *p == ',' || *p == '\r' || *p == '\n') p++;
    if (*p == '\0') return n;
    if (n == NCOL) return NCOL + 1;
    values[n] = strtod(p, &end);
    if (end == p) return -1;
    n++;
    p = end;
  }
}

int main(int argc, char** argv) {
  FILE* in = stdin;
  char line[LINE_LEN];
  casadi_real values[NCOL];
  long k = 0, lineno = 0;
  int i, n;
  if (argc > 2) {
    fprintf(stderr, "usage: %s [samples.csv]\n", argv[0]);
    return 2;
  }
  if (argc == 2 && (in = fopen(argv[1], "r")) == NULL) {
    perror(argv[1]);
    return 1;
  }
  while (fgets(line, sizeof line, in) != NULL) {
    const casadi_real *y, *u;
    lineno++;
    if (strchr(line, '\n') == NULL && !feof(in)) {
      fprintf(stderr, "line %ld: longer than %d characters\n", lineno, LINE_LEN - 1);
      return 1;
    }
    if (line[0] == '#') continue;
    n = parse_line(line, values);
    if (n == 0 || (n < 0 && lineno == 1)) continue;
    if (n != NCOL) {
      fprintf(stderr, "line %ld: expected %d numbers (t, %d outputs y, %d inputs u)\n",
              lineno, NCOL, __MACRO___NY, __MACRO___NU);
      return 1;
    }
    for (i = 0; i < NCOL; i++) {
      if (!isfinite(values[i])) {
        fprintf(stderr, "line %ld (sample %ld): value %d is not finite\n", lineno, k, i + 1);
        return 1;
      }
    }
    y = values + 1;
    u = values + 1 + __MACRO___NY;
    if (k == 0) {                 /* z_0 = 0, w_0 = init(y_0, u_0) */
      for (i = 0; i < __MACRO___NZ; i++) z[i] = 0;
      arg[0] = y; arg[1] = u; res[0] = win;
      if (__NAME___init(arg, res, iw, work, 0)) {
        fprintf(stderr, "sample %ld: __NAME___init failed\n", k);
        return 1;
      }
      arg[0] = z; arg[1] = win; res[0] = xhat;
      if (__NAME___decode(arg, res, iw, work, 0)) {
        fprintf(stderr, "sample %ld: __NAME___decode failed\n", k);
        return 1;
      }
    } else {
      arg[0] = z; arg[1] = win; arg[2] = y_prev; arg[3] = y; arg[4] = u;
      res[0] = z_next; res[1] = win_next; res[2] = xhat;
      if (__NAME___step(arg, res, iw, work, 0)) {
        fprintf(stderr, "sample %ld: __NAME___step failed\n", k);
        return 1;
      }
      memcpy(z, z_next, sizeof z);
      memcpy(win, win_next, sizeof win);
    }
    memcpy(y_prev, y, sizeof y_prev);
    printf("%.17g", values[0]);
    for (i = 0; i < __MACRO___NX; i++) printf(",%.17g", xhat[i]);
    printf("\n");
    k++;
  }
  if (in != stdin) fclose(in);
  return 0;
}
"""

# -------------------------------------------------------------------- rewriting CasADi's source
# CasADi 3.x writes every dense matrix-vector product as this call (sizes as literals, tr = 0).
_MTIMES_CALL = re.compile(r"casadi_mtimes_dense\(([^,();]+), (\d+), (\d+), ([^,();]+), (\d+), "
                          r"([^,();]+), 0\);")
_MTIMES_DEF = re.compile(r"^void casadi_mtimes_dense\(.*?^}\n", re.MULTILINE | re.DOTALL)
# ... and an element-wise exp or tanh of a vector as this loop; scalars as plain calls (the
# generated comments show the operands as "@3", which the last pattern skips).
_MATH_LOOP = re.compile(r"for \(i=0, rr=([^,();]+), cs=([^,();]+); i<(\d+); \+\+i\) "
                        r"\*rr\+\+ = (exp|tanh)\( \*cs\+\+ \);")
_MATH_CALL = re.compile(r"\b(exp|tanh)\((?!@)")
_INT_TYPE = re.compile(r"^#ifndef casadi_int\n#define casadi_int [^\n]*\n#endif\n", re.MULTILINE)
_MATH_INCLUDE = "#include <math.h>\n"

#: Outputs per register block of the axpy kernels (8 SSE2 or 4 AVX2 registers).
_BLOCK = 16

# The helpers below are C text. Functions named KKLCV_* come in versions: portable (kklc_c_*)
# and, under KKLC_DISPATCH, an AVX2 copy (kklc_avx2_*); the kklc_* entry points pick one.
_DISPATCH = """
/* kklcasadi: with gcc or clang on x86 the kernels below also come in an AVX2 version (gcc
 * vector extensions; the same results bit for bit, as long as no FMA contraction), used where
 * the CPU has AVX2: always when the build targets it (-march=native on a recent CPU), else
 * as __builtin_cpu_supports finds at run time. -DKKLC_NO_DISPATCH compiles the portable C99
 * version only. */
#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__)) \\
    && !defined(KKLC_NO_DISPATCH)
#define KKLC_DISPATCH 1
typedef double kklc_v4 __attribute__((vector_size(32)));
#ifdef __AVX2__
#define KKLC_AVX2
#define KKLC_HAS_AVX2 1
#else
#define KKLC_AVX2 __attribute__((target("avx2")))
#define KKLC_HAS_AVX2 __builtin_cpu_supports("avx2")
#endif
#endif
"""

_OVERLAP = """
/* kklcasadi: whether the arrays a[0..na-1] and b[0..nb-1] share memory */
static int kklc_overlap(const casadi_real* a, casadi_int na, const casadi_real* b, casadi_int nb) {
  uintptr_t a0 = (uintptr_t) a, b0 = (uintptr_t) b;
  return a0 < b0 + (uintptr_t) nb * sizeof(casadi_real)
      && b0 < a0 + (uintptr_t) na * sizeof(casadi_real);
}
"""

_MATH_CONSTANTS = """
/* kklcasadi: exp and tanh as C99 arithmetic without branches or library calls, so that loops
 * over them vectorise. Range reduction x = k ln2 + r (|r| <= ln2/2, Cody-Waite), Taylor
 * polynomial of expm1(r) to degree 13, 2^k assembled from the exponent bits. Relative error
 * within 1 ulp (exp) and 3 ulp (tanh) of a correctly rounded result; NaN and infinities as the
 * C library; exp overflows to HUGE_VAL and underflows through the subnormals to 0. */
#define KKLC_SHIFTER 6755399441055744.0         /* 0x1.8p52: x + it rounds x to an integer */
#define KKLC_LOG2E 1.4426950408889634
#define KKLC_LN2HI 6.93147180369123816490e-01   /* ln 2 = LN2HI + LN2LO, k LN2HI exact */
#define KKLC_LN2LO 1.90821492927058770002e-10
"""

_MATH_CORE = """
/* expm1(r) for |r| <= 0.35: Taylor polynomial to degree 13 (truncation below 1e-18) */
static inline casadi_real KKLCV_expm1_reduced(casadi_real r) {
  casadi_real q = 1.0 / 6227020800.0;
  q = q * r + 1.0 / 479001600.0;
  q = q * r + 1.0 / 39916800.0;
  q = q * r + 1.0 / 3628800.0;
  q = q * r + 1.0 / 362880.0;
  q = q * r + 1.0 / 40320.0;
  q = q * r + 1.0 / 5040.0;
  q = q * r + 1.0 / 720.0;
  q = q * r + 1.0 / 120.0;
  q = q * r + 1.0 / 24.0;
  q = q * r + 1.0 / 6.0;
  q = q * r + 0.5;
  return r + (r * r) * q;
}

/* 2^k for an integer -1022 <= k <= 1023 held as kd = k + 0x1.8p52 */
static inline casadi_real KKLCV_pow2(casadi_real kd) {
  uint64_t bits;
  casadi_real scale;
  memcpy(&bits, &kd, sizeof bits);
  bits = (bits + 1023) << 52;
  memcpy(&scale, &bits, sizeof scale);
  return scale;
}
"""

_VECTOR_EXP = """
/* exp(x) for x in [-746, 710] or NaN: 2^k split in two factors that stay normal numbers */
static inline casadi_real KKLCV_exp_clamped(casadi_real x) {
  casadi_real kd = x * KKLC_LOG2E + KKLC_SHIFTER, k = kd - KKLC_SHIFTER;
  casadi_real r = (x - k * KKLC_LN2HI) - k * KKLC_LN2LO;
  casadi_real hd = k * 0.5 + KKLC_SHIFTER, h = hd - KKLC_SHIFTER;
  return (1.0 + KKLCV_expm1_reduced(r)) * KKLCV_pow2(hd) * KKLCV_pow2((k - h) + KKLC_SHIFTER);
}

/* y[i] = exp(x[i]) for i < n; y is x or does not overlap it. Passes over y that vectorise. */
static void KKLCV_vexp(const casadi_real* x, casadi_int n, casadi_real* y) {
  casadi_int i;
  if (y != x) for (i = 0; i < n; ++i) y[i] = x[i];
  for (i = 0; i < n; ++i) y[i] = y[i] > 710.0 ? 710.0 : y[i];
  for (i = 0; i < n; ++i) y[i] = y[i] < -746.0 ? -746.0 : y[i];
  for (i = 0; i < n; ++i) y[i] = KKLCV_exp_clamped(y[i]);
}
"""

_VECTOR_TANH = """
/* tanh(a) = expm1(2a) / (expm1(2a) + 2) for a in [0, 20] or NaN (tanh(20) rounds to 1) */
static inline casadi_real KKLCV_tanh_clamped(casadi_real a) {
  casadi_real b = 2.0 * a, kd = b * KKLC_LOG2E + KKLC_SHIFTER, k = kd - KKLC_SHIFTER;
  casadi_real r = (b - k * KKLC_LN2HI) - k * KKLC_LN2LO, s = KKLCV_pow2(kd);
  casadi_real e = s * KKLCV_expm1_reduced(r) + (s - 1.0);
  return e / (e + 2.0);
}

/* y[i] = tanh(x[i]) for i < n; y is x or does not overlap it. Passes over y that vectorise. */
static void KKLCV_vtanh(const casadi_real* x, casadi_int n, casadi_real* y) {
  casadi_int i;
  if (y != x) for (i = 0; i < n; ++i) y[i] = x[i];
  for (i = 0; i < n; ++i) y[i] = y[i] > 20.0 ? 20.0 : y[i];
  for (i = 0; i < n; ++i) y[i] = y[i] < -20.0 ? -20.0 : y[i];
  for (i = 0; i < n; ++i) y[i] = copysign(KKLCV_tanh_clamped(fabs(y[i])), y[i]);
}
"""

_VECTOR_SCALAR = """
static casadi_real kklc_FUNCTION(casadi_real x) {
  casadi_real y;
  kklc_vFUNCTION(&x, 1, &y);
  return y;
}
"""


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
    code = _MATH_CORE + "".join(text for function, text in
                                (("exp", _VECTOR_EXP), ("tanh", _VECTOR_TANH))
                                if function in functions)
    return _MATH_CONSTANTS + code.replace("KKLCV_", "kklc_")


def _block_code(rows: int, ncol: int, nrow: int, width: int, indent: str) -> list[str]:
    """``z[j..j+rows-1] += x[j.., :] y``, with ``rows // width`` vector accumulators of
    ``width`` doubles (``kklc_v4``, when ``width`` is 4) and scalars for the rest (``j``,
    ``x``, ``y``, ``z``, ``xk``, ``k`` in scope). Every sum runs over ``k`` in ascending order
    from ``z``'s value, as casadi_mtimes_dense's does: the same results bit for bit."""
    vectors, scalars = _accumulators(rows, width)
    lines = [f"{indent}memcpy(&v{r}, z + j + {r * width}, sizeof yv);" for r in range(vectors)]
    lines += [f"{indent}a{r} = z[j + {r}];" for r in scalars]
    lines.append(f"{indent}for (k = 0, xk = x + j; k < {ncol}; ++k, xk += {nrow}) {{")
    lines.append(f"{indent}  yk = y[k];")
    if vectors:
        lines.append(f"{indent}  yv = (kklc_v4) {{yk, yk, yk, yk}};")
    for r in range(vectors):
        lines += [f"{indent}  memcpy(&w{r}, xk + {r * width}, sizeof yv);",
                  f"{indent}  v{r} += w{r} * yv;"]
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
    AVX2 vectors (gcc vector extensions) in the ``"avx2"`` version."""
    width = 4 if version == "avx2" else 1
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
             *_block_code(block, ncol, nrow, width, "      "),
             "    }"]
    if tail:
        lines += [f"    j = {nrow - tail};", *_block_code(tail, ncol, nrow, width, "    ")]
    lines += ["  }", "}"]
    return "\n".join(lines) + "\n"


def _entry(name: str, params: str, args: str, dispatch: bool, guard: str = "") -> str:
    """The kklc_<name> entry point: the AVX2 version where the CPU has it, else the portable."""
    avx2 = (f"#ifdef KKLC_DISPATCH\n  if (KKLC_HAS_AVX2) {{\n"
            f"    kklc_avx2_{name}({args});\n    return;\n  }}\n#endif\n") if dispatch else ""
    return (f"\nstatic void kklc_{name}({params}) {{\n{guard}{avx2}"
            f"  kklc_c_{name}({args});\n}}\n")


def _versions(code: Callable[[str], str], dispatch: bool) -> str:
    """``code(version)``'s KKLCV_ functions as the portable kklc_c_ and, under KKLC_DISPATCH, as
    the AVX2 kklc_avx2_ functions."""
    portable = code("c").replace("KKLCV_", "kklc_c_")
    if not dispatch:
        return portable
    avx2 = (code("avx2").replace("KKLCV_", "kklc_avx2_")
            .replace("\nstatic ", "\nKKLC_AVX2 static "))
    return f"{portable}\n#ifdef KKLC_DISPATCH\n{avx2}#endif\n"


def _rewrite(source: str, matvec: bool, math: bool, dispatch: bool) -> str:
    """Replace the dense mat-vec calls by axpy kernels (``matvec``, bitwise equal) and the C
    library's exp and tanh by vectorisable ones (``math``, within 3 ulp); ``dispatch`` adds the
    AVX2 versions. Returns ``source`` unchanged when there is nothing to replace."""
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
        raise RuntimeError(f"CasADi {ca.__version__} wrote a source that kklcasadi.codegen does "
                           "not recognise (its preamble or casadi_mtimes_dense); it needs "
                           "updating for it.")
    math_code, entries = "", ""
    if used:
        math_code += _MATH_CORE
        vector = "const casadi_real* x, casadi_int n, casadi_real* y"
        for function, text in (("exp", _VECTOR_EXP), ("tanh", _VECTOR_TANH)):
            if function in used:
                math_code += text
                entries += _entry(f"v{function}", vector, "x, n, y", dispatch)
            if function in scalar:
                entries += _VECTOR_SCALAR.replace("FUNCTION", function)
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

    helpers = ((_DISPATCH if dispatch else "") + (_OVERLAP if shapes else "")
               + (_MATH_CONSTANTS if used else "") + _versions(code, dispatch) + entries)
    source = source[:anchor.end()] + helpers + source[anchor.end():]
    return source.replace(_MATH_INCLUDE, _MATH_INCLUDE + "#include <stdint.h>\n"
                          "#include <string.h>\n", 1)


def axpy_matvec(source: str) -> str:
    """``source`` (C from ``ca.CodeGenerator``) with every dense mat-vec in axpy order.

    The kernels keep each output's summation order, so results are bitwise CasADi's; for
    :class:`kklcasadi.compiled.Compiler`'s ``postprocess`` (the evaluation path of
    ``kklcasadi evaluate``).
    """
    return _rewrite(_source(source), matvec=True, math=False, dispatch=False)


def fast_kernels(source: str) -> str:
    """``source`` with the axpy mat-vec kernels, the vectorisable exp/tanh and their AVX2 versions.

    As :func:`generate_c`'s defaults: within :data:`VECTOR_MATH_TOLERANCE` of CasADi's values
    (the exp/tanh within 3 ulp) rather than bitwise; the default of ``kklcasadi evaluate``
    (``--math libm`` keeps it bitwise).
    """
    return _rewrite(_source(source), matvec=True, math=True, dispatch=True)


def _source(source: object) -> str:
    if not isinstance(source, str):
        raise TypeError(f"source: expected the C source as str (ca.CodeGenerator output), received "
                        f"{type(source).__name__}.")
    return source


_PRAGMA_PUSH = """#if defined(__GNUC__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wunused-parameter"
#endif
"""
_PRAGMA_POP = """#if defined(__GNUC__)
#pragma GCC diagnostic pop
#endif
"""


def check_flags(flags: object) -> tuple[str, ...]:
    """Return ``flags`` as a tuple of compiler options, each one word starting with ``-``.

    Raises
    ------
    TypeError
        If ``flags`` is a string or not a sequence.
    ValueError
        If a flag is not a string, does not start with ``-`` or holds blanks or quotes.
    """
    if isinstance(flags, str) or not isinstance(flags, Sequence):
        raise TypeError(f"flags: expected a sequence of strings such as {DEFAULT_FLAGS}, "
                        f"received {type(flags).__name__}.")
    for flag in flags:
        if not isinstance(flag, str) or not re.fullmatch(r"-[^\s'\"\\]+", flag):
            raise ValueError(f"flags: expected compiler options that start with '-' and hold no "
                             f"blanks or quotes, such as {DEFAULT_FLAGS}, received {flag!r}.")
    return tuple(flags)


def generate_c(observer: KKLObserver, out_dir: Union[str, os.PathLike], name: str = "kkl_obs",
               *, overwrite: bool = False, matvec: str = "axpy", math: str = "vector",
               dispatch: bool = True, flags: Sequence[str] = DEFAULT_FLAGS) -> list[Path]:
    """Write the observer step as C99 source, a header and a ``main`` example.

    Parameters
    ----------
    observer : KKLObserver
    out_dir : str or path-like
        Output directory; created if missing.
    name : str
        Prefix of the files and C symbols: ``name.c``, ``name.h``, ``name_main.c``, functions
        ``name_step``, ``name_decode`` and ``name_init``, macros ``NAME_NX`` etc.
    overwrite : bool
        Replace existing files of the same names.
    matvec : {"axpy", "casadi"}
        The dense matrix-vector products: fixed-size kernels in column (axpy) order with a block
        of outputs in registers, which vectorise (default), or CasADi's own loops. Both sum every
        output in the same order: the results are bitwise equal.
    math : {"vector", "libm"}
        ``exp`` and ``tanh``: branch-free C99 arithmetic that vectorises, within 3 ulp of the C
        library, so that the step is within :data:`VECTOR_MATH_TOLERANCE` of the CasADi VM
        (default); or the C library's functions, bitwise as the CasADi VM (with
        ``matvec="axpy"`` or ``"casadi"``).
    dispatch : bool
        With gcc or clang on x86, also compile the kernels and the vector exp/tanh for AVX2
        (gcc vector extensions, under ``#if``) and use that version where the CPU has it:
        chosen at run time (``__builtin_cpu_supports``), or always when the build targets AVX2
        (``-march=native`` on a recent CPU). The results are the same bit for bit.
        ``-DKKLC_NO_DISPATCH`` at compile time, or ``dispatch=False`` (no extensions in the
        source), leaves the portable C99 version only.
    flags : sequence of str
        The compiler options written into the build lines of ``name.h`` and ``name_main.c``
        (``gcc FLAGS name.c name_main.c -lm -o name``); default :data:`DEFAULT_FLAGS`
        (portable). :data:`NATIVE_FLAGS` adds ``-march=native`` (faster, for the build
        machine's CPU only). The source compiles without warnings under ``-Wall -Wextra`` with
        either. Bitwise equality with the CasADi VM needs a build without floating-point
        contraction, as ``-std=c99`` gives (no ``-ffast-math``, no ``-ffp-contract=fast``).

    Returns
    -------
    list of Path
        ``[name.c, name.h, name_main.c]``.

    Raises
    ------
    ValueError
        ``name`` is not a valid C identifier, ``out_dir`` exists and is not a directory,
        ``matvec`` or ``math`` is not one of the choices, or a flag is not an option word.
    TypeError
        ``flags`` is not a sequence of strings, ``dispatch`` not a bool, or another argument
        has the wrong type.
    FileExistsError
        One of the files exists and ``overwrite`` is False.
    """
    from .observer import KKLObserver

    if not isinstance(observer, KKLObserver):
        raise TypeError(f"observer: expected a KKLObserver, received {type(observer).__name__}.")
    name = check_c_name(name)
    matvec = one_of(matvec, "matvec", MATVECS)
    math = one_of(math, "math", MATHS)
    if not isinstance(dispatch, bool):
        raise TypeError(f"dispatch: expected a bool, received {type(dispatch).__name__}.")
    flags = check_flags(flags)
    if not isinstance(out_dir, (str, os.PathLike)):
        raise TypeError(f"out_dir: expected a path, received {type(out_dir).__name__}.")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"out_dir: expected a directory, received {str(out)!r}, which is a "
                         "file. Choose a directory path.")
    paths = [out / f"{name}.c", out / f"{name}.h", out / f"{name}_main.c"]
    existing = [p for p in paths if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{existing[0]}: already exists; pass overwrite=True to replace "
                              "it, or choose another out_dir or name.")

    functions = [_renamed(observer.step, f"{name}_step"), _renamed(observer.decode, f"{name}_decode"),
                 # the start only, once: as SX, so that it has no nested calls (gcc's -Wdangling-pointer)
                 _renamed(observer.memory_init, f"{name}_init", ca.SX)]
    if observer.domain_check is not None:          # the domain monitor, where the card records a domain
        functions.append(_renamed(observer.domain_check, f"{name}_in_domain"))
    generator = ca.CodeGenerator(f"{name}.c", {"with_header": True, "casadi_real": "double"})
    for f in functions:
        generator.add(f)
    with tempfile.TemporaryDirectory() as tmp:
        generator.generate(tmp + os.sep)
        source = (Path(tmp) / f"{name}.c").read_text()
        casadi_header = (Path(tmp) / f"{name}.h").read_text()
    source = _rewrite(source, matvec == "axpy", math == "vector", dispatch)
    build = f"gcc {' '.join(flags)} {name}.c {name}_main.c -lm -o {name}"

    out.mkdir(parents=True, exist_ok=True)
    paths[0].write_text(f"/* {name}.c -- KKL observer step generated by kklcasadi; see {name}.h."
                        f" */\n{_PRAGMA_PUSH}{source}{_PRAGMA_POP}")
    sizes = _work_sizes(casadi_header, [f.name() for f in functions])
    paths[1].write_text(_header(observer, name, casadi_header, sizes, build, matvec,
                                math, dispatch))
    paths[2].write_text(_MAIN.replace("__BUILD__", build).replace("__NAME__", name)
                        .replace("__MACRO__", name.upper()))
    return paths
