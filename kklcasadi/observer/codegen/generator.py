"""C code for the observer step: CasADi code generation plus a header and a ``main`` example.

The speed rewrites of CasADi's C live in :mod:`.kernels`, the C text in ``templates/``.

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
    A program that runs the observer over a CSV log (first argument, or stdin): it reads the
    header and takes the model's columns **by name** (``time_col``, ``y_cols``, ``u_cols`` of
    :func:`generate_c`, written into the header as ``KKL_OBS_TIME_COL``, ``_Y_COLS``,
    ``_U_COLS``), in any order, and writes one line per sample: ``time``, the estimate (the
    ``state_names``), ``in_domain`` where the model records a domain, and the sample guard's
    ``status`` (:mod:`kklcasadi.observer.guard`: a non-finite or absurd sample is not fed, a step
    that leaves the latent's guard box restarts the observer; the guard boxes are
    ``KKL_OBS_GUARD_LO``, ``_HI``, ``_Z_LO``, ``_Z_HI``), exactly as
    :func:`~kklcasadi.observer.guard.guarded_simulate` computes them. Only plain decimal numbers
    are read; a missing column, a malformed row or number, or a time step other than the model's
    ``dt`` (to 1e-6 of it) stops it with one line ``error: line L: ...`` and exit status 2; a run
    with flagged samples ends with exit status 3. Build it with ``gcc -std=c99 -O3 kkl_obs.c
    kkl_obs_main.c -lm -o kkl_obs`` (the ``flags`` of :func:`generate_c`, written into both C
    files).
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path
from typing import Optional, Sequence, Union

import casadi as ca

from ...validation import Text, error, one_of
from ...writes import write_dir
from ..guard import SampleGuard
from ..kkl import DOMAIN_MARGIN, KKLObserver
from .kernels import rewrite, single_precision, template

__all__ = ["generate_c", "casadi_source", "renamed", "check_c_name", "check_flags", "c_targets", "C_FLAGS",
           "DEFAULT_FLAGS",
           "NATIVE_FLAGS", "MATVECS", "MATHS", "PRECISIONS"]

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
#: ``generate_c(precision=...)``: the C type of every value, ``double`` or ``float`` (microcontrollers).
PRECISIONS = ("float64", "float32")
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
        raise error("name", "a string", Text(type(name).__name__), kind=TypeError)
    if not _C_NAME.match(name) or name in _C_KEYWORDS:
        raise error("name", "a C identifier that starts with a letter and holds letters, digits and single "
                    "underscores (not a C keyword)", name, "Try e.g. 'kkl_obs'.")
    return name


def renamed(f: ca.Function, name: str, symbol: type = ca.MX) -> ca.Function:
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
                               f"{', '.join(names)}; kklcasadi.observer.codegen needs updating for it.")
        sizes[key] = max(int(v.group(1)) for v in values)
    return sizes


# A column name as the C main reads it: printable ASCII without commas, quotes, backslashes or
# "??" (a trigraph in ISO C), no blanks at either end and no '#' first (so it is a C string literal
# and a CSV header field as it is, and a header that starts with it is no comment).
_COLUMN = re.compile(r"(?!.*\?\?)[!$-+\--\[\]-~](?:[ !#-+\--\[\]-~]*[!#-+\--\[\]-~])?")


def _column_names(value: object, argument: str, count: int, default: str) -> tuple[str, ...]:
    """``count`` column names for the C main (``default1 .. defaultN`` when None), else raise."""
    if value is None:
        return tuple(f"{default}{i + 1}" for i in range(count))
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise error(argument, f"a sequence of {count} column names", Text(type(value).__name__), kind=TypeError)
    names = tuple(value)
    if len(names) != count:
        raise error(argument, f"{count} column names", list(names))
    for item in names:
        if not isinstance(item, str) or _COLUMN.fullmatch(item) is None:
            raise error(argument, "names of printable ASCII characters without commas, quotes, backslashes or '??', "
                        "no blanks at either end, no '#' first", item)
    return names


def _c_list(values: Sequence[float]) -> str:
    """Numbers as a C initializer list (``-HUGE_VAL``/``HUGE_VAL`` for infinities)."""
    return ", ".join("HUGE_VAL" if v == float("inf") else "-HUGE_VAL" if v == float("-inf") else repr(float(v))
                     for v in values)


def _strings(names: Sequence[str]) -> str:
    return ", ".join(f'"{n}"' for n in names)


def _header(observer: KKLObserver, name: str, casadi_header: str, sizes: dict[str, int], build: str,
            matvec: str, math: str, dispatch: bool, columns: dict[str, tuple[str, ...]],
            precision: str) -> str:
    macro = name.upper()
    rows, cols = observer.memory_shape
    defines = {"NX": observer.nx, "NU": observer.nu, "NY": observer.ny, "NZ": observer.nz,
               "WINDOW": observer.window, "NW": rows * cols, **sizes}
    lines = [f"#define {macro}_{key} {value}" for key, value in defines.items()]
    lines.append(f"#define {macro}_DT {observer.dt!r}")
    guard = SampleGuard.of(observer)
    lines += [f'#define {macro}_TIME_COL "{columns["time"][0]}"',
              f"#define {macro}_Y_COLS {_strings(columns['y'])}",
              f"#define {macro}_U_COLS {_strings(columns['u'])}",
              f"#define {macro}_STATE_NAMES {_strings(columns['states'])}",
              f"#define {macro}_GUARD_LO {_c_list([*guard.y_lo, *guard.u_lo])}",
              f"#define {macro}_GUARD_HI {_c_list([*guard.y_hi, *guard.u_hi])}",
              f"#define {macro}_GUARD_Z_LO {_c_list(guard.z_lo)}",
              f"#define {macro}_GUARD_Z_HI {_c_list(guard.z_hi)}"]
    if observer.domain_check is not None:
        lines.append(f"#define {macro}_HAS_DOMAIN 1")
        tests = []
        if observer.domain is not None:
            tests.append(f"the estimate and the latent lie in the card's state and latent boxes widened by "
                         f"{DOMAIN_MARGIN!r} of their ranges")
        if observer.monitor is not None:
            lines.append(f"#define {macro}_HAS_FEATURE_MONITOR 1")
            tests.append(f"the decoder's input [z; w] lies within {observer.monitor.spec.threshold:.6g} radii of "
                         f"one of the {observer.monitor.spec.prototypes} prototypes of its fitting data, in the "
                         "monitor's metric")
        monitor = (f"""
 * {name}_in_domain(arg, res, iw, w, mem): arg[0] z (NZ), arg[1] w (NW), arg[2] xhat (NX) -> res[0]
 *   1.0 if {" and ".join(tests)}, else 0.0: the domain monitor, to call after a step where wanted
 *   (with the step's z_next, w_next, xhat_next; {macro}_HAS_DOMAIN is defined).""")
    else:
        monitor = "\n * (The model records no training domain: no domain monitor.)"
    covariance = ""
    if observer.covariance is not None:
        lines.append(f"#define {macro}_HAS_COVARIANCE 1")
        covariance = (f"""
 *   res[3] P_next  (NX*NX)           the covariance of xhat_next's error, column-major (the card's
 *                                    covariance head; {macro}_HAS_COVARIANCE is defined; a null
 *                                    res[3] skips it)
 * {name}_covariance(arg, res, iw, w, mem): arg[0] z (NZ), arg[1] w (NW), arg[2] xhat (NX) -> res[0] P
 *   (NX*NX), the covariance at the start (with z_0, w_0, xhat_0).""")
        if observer.inflation is not None:
            lines.append(f"#define {macro}_HAS_INFLATION 1")
            start = observer.inflation_start
            lines.append(f"#define {macro}_NM {start.size}")
            lines.append(f"#define {macro}_M0 {{{', '.join(repr(float(v)) for v in start)}}}")
            covariance = (f"""
 *   arg[5] m       (NM)               the covariance inflation's state m_k ({macro}_HAS_INFLATION is defined:
 *                                    the card's architecture.inflation): {macro}_M0 at the start, then m_next
 *   res[3] P_next  (NX*NX)           the covariance of xhat_next's error, column-major (the card's
 *                                    covariance head, times its inflation factor; a null res[3] skips it)
 *   res[4] m_next  (NM)              the inflation's state after the step (feed it back as arg[5])
 * {name}_covariance(arg, res, iw, w, mem): arg[0] z (NZ), arg[1] w (NW), arg[2] xhat (NX) -> res[0] P
 *   (NX*NX), the covariance at the start (with z_0, w_0, xhat_0; not inflated).""")
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
 *   res[0] z_next  (NZ), res[1] w_next (NW), res[2] xhat_next (NX){covariance}
 * {name}_decode(arg, res, iw, w, mem): arg[0] z (NZ), arg[1] w -> res[0] xhat (NX).
 * {name}_init(arg, res, iw, w, mem): arg[0] y_0 (NY), arg[1] u_0 (NU) -> res[0] w_0 (NW), the
 *   memory at the start.{monitor}
 * Start: z_0 = 0, w_0 = init(u_0), xhat_0 = decode(z_0, w_0).
 * The CSV columns {name}_main reads, by name: {macro}_TIME_COL, {macro}_Y_COLS (the outputs in
 *   order), {macro}_U_COLS (the inputs in order); it writes time, {macro}_STATE_NAMES. The sample
 *   guard (kklcasadi.observer.guard): [y; u] outside [{macro}_GUARD_LO, {macro}_GUARD_HI] or not finite
 *   is not fed; a step whose z leaves [{macro}_GUARD_Z_LO, {macro}_GUARD_Z_HI] restarts the run
 *   (HUGE_VAL where unbounded; these use <math.h>).
 * Work arrays: arg[{macro}_SZ_ARG], res[{macro}_SZ_RES], iw[{macro}_SZ_IW],
 * w[{macro}_SZ_W] (enough for both functions); outputs must not alias inputs; mem = 0.
 *
 * Code: matvec={matvec!r}, math={math!r}, dispatch={dispatch!r}, precision={precision!r}
 * (casadi_real is {"float" if precision == "float32" else "double"}; kklcasadi.observer.codegen).
 * Build:
 *   {build}
 */
#ifndef {macro}_H
#define {macro}_H

{chr(10).join(lines)}

{casadi_header.strip()}

#endif /* {macro}_H */
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
        raise error("flags", f"a sequence of strings such as {DEFAULT_FLAGS}", Text(type(flags).__name__),
                    kind=TypeError)
    for flag in flags:
        if not isinstance(flag, str) or not re.fullmatch(r"-[^\s'\"\\]+", flag):
            raise error("flags", f"compiler options that start with '-' and hold no blanks or quotes, such as "
                        f"{DEFAULT_FLAGS}", flag)
    return tuple(flags)


def c_targets(out_dir: Union[str, os.PathLike], names: Sequence[str], overwrite: bool) -> tuple[Path, list[Path]]:
    """The output directory of C files and their paths, checked: a directory path (or a new one), and none of
    the files there already unless ``overwrite``.

    Raises
    ------
    TypeError
        ``out_dir`` is not a path.
    ValueError
        ``out_dir`` is a file.
    FileExistsError
        One of the files exists and ``overwrite`` is False.
    """
    if not isinstance(out_dir, (str, os.PathLike)):
        raise error("out_dir", "a path", Text(type(out_dir).__name__), kind=TypeError)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise error("out_dir", "a directory", str(out), "It is a file; choose a directory path.")
    paths = [out / name for name in names]
    existing = [p for p in paths if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{existing[0]}: already exists; pass overwrite=True to replace it, or choose another "
                              "out_dir or name.")
    return out, paths


def casadi_source(functions: Sequence[ca.Function], name: str, *, matvec: str = "axpy", math: str = "vector",
                  dispatch: bool = True) -> tuple[str, str, dict[str, int]]:
    """The C of CasADi Functions as :func:`generate_c` writes it: CasADi's code generation, the
    rewrites of :mod:`.kernels` and the ``#pragma`` lines that let it compile with ``-Wall -Wextra
    -Werror`` (the EKF's :meth:`~kklcasadi.estimators.ekf.EKF.generate_c` uses it too).

    Parameters
    ----------
    functions : sequence of casadi.Function
        Named as their C symbols are to be (``name_step``, ...).
    name : str
        The C file's name (``name.c``), a C identifier.
    matvec, math, dispatch
        As for :func:`generate_c`.

    Returns
    -------
    source : str
        The C source.
    casadi_header : str
        CasADi's header of it (declarations and the ``<function>_SZ_*`` work-size macros).
    sizes : dict
        The largest work sizes over the functions: ``SZ_ARG``, ``SZ_RES``, ``SZ_IW``, ``SZ_W``.
    """
    name = check_c_name(name)
    matvec = one_of(matvec, "matvec", MATVECS)
    math = one_of(math, "math", MATHS)
    if not isinstance(dispatch, bool):
        raise error("dispatch", "a bool", Text(type(dispatch).__name__), kind=TypeError)
    generator = ca.CodeGenerator(f"{name}.c", {"with_header": True, "casadi_real": "double"})
    for f in functions:
        generator.add(f)
    with tempfile.TemporaryDirectory() as tmp:
        generator.generate(tmp + os.sep)
        source = (Path(tmp) / f"{name}.c").read_text()
        casadi_header = (Path(tmp) / f"{name}.h").read_text()
    source = rewrite(source, matvec == "axpy", math == "vector", dispatch)
    return (f"{template('pragma_push')}{source}{template('pragma_pop')}", casadi_header,
            _work_sizes(casadi_header, [f.name() for f in functions]))


def _single(precision: str, math: str, dispatch: bool) -> bool:
    """Whether ``precision`` is float32; its options checked (the vector exp/tanh and the AVX2 kernels are
    double code)."""
    single = one_of(precision, "precision", PRECISIONS) == "float32"
    fix = "Leave math and dispatch at their defaults (the vector exp/tanh and the AVX2 kernels are double code)."
    if single and math != "libm":
        raise error("math", "'libm' with precision='float32'", math, fix)
    if single and dispatch:
        raise error("dispatch", "False with precision='float32'", dispatch, fix)
    return single


def generate_c(observer: KKLObserver, out_dir: Union[str, os.PathLike], name: str = "kkl_obs",
               *, overwrite: bool = False, matvec: str = "axpy", math: Optional[str] = None,
               dispatch: Optional[bool] = None, flags: Sequence[str] = DEFAULT_FLAGS, time_col: str = "time",
               y_cols: Optional[Sequence[str]] = None, u_cols: Optional[Sequence[str]] = None,
               state_names: Optional[Sequence[str]] = None, precision: str = "float64") -> list[Path]:
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
    math : {"vector", "libm"}, optional
        ``exp`` and ``tanh``: branch-free C99 arithmetic that vectorises, within 3 ulp of the C
        library, so that the step is within :data:`VECTOR_MATH_TOLERANCE` of the CasADi VM
        (the default in float64); or the C library's functions, bitwise as the CasADi VM (with
        ``matvec="axpy"`` or ``"casadi"``; the only choice, and the default, in float32).
    dispatch : bool, optional
        With gcc or clang on x86, also compile the kernels and the vector exp/tanh for AVX2
        (gcc vector extensions, under ``#if``) and use that version where the CPU has it:
        chosen at run time (``__builtin_cpu_supports``), or always when the build targets AVX2
        (``-march=native`` on a recent CPU). The results are the same bit for bit.
        ``-DKKLC_NO_DISPATCH`` at compile time, or ``dispatch=False`` (no extensions in the
        source), leaves the portable C99 version only. Default True in float64, False (the only
        choice) in float32.
    flags : sequence of str
        The compiler options written into the build lines of ``name.h`` and ``name_main.c``
        (``gcc FLAGS name.c name_main.c -lm -o name``); default :data:`DEFAULT_FLAGS`
        (portable). :data:`NATIVE_FLAGS` adds ``-march=native`` (faster, for the build
        machine's CPU only). The source compiles without warnings under ``-Wall -Wextra`` with
        either. Bitwise equality with the CasADi VM needs a build without floating-point
        contraction, as ``-std=c99`` gives (no ``-ffast-math``, no ``-ffp-contract=fast``).
    time_col : str
        The column of times the ``main`` reads from a log's header.
    y_cols, u_cols : sequence of str, optional
        The columns of the outputs and the inputs it reads, in the plant's order; default ``y1 ..
        yN`` and ``u1 .. uM``. Printable ASCII without commas, quotes or backslashes, distinct.
    state_names : sequence of str, optional
        The columns of the estimates it writes; default ``x1 .. xN`` (as ``kklcasadi estimate``).
    precision : {"float64", "float32"}
        The C type of every value: ``double`` (default), or ``float`` for microcontrollers whose
        FPU is single precision (Cortex-M4F, M33): every constant, weight, work array and
        argument is a ``float``, the C library's float functions (``tanhf``, ``expf``) are
        called, and ``casadi_int`` is ``int``. The step then differs from the float64 step by
        the rounding of float (see docs/design.md, "float32 C", for the error over whole trials);
        ``name_main.c`` still reads the times in double.

    Returns
    -------
    list of Path
        ``[name.c, name.h, name_main.c]``.

    Raises
    ------
    ValueError
        ``name`` is not a valid C identifier, ``out_dir`` exists and is not a directory,
        ``matvec``, ``math`` or ``precision`` is not one of the choices, a flag is not an option
        word, or float32 is asked with ``math="vector"`` or ``dispatch=True``.
    TypeError
        ``flags`` is not a sequence of strings, ``dispatch`` not a bool, or another argument
        has the wrong type.
    FileExistsError
        One of the files exists and ``overwrite`` is False.
    """
    if not isinstance(observer, KKLObserver):
        raise error("observer", "a KKLObserver", Text(type(observer).__name__), kind=TypeError)
    name = check_c_name(name)
    single = one_of(precision, "precision", PRECISIONS) == "float32"
    math = one_of(("libm" if single else "vector") if math is None else math, "math", MATHS)
    dispatch = not single if dispatch is None else dispatch
    matvec = one_of(matvec, "matvec", MATVECS)
    if not isinstance(dispatch, bool):
        raise error("dispatch", "a bool", Text(type(dispatch).__name__), kind=TypeError)
    _single(precision, math, dispatch)
    flags = check_flags(flags)
    columns = {"time": _column_names((time_col,) if isinstance(time_col, str) else time_col, "time_col", 1, "time"),
               "y": _column_names(y_cols, "y_cols", observer.ny, "y"),
               "u": _column_names(u_cols, "u_cols", observer.nu, "u"),
               "states": _column_names(state_names, "state_names", observer.nx, "x")}
    read = columns["time"] + columns["y"] + columns["u"]
    if len(set(read)) != len(read):
        raise error("time_col, y_cols, u_cols", "distinct column names", list(read))
    if len(set(columns["states"])) != observer.nx or {"time", "in_domain", "status"} & set(columns["states"]):
        raise error("state_names", "distinct names other than 'time', 'in_domain' and 'status'",
                    list(columns["states"]))
    out, paths = c_targets(out_dir, [f"{name}.c", f"{name}.h", f"{name}_main.c"], overwrite)

    step = observer.step if observer.step_covariance is None else observer.step_covariance
    functions = [renamed(step, f"{name}_step"), renamed(observer.decode, f"{name}_decode"),
                 # the start only, once: as SX, so that it has no nested calls (gcc's -Wdangling-pointer)
                 renamed(observer.memory_init, f"{name}_init", ca.SX)]
    if observer.domain_check is not None:          # the domain monitor, where the card records a domain or monitor
        functions.append(renamed(observer.domain_check, f"{name}_in_domain"))
    if observer.covariance is not None:            # the covariance of the estimate, where the card has a head
        functions.append(renamed(observer.covariance, f"{name}_covariance"))
    source, casadi_header, sizes = casadi_source(functions, name, matvec=matvec, math=math, dispatch=dispatch)
    build = f"gcc {' '.join(flags)} {name}.c {name}_main.c -lm -o {name}"
    if single:                                     # the same C with float values and calls (kernels.single_precision)
        source, casadi_header = single_precision(source), single_precision(casadi_header)

    write_dir(out, {paths[0].name: f"/* {name}.c -- KKL observer step generated by kklcasadi; see {name}.h. */\n"
                                   f"{source}",
                    paths[1].name: _header(observer, name, casadi_header, sizes, build, matvec, math, dispatch,
                                           columns, precision),
                    paths[2].name: template("main").replace("__BUILD__", build).replace("__NAME__", name)
                    .replace("__MACRO__", name.upper())}, overwrite=overwrite, argument="out_dir")
    return paths
