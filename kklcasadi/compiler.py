"""Any CasADi Function as C, built once with gcc and loaded with ``ca.external``: the compiled paths of the
observer's :meth:`~kklcasadi.observer.kkl.KKLObserver.simulate` and of the benchmarks.

:class:`Compiler` turns any :class:`casadi.Function` into a shared library: the C source from
:class:`casadi.CodeGenerator`, an optional source post-processing hook, then the C compiler. The
library is cached on disk under the SHA-256 of the source, the compiler and its flags, so a
Function is compiled once per machine; an unchanged Function loads in milliseconds. Without the
compiler the Function runs in the CasADi VM, with a :class:`CompilerWarning`. :meth:`Compiler.build`
separates the CasADi part (the source) from the C compiler's run, so that ``precompile`` runs
several compilers at once while the caller's thread does other work (simulating trials)
(:func:`kklcasadi.evaluation.compiled.precompile`).

The default flags are portable (``-O3 -ffp-contract=off``, no ``-march=native``): with the same
expression graph the compiled Function returns bitwise the VM's values (``-ffp-contract=off``
keeps compilers from fusing multiply-adds on targets that have FMA).
"""

from __future__ import annotations

import functools
import hashlib
import os
import shutil
import subprocess
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Union

import casadi as ca

from .cache import cache_root

__all__ = ["Compiler", "CompilerWarning", "Build", "compile_function", "DEFAULT_FLAGS", "children_cpu", "c_name",
           "code_digest"]

#: Portable optimisation flags; ``-fPIC -shared`` are always added.
DEFAULT_FLAGS = ("-O3", "-ffp-contract=off")

PathLike = Union[str, os.PathLike]


class CompilerWarning(UserWarning):
    """The C compiler is not available: the Function runs in the CasADi VM instead."""


