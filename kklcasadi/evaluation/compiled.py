"""Compiled trajectories: a CasADi Function as C, built once with gcc and loaded with ``ca.external``.

:class:`Compiler` turns any :class:`casadi.Function` into a shared library: the C source from
:class:`casadi.CodeGenerator`, an optional source post-processing hook, then the C compiler. The
library is cached on disk under the SHA-256 of the source, the compiler and its flags, so a
Function is compiled once per machine; an unchanged Function loads in milliseconds. Without the
compiler the Function runs in the CasADi VM, with a :class:`CompilerWarning`.

The default flags are portable (``-O3 -ffp-contract=off``, no ``-march=native``): with the same
expression graph the compiled Function returns bitwise the VM's values (``-ffp-contract=off``
keeps compilers from fusing multiply-adds on targets that have FMA).

:class:`CompiledEstimator` is the estimator protocol of the fast benchmark path: an estimator
that gives one trial's estimate as a CasADi Function ``(y (ny, N), u (nu, N), s0) -> xhat (nx, N)``
and its initial state ``s0``; calling it compiles that Function and maps it over the trials on
threads. :func:`observer_estimator`
and :func:`ekf_estimator` adapt a :class:`~kklcasadi.observer.kkl.KKLObserver` and an
:class:`~kklcasadi.estimators.ekf.EKF`; each is bitwise its reference path (``obs.simulate``,
``ekf.simulate``).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
import warnings
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Optional, Union

import casadi as ca
import numpy as np

from .trialcache import cache_root

if TYPE_CHECKING:
    from ..estimators.ekf import EKF
    from ..observer.kkl import KKLObserver

__all__ = ["Compiler", "CompilerWarning", "compile_function", "CompiledEstimator", "CompiledObserver",
           "CompiledEKF", "observer_estimator", "ekf_estimator", "DEFAULT_FLAGS"]

#: Portable optimisation flags; ``-fPIC -shared`` are always added.
DEFAULT_FLAGS = ("-O3", "-ffp-contract=off")

PathLike = Union[str, os.PathLike]


class CompilerWarning(UserWarning):
    """The C compiler is not available: the Function runs in the CasADi VM instead."""


@dataclass(frozen=True)
class Compiler:
    """How to compile CasADi Functions to shared libraries (see :meth:`compile`).

    Parameters
    ----------
    command : str
        The C compiler (a name on ``PATH`` or a path), called as
        ``command *flags -fPIC -shared source.c -o library.so -lm``.
    flags : tuple of str
        Optimisation flags; default :data:`DEFAULT_FLAGS` (portable, bitwise the VM).
    cache_dir : path-like, optional
        Where libraries are kept; default ``<cache_root()>/compiled`` (``$KKLCASADI_CACHE``).
    postprocess : callable ``str -> str``, optional
        Rewrites the generated C source before it is compiled (e.g. a faster mat-vec kernel).
        The cache key is the rewritten source, so changing the hook recompiles.
    """

    command: str = "gcc"
    flags: tuple = DEFAULT_FLAGS
    cache_dir: Optional[PathLike] = None
    postprocess: Optional[Callable[[str], str]] = None

    def __post_init__(self) -> None:
        if not isinstance(self.command, str) or not self.command:
            raise TypeError(f"command: expected the C compiler's name or path, received {self.command!r}.")
        if isinstance(self.flags, str) or not all(isinstance(f, str) for f in self.flags):
            raise TypeError(f"flags: expected a tuple of str such as ('-O3',), received {self.flags!r}.")
        object.__setattr__(self, "flags", tuple(self.flags))
        if self.cache_dir is not None and not isinstance(self.cache_dir, (str, os.PathLike)):
            raise TypeError(f"cache_dir: expected a path or None, received {type(self.cache_dir).__name__}.")
        if self.postprocess is not None and not callable(self.postprocess):
            raise TypeError(f"postprocess: expected a callable str -> str or None, received "
                            f"{type(self.postprocess).__name__}.")

    @property
    def directory(self) -> Path:
        """The library cache directory."""
        return Path(self.cache_dir).expanduser() if self.cache_dir is not None else cache_root() / "compiled"

    def available(self) -> bool:
        """Whether :attr:`command` can be run."""
        return shutil.which(self.command) is not None

    def source(self, f: ca.Function) -> str:
        """The C source compiled for ``f`` (after :attr:`postprocess`)."""
        if not isinstance(f, ca.Function):
            raise TypeError(f"f: expected a casadi.Function, received {type(f).__name__}.")
        generator = ca.CodeGenerator(f"{f.name()}.c", {"with_header": False})
        generator.add(f)
        text = generator.dump()
        if self.postprocess is not None:
            text = self.postprocess(text)
            if not isinstance(text, str):
                raise TypeError(f"postprocess: expected it to return the C source as str, received "
                                f"{type(text).__name__}.")
        return text

    def library(self, f: ca.Function) -> Path:
        """Compile ``f`` (or find it in the cache); the path of its shared library.

        Raises
        ------
        FileNotFoundError
            The compiler is not on ``PATH``.
        RuntimeError
            The compiler failed (its command line and the end of its output are in the message;
            the source is kept as ``<library>.failed.c``).
        """
        compiler = shutil.which(self.command)
        if compiler is None:
            raise FileNotFoundError(f"C compiler {self.command!r} not found on PATH; install it (e.g. gcc) or "
                                    "pass Compiler(command=...).")
        text = self.source(f)
        key = hashlib.sha256("\0".join((text, self.command, *self.flags)).encode()).hexdigest()
        library = self.directory / f"{f.name()}_{key[:24]}.so"
        if library.exists():
            return library
        library.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=library.parent, prefix=".build-") as build:
            source = Path(build) / f"{f.name()}.c"
            source.write_text(text)
            target = Path(build) / library.name
            command = [compiler, *self.flags, "-fPIC", "-shared", str(source), "-o", str(target), "-lm"]
            result = subprocess.run(command, capture_output=True, text=True)
            if result.returncode != 0:
                kept = library.with_suffix(".failed.c")
                os.replace(source, kept)
                tail = (result.stderr or result.stdout)[-2000:]
                raise RuntimeError(f"compiling {f.name()!r} failed (exit {result.returncode}; source kept in "
                                   f"{kept}): {' '.join(command)}\n{tail}")
            os.replace(source, library.with_suffix(".c"))
            os.replace(target, library)
        return library

    def compile(self, f: ca.Function) -> ca.Function:
        """``f`` as compiled code: a ``ca.external`` Function with the same inputs and outputs.

        Falls back to ``f`` itself (CasADi VM) with a :class:`CompilerWarning` when the compiler
        is not on ``PATH``.

        Parameters
        ----------
        f : casadi.Function

        Returns
        -------
        casadi.Function
        """
        if not isinstance(f, ca.Function):
            raise TypeError(f"f: expected a casadi.Function, received {type(f).__name__}.")
        if not self.available():
            warnings.warn(f"C compiler {self.command!r} not found on PATH; {f.name()!r} runs in the CasADi VM "
                          "(slower, same values). Install gcc or pass Compiler(command=...).", CompilerWarning,
                          stacklevel=2)
            return f
        return ca.external(f.name(), str(self.library(f)))


def compile_function(f: ca.Function, *, command: str = "gcc", flags: tuple = DEFAULT_FLAGS,
                     cache_dir: Optional[PathLike] = None,
                     postprocess: Optional[Callable[[str], str]] = None) -> ca.Function:
    """Compile a CasADi Function to a cached shared library (see :class:`Compiler`).

    Parameters
    ----------
    f : casadi.Function
    command, flags, cache_dir, postprocess
        See :class:`Compiler`.

    Returns
    -------
    casadi.Function
        The compiled Function (``ca.external``), or ``f`` when the compiler is missing.
    """
    return Compiler(command, flags, cache_dir, postprocess).compile(f)


# ---------------------------------------------------------------------- estimators
class CompiledEstimator(ABC):
    """An estimator that runs each trial through one CasADi Function, compiled, mapped over trials.

    Subclasses give :meth:`trajectory`: one trial of ``n`` samples,
    ``(y (ny, n), u (nu, n), s0 (ns, 1)) -> xhat (nx, n)``, ``u_k`` held over ``[t_k, t_k+1)``,
    started from the estimator's :meth:`initial_state` ``s0``. Calling the estimator compiles that
    Function (once per ``n``) and maps it over the trials on threads. It is an
    :data:`kklcasadi.evaluation.protocol.BatchEstimator`.

    Parameters
    ----------
    nx, nu, ny : int
        Sizes of the plant.
    dt : float
        Sample period the estimator runs at.
    compiler : Compiler or None
        How to compile; None runs the CasADi VM (the reference path).
    n_threads : int, optional
        Worker threads over trials (default: the CPU count).
    """

    def __init__(self, nx: int, nu: int, ny: int, dt: float, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None) -> None:
        if compiler is not None and not isinstance(compiler, Compiler):
            raise TypeError(f"compiler: expected a kklcasadi.evaluation.compiled.Compiler or None, received "
                            f"{type(compiler).__name__}.")
        if n_threads is not None and (isinstance(n_threads, bool) or not isinstance(n_threads, int)
                                      or n_threads < 1):
            raise ValueError(f"n_threads: expected a positive int or None, received {n_threads!r}.")
        self.nx, self.nu, self.ny, self.dt = nx, nu, ny, float(dt)
        self.compiler = compiler
        self.n_threads = n_threads
        self._functions: dict[int, ca.Function] = {}

    @abstractmethod
    def trajectory(self, n: int) -> ca.Function:
        """One trial over ``n`` >= 2 samples: ``(y (ny, n), u (nu, n), s0 (ns, 1)) -> xhat (nx, n)`` (VM)."""

    @abstractmethod
    def initial_state(self) -> np.ndarray:
        """The ``s0`` (ns,) every trial starts from."""

    def function(self, n: int) -> ca.Function:
        """:meth:`trajectory` as it runs: compiled (cached per ``n``), or the VM Function."""
        if n not in self._functions:
            f = self.trajectory(n)
            self._functions[n] = f if self.compiler is None else self.compiler.compile(f)
        return self._functions[n]

    def __call__(self, t: Any, y: Any, u: Any) -> np.ndarray:
        """Estimate M trials.

        Parameters
        ----------
        t : array_like, shape (N,)
            Sample times spaced by :attr:`dt`, N >= 2.
        y : array_like, shape (M, N, ny)
        u : array_like, shape (M, N, nu)

        Returns
        -------
        numpy.ndarray, shape (M, N, nx)
        """
        t, y, u = self._check(t, y, u)
        m, n = y.shape[:2]
        if m == 0:
            return np.empty((0, n, self.nx))
        threads = self.n_threads or os.cpu_count() or 1
        mapped = self.function(n).map(m, "thread", min(threads, m))
        out = mapped(y.transpose(2, 0, 1).reshape(self.ny, m * n), u.transpose(2, 0, 1).reshape(self.nu, m * n),
                     self.initial_state())
        return np.asarray(out).reshape(self.nx, m, n).transpose(1, 2, 0)

    def _check(self, t: Any, y: Any, u: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        if t.ndim != 1 or t.size < 2:
            raise ValueError(f"t: expected sample times of shape (N,) with N >= 2, received shape {t.shape}.")
        steps = np.diff(t)
        if not np.allclose(steps, self.dt, rtol=1e-9, atol=1e-12 * max(1.0, abs(t[-1]))):
            k = int(np.argmax(np.abs(steps - self.dt)))
            raise ValueError(f"t: expected samples spaced by dt = {self.dt}, received t[{k + 1}] - t[{k}] = "
                             f"{steps[k]}.")
        n = t.size
        y = np.asarray(y, dtype=float)
        u = np.asarray(u, dtype=float)
        if y.ndim != 3 or y.shape[1:] != (n, self.ny):
            raise ValueError(f"y: expected shape (M, {n}, {self.ny}), received {y.shape}.")
        if u.shape != (y.shape[0], n, self.nu):
            raise ValueError(f"u: expected shape ({y.shape[0]}, {n}, {self.nu}), received {u.shape}.")
        for name, values in (("y", y), ("u", u)):
            bad = np.argwhere(~np.isfinite(values))
            if bad.size:
                raise ValueError(f"{name}: expected finite values, received {values[tuple(bad[0])]} at trial "
                                 f"{bad[0, 0]}, sample {bad[0, 1]}.")
        return t, y, u


class CompiledObserver(CompiledEstimator):
    """A :class:`~kklcasadi.observer.kkl.KKLObserver` as a :class:`CompiledEstimator`.

    The trajectory is the observer's own Functions: ``s0 = z_0 = 0`` (docs/protocol.md), the
    memory ``w_0 = memory_init(y_0, u_0)``, ``xhat_0 = decode(z_0, w_0)``, then ``step`` folded with
    ``mapaccum``; bitwise :meth:`KKLObserver.simulate`.

    Parameters
    ----------
    observer : KKLObserver
    compiler, n_threads
        See :class:`CompiledEstimator`.
    """

    def __init__(self, observer: KKLObserver, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None) -> None:
        from ..observer.kkl import KKLObserver

        if not isinstance(observer, KKLObserver):
            raise TypeError(f"observer: expected a kklcasadi.KKLObserver, received {type(observer).__name__}.")
        super().__init__(observer.nx, observer.nu, observer.ny, observer.dt, compiler=compiler,
                         n_threads=n_threads)
        self.observer = observer

    def trajectory(self, n: int) -> ca.Function:
        obs = self.observer
        y, u, z0 = ca.MX.sym("y", obs.ny, n), ca.MX.sym("u", obs.nu, n), ca.MX.sym("z0", obs.nz)
        w0 = obs.memory_init(y[:, 0], u[:, 0])
        steps = obs.step.mapaccum("trajectory", n - 1, [0, 1], [0, 1])
        _, _, xhat = steps(z0, w0, y[:, :n - 1], y[:, 1:], u[:, 1:])
        return ca.Function(f"{_c_name(obs.system.name)}_{obs.method}_n{n}", [y, u, z0],
                           [ca.horzcat(obs.decode(z0, w0), xhat)], ["y", "u", "s0"], ["xhat"])

    def initial_state(self) -> np.ndarray:
        """``z_0 = 0`` (nz,)."""
        return np.zeros(self.observer.nz)


class CompiledEKF(CompiledEstimator):
    """An :class:`~kklcasadi.estimators.ekf.EKF` as a :class:`CompiledEstimator`; bitwise :meth:`EKF.simulate`.

    The trajectory is the filter's own Functions: ``s0 = [x0; vec(P0)]`` (its prior), ``update``
    at ``(x0, P0, y_0)``, then ``step`` (predict with ``u_k``, update with ``y_k+1``) folded with
    ``mapaccum``.

    Parameters
    ----------
    ekf : EKF
    compiler, n_threads
        See :class:`CompiledEstimator`.
    """

    def __init__(self, ekf: EKF, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None) -> None:
        from ..estimators.ekf import EKF

        if not isinstance(ekf, EKF):
            raise TypeError(f"ekf: expected a kklcasadi.estimators.ekf.EKF, received {type(ekf).__name__}.")
        system = ekf.system
        super().__init__(system.nx, system.nu, system.ny, ekf.dt, compiler=compiler, n_threads=n_threads)
        self.ekf = ekf

    def trajectory(self, n: int) -> ca.Function:
        ekf, nx = self.ekf, self.nx
        y, u = ca.MX.sym("y", self.ny, n), ca.MX.sym("u", self.nu, n)
        prior = ca.MX.sym("s0", nx + nx * nx)
        x0, P0 = ekf.update(prior[:nx], ca.reshape(prior[nx:], nx, nx), y[:, 0])
        steps = ekf.step.mapaccum("ekf_traj", n - 1)
        states = steps(ca.vertcat(x0, ca.vec(P0)), ca.vertcat(u[:, :n - 1], y[:, 1:]))
        return ca.Function(f"{_c_name(ekf.system.name)}_ekf_n{n}", [y, u, prior],
                           [ca.horzcat(x0, states[:nx, :])], ["y", "u", "s0"], ["xhat"])

    def initial_state(self) -> np.ndarray:
        """The prior ``[x0; vec(P0)]`` (nx + nx^2,), ``vec`` column-major."""
        return np.concatenate([self.ekf.x0, self.ekf.P0.ravel(order="F")])


def observer_estimator(observer: KKLObserver, *, compiler: Optional[Compiler] = Compiler(),
                       n_threads: Optional[int] = None) -> CompiledObserver:
    """The fast estimator of an observer: its trajectory compiled, mapped over trials.

    Parameters
    ----------
    observer : KKLObserver
    compiler : Compiler or None
        None: the CasADi VM (the reference, ``observer.simulate``'s path).
    n_threads : int, optional
        Worker threads over trials (default: the CPU count).

    Returns
    -------
    CompiledObserver
        ``est(t (N,), y (M, N, ny), u (M, N, nu)) -> xhat (M, N, nx)``.
    """
    return CompiledObserver(observer, compiler=compiler, n_threads=n_threads)


def ekf_estimator(ekf: EKF, *, compiler: Optional[Compiler] = Compiler(),
                  n_threads: Optional[int] = None) -> CompiledEKF:
    """The fast estimator of an EKF (see :func:`observer_estimator`); the filter is unchanged."""
    return CompiledEKF(ekf, compiler=compiler, n_threads=n_threads)


def _c_name(text: str) -> str:
    """``text`` with every character that is not a letter, digit or underscore replaced by ``_``."""
    return "".join(c if c.isalnum() or c == "_" else "_" for c in text)