@dataclass(frozen=True)
class Build:
    """One Function's shared library, its C source ready: :meth:`run` compiles it, :meth:`load` loads it.

    :meth:`run` does not touch CasADi, so several builds can run on threads at once.

    Attributes
    ----------
    name : str
        The Function's name (the symbol in the library).
    library : Path
        Where the library is (or will be) cached.
    source : str
        The C source.
    command : tuple of str
        The compiler and its flags (the source and output paths are added).
    """

    name: str
    library: Path
    source: str
    command: tuple

    def run(self) -> Path:
        """Compile the library unless it is cached; its path.

        Raises
        ------
        RuntimeError
            The compiler failed (its command line and the end of its output are in the message;
            the source is kept as ``<library>.failed.c``).
        """
        library = self.library
        if library.exists():
            return library
        library.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=library.parent, prefix=".build-") as build:
            source = Path(build) / f"{self.name}.c"
            source.write_text(self.source)
            target = Path(build) / library.name
            command = [*self.command, "-fPIC", "-shared", str(source), "-o", str(target), "-lm"]
            result = subprocess.run(command, capture_output=True, text=True)
            if result.returncode != 0:
                kept = library.with_suffix(".failed.c")
                os.replace(source, kept)
                tail = (result.stderr or result.stdout)[-2000:]
                raise RuntimeError(f"compiling {self.name!r} failed (exit {result.returncode}; source kept in "
                                   f"{kept}): {' '.join(command)}\n{tail}")
            os.replace(source, library.with_suffix(".c"))
            os.replace(target, library)
        return library

    def load(self) -> ca.Function:
        """The compiled Function (``ca.external``); compiles first where needed."""
        return ca.external(self.name, str(self.run()))


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

    def build(self, f: ca.Function) -> Build:
        """The :class:`Build` of ``f``: its source written by CasADi, the compiler not yet run.

        Raises
        ------
        FileNotFoundError
            The compiler is not on ``PATH``.
        """
        compiler = shutil.which(self.command)
        if compiler is None:
            raise FileNotFoundError(f"C compiler {self.command!r} not found on PATH; install it (e.g. gcc) or "
                                    "pass Compiler(command=...).")
        text = self.source(f)
        key = hashlib.sha256("\0".join((text, self.command, *self.flags)).encode()).hexdigest()
        return Build(f.name(), self.directory / f"{f.name()}_{key[:24]}.so", text, (compiler, *self.flags))

    def build_known(self, identity: Optional[str], make: Callable[[], ca.Function]) -> Build:
        """The :class:`Build` of ``make()``, without calling ``make`` where a library built for ``identity`` is cached.

        ``identity`` must determine the Function ``make()`` returns completely (its caller's inputs to it and the
        code that builds it: :func:`code_digest`); building some Functions (a long trajectory's sparsity, its C
        source) takes seconds, and this skips both on a warm cache. The index (``index/`` of the cache directory,
        one small file per identity, compiler, flags and :attr:`postprocess`) names the library the source-keyed
        :meth:`build` chose; an index whose library is gone, or ``identity`` None, or a :attr:`postprocess` without
        a module-level name (a lambda or closure, which no name identifies), builds as :meth:`build` does.

        Parameters
        ----------
        identity : str or None
        make : callable ``() -> casadi.Function``

        Raises
        ------
        FileNotFoundError
            The compiler is not on ``PATH``.
        """
        if identity is not None and not isinstance(identity, str):
            raise TypeError(f"identity: expected a str that determines the Function, or None, received "
                            f"{type(identity).__name__}.")
        if not callable(make):
            raise TypeError(f"make: expected a callable () -> casadi.Function, received {type(make).__name__}.")
        index = self._index(identity)
        if index is not None and index.is_file():
            name, _, library = index.read_text().partition("\n")
            path = self.directory / library.strip()
            if name.isidentifier() and path.parent == self.directory and path.is_file():
                return Build(name, path, "", (self.command, *self.flags))
        build = self.build(make())
        if index is not None:
            index.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile("w", dir=index.parent, prefix=".index-", delete=False) as temp:
                temp.write(f"{build.name}\n{build.library.name}\n")
            os.replace(temp.name, index)
        return build

    def _index(self, identity: Optional[str]) -> Optional[Path]:
        """The index file of ``identity`` under this compiler's settings, or None where none can be trusted."""
        hook = self.postprocess
        named = hook is None or ("<" not in hook.__qualname__ and "." not in hook.__qualname__)
        if identity is None or not named:
            return None
        hook_name = "" if hook is None else f"{hook.__module__}.{hook.__qualname__}"
        key = hashlib.sha256("\0".join((identity, ca.CasadiMeta.version(), self.command, *self.flags,
                                         hook_name)).encode())
        return self.directory / "index" / key.hexdigest()[:32]

    def library(self, f: ca.Function) -> Path:
        """Compile ``f`` (or find it in the cache); the path of its shared library.

        Raises
        ------
        FileNotFoundError
            The compiler is not on ``PATH``.
        RuntimeError
            The compiler failed (see :meth:`Build.run`).
        """
        return self.build(f).run()

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
            self._warn_missing(f)
            return f
        return self.build(f).load()

    def _warn_missing(self, f: ca.Function) -> None:
        warnings.warn(f"C compiler {self.command!r} not found on PATH; {f.name()!r} runs in the CasADi VM "
                      "(slower, same values). Install gcc or pass Compiler(command=...).", CompilerWarning,
                      stacklevel=3)


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


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """SHA-256 of kklcasadi's own code (every ``.py`` and ``.c`` file of the package, by relative path): part of
    an identity for :meth:`Compiler.build_known`, so that a changed package never reuses a library it built
    before (computed once per process)."""
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.suffix in (".py", ".c") and "__pycache__" not in p.parts):
        digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def children_cpu(before: os.times_result) -> float:
    """CPU seconds of the child processes (the C compiler) waited for since ``before``."""
    after = os.times()
    return after.children_user + after.children_system - before.children_user - before.children_system


def c_name(text: str) -> str:
    """``text`` with every character that is not a letter, digit or underscore replaced by ``_``."""
    return "".join(c if c.isalnum() or c == "_" else "_" for c in text)
