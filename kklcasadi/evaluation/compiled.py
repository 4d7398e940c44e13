"""Compiled trajectories: a CasADi Function as C, built once with gcc and loaded with ``ca.external``.

:class:`Compiler` turns any :class:`casadi.Function` into a shared library: the C source from
:class:`casadi.CodeGenerator`, an optional source post-processing hook, then the C compiler. The
library is cached on disk under the SHA-256 of the source, the compiler and its flags, so a
Function is compiled once per machine; an unchanged Function loads in milliseconds. Without the
compiler the Function runs in the CasADi VM, with a :class:`CompilerWarning`. :meth:`Compiler.build`
separates the CasADi part (the source) from the C compiler's run, so that :func:`precompile` runs
several compilers at once while the caller's thread does other work (simulating trials).

The default flags are portable (``-O3 -ffp-contract=off``, no ``-march=native``): with the same
expression graph the compiled Function returns bitwise the VM's values (``-ffp-contract=off``
keeps compilers from fusing multiply-adds on targets that have FMA).

:class:`CompiledEstimator` is the estimator protocol of the fast benchmark path: an estimator
that gives one trial's estimate as a CasADi Function ``(y (ny, N), u (nu, N), s0) -> xhat (nx, N)``
and its initial state ``s0``; calling it compiles that Function and maps it over the trials on
threads. :func:`observer_estimator` and :func:`ekf_estimator` adapt a
:class:`~kklcasadi.observer.kkl.KKLObserver` and an :class:`~kklcasadi.estimators.ekf.EKF`;
each is bitwise its reference path (``obs.simulate``, ``ekf.simulate``).

The observer's trajectory does only the work that its inputs require (:func:`split_step`): the part
of a step that depends on the input memory alone (the window GRU of ``obs`` and ``dyn`` with the
LoRA factors, the streaming context cell) is evaluated once per sample for every group of trials
that share their inputs (the noise-free and noisy cells of the benchmark, or the trials of the
zero-input regime), and reused while the memory does not change (a constant input, a square wave
between its edges); the model-based injection is skipped where the input is exactly 0, where it
is exactly 0. Every estimate is bitwise what the plain step gives (the same operations on the same
values, in the same order).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
import time
import warnings
from abc import ABC, abstractmethod
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Optional, Sequence, Union

import casadi as ca
import numpy as np

from .protocol import Profile, phase
from .trialcache import cache_root

if TYPE_CHECKING:
    from ..estimators.ekf import EKF
    from ..estimators.pf import ParticleFilter
    from ..observer.kkl import KKLObserver

__all__ = ["Compiler", "CompilerWarning", "Build", "compile_function", "CompiledEstimator", "CompiledObserver",
           "CompiledEKF", "CompiledRecord", "SplitStep", "split_step", "skip_at_zero_input", "reuse_decoded",
           "observer_estimator", "ekf_estimator", "pf_estimator", "precompile", "DEFAULT_FLAGS", "GROUP"]

#: Portable optimisation flags; ``-fPIC -shared`` are always added.
DEFAULT_FLAGS = ("-O3", "-ffp-contract=off")
#: Default largest group of trials with the same inputs that one trajectory runs together.
GROUP = 2

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


# ---------------------------------------------------------------------- the shared part of a step
def _nodes(outputs: Sequence[ca.MX]) -> list[ca.MX]:
    """Every node of the expression graph of ``outputs``, each once, dependencies first."""
    seen: set[int] = set()
    order: list[ca.MX] = []
    stack = [(node, False) for node in reversed(outputs)]
    while stack:
        node, expanded = stack.pop()
        if expanded:
            order.append(node)
            continue
        if hash(node) in seen:
            continue
        seen.add(hash(node))
        stack.append((node, True))
        stack.extend((node.dep(i), False) for i in reversed(range(node.n_dep())))
    return order


def _deps(node: ca.MX) -> list[ca.MX]:
    return [node.dep(i) for i in range(node.n_dep())]


def _tainted(nodes: Sequence[ca.MX], sources: Sequence[ca.MX]) -> dict[int, bool]:
    """Whether each node depends on one of the symbols ``sources``.

    An output of a Function call depends on the call's arguments that its Jacobian's sparsity
    says it depends on (the memory update takes ``y_next`` without reading it).
    """
    source = {hash(s) for s in sources}
    tainted: dict[int, bool] = {}
    for node in nodes:
        if node.is_symbolic():
            tainted[hash(node)] = hash(node) in source
        elif node.is_output():
            call = node.dep(0)
            f, j = call.which_function(), node.which_output()
            tainted[hash(node)] = any(tainted[hash(arg)] and f.sparsity_jac(i, j).nnz() > 0
                                      for i, arg in enumerate(_deps(call)))
        else:
            tainted[hash(node)] = any(tainted[hash(d)] for d in _deps(node))
    return tainted


def _costly(f: ca.Function) -> bool:
    """Whether a call of ``f`` does real work: a matrix product or a costly call inside an MX Function,
    anything but a plain SX expression otherwise (maps, folds, switches, SX networks of more than 100
    operations)."""
    if f.class_name() == "MXFunction":
        return any(f.instruction_id(k) == ca.OP_MTIMES
                   or (f.instruction_id(k) == ca.OP_CALL and _costly(f.instruction_MX(k).which_function()))
                   for k in range(f.n_instructions()))
    if f.class_name() == "SXFunction":
        return f.n_instructions() > 100
    return True


def _heavy(nodes: Sequence[ca.MX], tainted: dict[int, bool]) -> dict[int, bool]:
    """Whether each node is free of the sources and its subgraph does real work (see :func:`_costly`)."""
    heavy: dict[int, bool] = {}
    for node in nodes:
        key = hash(node)
        if tainted[key]:
            heavy[key] = False
        elif node.is_output():
            heavy[key] = heavy[hash(node.dep(0))] or _costly(node.dep(0).which_function())
        else:
            heavy[key] = node.is_multiplication() or any(heavy[hash(d)] for d in _deps(node))
    return heavy


def _holds_shared_work(f: ca.Function, tainted_in: Sequence[bool]) -> bool:
    """Whether an MX Function called with the arguments ``tainted_in`` does work free of them inside."""
    if f.class_name() != "MXFunction":
        return False
    args = [ca.MX.sym(f"a{i}", f.sparsity_in(i)) for i in range(f.n_in())]
    nodes = _nodes(f.call(args, True))
    tainted = _tainted(nodes, [a for a, t in zip(args, tainted_in) if t])
    heavy = _heavy(nodes, tainted)
    for node in nodes:
        if tainted[hash(node)]:
            if any(heavy[hash(d)] for d in _deps(node)):
                return True
            if node.is_call() and _holds_shared_work(node.which_function(),
                                                     [tainted[hash(d)] for d in _deps(node)]):
                return True
    return False


def _replace_outputs(outputs: list[ca.MX],
                     replacement: Callable[[ca.MX, list[ca.MX]], Optional[list[ca.MX]]]) -> list[ca.MX]:
    """``outputs`` with the outputs of some calls replaced, in the order of the graph.

    ``replacement(output, args)`` gives the new expression of a call's ``output`` node (or None to
    keep it), from the call's arguments ``args`` in which the outputs replaced before are replaced.
    """
    old: list[ca.MX] = []
    new: list[ca.MX] = []
    for node in _nodes(outputs):
        if node.is_output():
            args = _deps(node.dep(0))
            expression = replacement(node, ca.graph_substitute(args, old, new) if old else args)
            if expression is not None:
                old.append(node)
                new.append(expression)
    return ca.graph_substitute(outputs, old, new) if old else outputs


def _expand(outputs: list[ca.MX], sources: Sequence[ca.MX]) -> list[ca.MX]:
    """``outputs`` with every call inlined that depends on ``sources`` and holds work free of them."""
    while True:
        tainted = _tainted(_nodes(outputs), sources)
        inlined: dict[int, list[ca.MX]] = {}

        def inline(output: ca.MX, args: list[ca.MX]) -> Optional[list[ca.MX]]:
            call = output.dep(0)
            if not tainted[hash(call)]:
                return None
            if hash(call) not in inlined:
                f = call.which_function()
                shared_work = _holds_shared_work(f, [tainted[hash(a)] for a in _deps(call)])
                inlined[hash(call)] = f.call(args, True) if shared_work else None
            values = inlined[hash(call)]
            return None if values is None else values[output.which_output()]

        expanded = _replace_outputs(outputs, inline)
        if not any(v is not None for v in inlined.values()):
            return outputs
        outputs = expanded


def _untangle(outputs: list[ca.MX], sources: Sequence[ca.MX]) -> list[ca.MX]:
    """``outputs`` with each source-free output of a call that takes a source it does not read
    called again with zeros for that argument (the same values, without the source)."""
    tainted = _tainted(_nodes(outputs), sources)

    def clean(output: ca.MX, args: list[ca.MX]) -> Optional[ca.MX]:
        call = output.dep(0)
        mask = [tainted[hash(a)] for a in _deps(call)]
        if tainted[hash(output)] or not any(mask):
            return None
        f = call.which_function()
        return f.call([ca.DM.zeros(f.sparsity_in(i)) if t else a for i, (a, t) in enumerate(zip(args, mask))])[
            output.which_output()]

    return _replace_outputs(outputs, clean)


@dataclass(frozen=True)
class SplitStep:
    """An observer step split into the part its input memory alone decides and the per-trial rest.

    ``step(z, w, ..., u_next) -> (z_next, w_next, ...)`` is ``s = shared(w, u_next)`` (what depends
    on nothing but the memory ``w`` and the next input: the values the rest reads, then ``w_next``,
    packed in one column), then ``core(z, w, ..., u_next, s)``, the step's outputs but ``w_next``;
    bitwise the step.

    Attributes
    ----------
    shared : casadi.Function
        ``(w, u_next) -> s (ns, 1)``.
    core : casadi.Function
        The step's inputs, then ``s``; the step's outputs without ``w_next``.
    memory : tuple of int
        Rows of ``s`` that hold ``vec(w_next)`` (start, stop).
    """

    shared: ca.Function
    core: ca.Function
    memory: tuple

    def w_next(self, s: ca.MX, shape: tuple[int, int]) -> ca.MX:
        """``w_next`` from the packed ``s``."""
        return ca.reshape(s[self.memory[0]:self.memory[1]], *shape)


def split_step(step: ca.Function) -> Optional[SplitStep]:
    """Split an observer step into its memory-only part and the rest (see :class:`SplitStep`).

    Calls are inlined where they mix both (the LoRA decoder of ``dyn`` reads ``z`` and the window's
    GRU); the shared part is every value free of every input but ``w`` and ``u_next`` that does
    real work (a matrix product) and that the rest reads, and the memory update.

    Parameters
    ----------
    step : casadi.Function
        Inputs named ``z``, ``w``, ..., ``u_next`` and outputs ``z_next``, ``w_next``, ...
        (:attr:`KKLObserver.step`: ``(z, w, y, y_next, u_next) -> (z_next, w_next, xhat_next)``).

    Returns
    -------
    SplitStep or None
        None where there is nothing to share: the memory update reads the measurements (then each
        trial has its own memory), or neither the memory update nor anything the rest reads from
        the memory does real work.
    """
    names = step.name_in()
    args = [ca.MX.sym(name, step.sparsity_in(i)) for i, name in enumerate(names)]
    w, u_next = args[names.index("w")], args[names.index("u_next")]
    sources = [a for a in args if a is not w and a is not u_next]
    outputs = _untangle(_expand(step.call(args, True), sources), sources)
    memory = step.name_out().index("w_next")
    nodes = _nodes(outputs)
    tainted = _tainted(nodes, sources)
    if tainted[hash(outputs[memory])]:
        return None
    heavy = _heavy(nodes, tainted)
    frontier, seen = [], {hash(outputs[memory])}
    for node in nodes:
        if tainted[hash(node)]:
            for d in _deps(node):
                if heavy[hash(d)] and hash(d) not in seen:
                    seen.add(hash(d))
                    frontier.append(d)
    if not frontier and not heavy[hash(outputs[memory])]:
        return None
    values = frontier + [outputs[memory]]
    packed = [ca.sparsity_cast(v, ca.Sparsity.dense(v.nnz(), 1)) for v in values]
    offsets = np.cumsum([0] + [v.nnz() for v in values]).tolist()
    s = ca.MX.sym("s", offsets[-1])
    parts = [ca.sparsity_cast(s[a:b], v.sparsity()) for a, b, v in zip(offsets, offsets[1:], values)]
    rest = [out for i, out in enumerate(outputs) if i != memory]
    names_out = [name for i, name in enumerate(step.name_out()) if i != memory]
    shared = ca.Function("shared", [w, u_next], [ca.vertcat(*packed)], ["w", "u_next"], ["s"])
    core = ca.Function("core", args + [s], ca.graph_substitute(rest, values, parts), names + ["s"], names_out)
    return SplitStep(shared, core, (offsets[-2], offsets[-1]))


def reuse_decoded(step: ca.Function, injection: ca.Function,
                  decode: ca.Function) -> Optional[tuple[ca.Function, ca.Function]]:
    """``step`` reading ``xhat = decode(z, w)``, the estimate of the previous sample, instead of decoding
    its own ``z`` again where it calls ``injection(z, u)``.

    ``injection`` decodes its ``z`` with the decoder that ``decode`` calls (``inject``'s
    ``dT/dx(xhat) (f(xhat, u) - f(xhat, 0))`` at ``xhat = T*(z)``); at the step's own ``z`` (the
    first Runge-Kutta stage) that is the estimate the previous step output. The same values, one
    decoder evaluation less per step.

    Parameters
    ----------
    step : casadi.Function
        ``(z, w, y, y_next, u_next) -> (z_next, w_next, xhat_next)``.
    injection : casadi.Function
        ``(z, u) -> dz``.
    decode : casadi.Function
        ``(z, w) -> xhat``.

    Returns
    -------
    (casadi.Function, casadi.Function) or None
        The step with the input ``xhat`` after ``w``, and ``(xhat, u) -> dz`` (the injection of a
        decoded state); None where ``injection`` and ``decode`` do not decode with the same
        Function, or ``step`` does not call ``injection`` at its own ``z``.
    """
    z, u = ca.MX.sym("z", injection.sparsity_in(0)), ca.MX.sym("u", injection.sparsity_in(1))
    inner = injection.call([z, u], True)
    decoder = _decoded(inner, z)
    zd, wd = ca.MX.sym("z", decode.sparsity_in(0)), ca.MX.sym("w", decode.sparsity_in(1))
    outer = decode.call([zd, wd], True)[0]
    if decoder is None or not outer.is_output() or _decoded([outer], zd) is None or \
            hash(outer.dep(0).which_function()) != hash(decoder.dep(0).which_function()) or \
            outer.which_output() != decoder.which_output():
        return None
    xhat = ca.MX.sym("xhat", decoder.sparsity())
    rest = ca.graph_substitute(inner, [decoder], [xhat])
    if any(ca.depends_on(r, z) for r in rest):
        return None
    of_xhat = ca.Function(f"{injection.name()}_of_xhat", [xhat, u], rest, ["xhat", "u"], injection.name_out())
    names = step.name_in()
    args = [ca.MX.sym(name, step.sparsity_in(i)) for i, name in enumerate(names)]
    estimate = ca.MX.sym("xhat", decode.sparsity_out(0))
    own_z = hash(args[names.index("z")])

    def reuse(output: ca.MX, call_args: list[ca.MX]) -> Optional[ca.MX]:
        call = output.dep(0)
        if hash(call.which_function()) != hash(injection) or hash(call.dep(0)) != own_z:
            return None
        return of_xhat(estimate, call_args[1])

    outputs = step.call(args, True)
    replaced = _replace_outputs(outputs, reuse)
    if replaced is outputs:
        return None
    at = names.index("w") + 1
    new = ca.Function(step.name(), args[:at] + [estimate] + args[at:], replaced, names[:at] + ["xhat"] + names[at:],
                      step.name_out())
    return new, of_xhat


def _decoded(outputs: list[ca.MX], z: ca.MX) -> Optional[ca.MX]:
    """The one output of a call in ``outputs``'s graph that decodes ``z``: its first argument is ``z``
    itself and it reads no other; None if there is not exactly one."""
    found = []
    for node in _nodes(outputs):
        if node.is_output() and hash(node.dep(0).dep(0)) == hash(z):
            f, j = node.dep(0).which_function(), node.which_output()
            if all(f.sparsity_jac(i, j).nnz() == 0 for i in range(1, f.n_in())):
                found.append(node)
    return found[0] if len(found) == 1 else None


def skip_at_zero_input(step: ca.Function, injection: ca.Function) -> ca.Function:
    """``step`` with each call of ``injection(z, u)`` skipped (replaced by 0) where ``u`` is exactly 0.

    For a term that is exactly 0 at ``u = 0`` by construction (the model-based injection: the
    difference of two evaluations of the same plant function, through the encoder's JVP): the
    same values, without evaluating the decoder and the JVP.

    Parameters
    ----------
    step : casadi.Function
        An MX Function that calls ``injection``.
    injection : casadi.Function
        ``(z (nz, 1), u (nu, 1)) -> dz (nz, 1)``, exactly +0 where ``u`` is 0.

    Returns
    -------
    casadi.Function
        Same name, inputs and outputs as ``step``.
    """
    args = step.mx_in()
    outputs = step.call(args, True)
    z, u = ca.MX.sym("z", injection.sparsity_in(0)), ca.MX.sym("u", injection.sparsity_in(1))
    zero = ca.Function("no_injection", [z, u], [ca.DM.zeros(injection.sparsity_out(0))])
    either = ca.Function.if_else(f"{injection.name()}_unless_u0", zero, injection)

    def skip(output: ca.MX, call_args: list[ca.MX]) -> Optional[ca.MX]:
        if hash(output.dep(0).which_function()) != hash(injection):
            return None
        zz, uu = call_args
        return either(ca.mmin(uu == 0), zz, uu)

    replaced = _replace_outputs(outputs, skip)
    if replaced is outputs:
        return step
    return ca.Function(step.name(), args, replaced, step.name_in(), step.name_out())


# ---------------------------------------------------------------------- estimators
class CompiledEstimator(ABC):
    """An estimator that runs each trial through one CasADi Function, compiled, mapped over trials.

    Subclasses give :meth:`trajectory`: one trial of ``n`` samples,
    ``(y (ny, n), u (nu, n), s0 (ns, 1)) -> xhat (nx, n)``, ``u_k`` held over ``[t_k, t_k+1)``,
    started from the estimator's :meth:`initial_state` ``s0``. Calling the estimator compiles that
    Function (once per ``n``) and maps it over the trials on threads. It is an
    :data:`kklcasadi.evaluation.protocol.BatchEstimator`.

    An estimator whose :attr:`shares_inputs` is True also gives the trajectory of a group of ``K``
    trials with the same inputs (``y (ny, K n)``, column ``k K + j`` the sample ``k`` of trial ``j``,
    ``u (nu, n)``), which does the work that depends on the inputs alone once for the group; a call
    groups its trials by their inputs (bitwise equal rows of ``u``), at most :attr:`group` per group.

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
    group : int
        Largest group of trials with the same inputs run together (default :data:`GROUP`).
    profile : Profile, optional
        Where to record the time spent compiling (:class:`kklcasadi.evaluation.protocol.Profile`).
    """

    #: Whether trials with the same inputs share work (see :meth:`trajectory`).
    shares_inputs: bool = False

    def __init__(self, nx: int, nu: int, ny: int, dt: float, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None, group: int = GROUP, profile: Optional[Profile] = None) -> None:
        if compiler is not None and not isinstance(compiler, Compiler):
            raise TypeError(f"compiler: expected a kklcasadi.evaluation.compiled.Compiler or None, received "
                            f"{type(compiler).__name__}.")
        for name, value in (("n_threads", n_threads), ("group", group)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ValueError(f"{name}: expected a positive int{' or None' if name == 'n_threads' else ''}, "
                                 f"received {value!r}.")
        self.nx, self.nu, self.ny, self.dt = nx, nu, ny, float(dt)
        self.compiler = compiler
        self.n_threads = n_threads
        self.group = group
        self.profile = profile
        self._functions: dict[tuple[int, int], ca.Function] = {}

    @abstractmethod
    def trajectory(self, n: int, group: int = 1) -> ca.Function:
        """``group`` trials with the same inputs over ``n`` >= 2 samples (VM):
        ``(y (ny, group n), u (nu, n), s0 (ns, 1)) -> xhat (nx, group n)``, column ``k group + j``."""

    @abstractmethod
    def initial_state(self) -> np.ndarray:
        """The ``s0`` (ns,) every trial starts from."""

    def function(self, n: int, group: int = 1) -> ca.Function:
        """:meth:`trajectory` as it runs: compiled (cached per ``n`` and ``group``), or the VM Function."""
        if (n, group) not in self._functions:
            children = os.times()
            with phase(self.profile, "compile"):
                f = self.trajectory(n, group)
                self._functions[n, group] = f if self.compiler is None else self.compiler.compile(f)
            if self.profile is not None:
                self.profile.add("compile", 0.0, _children_cpu(children))
        return self._functions[n, group]

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
        xhat = np.empty((m, n, self.nx))
        threads = self.n_threads or os.cpu_count() or 1
        for indices in self._grouped(u):                      # (G, K): G groups of K trials, same inputs
            g, k = indices.shape
            mapped = self.function(n, k).map(g, "thread", min(threads, g))
            out = mapped(y[indices].transpose(3, 0, 2, 1).reshape(self.ny, g * n * k),
                         u[indices[:, 0]].transpose(2, 0, 1).reshape(self.nu, g * n), self.initial_state())
            xhat[indices] = np.asarray(out).reshape(self.nx, g, n, k).transpose(1, 3, 2, 0)
        return xhat

    def _grouped(self, u: np.ndarray) -> list[np.ndarray]:
        """The trials as index arrays (G, K) per group size K: groups of at most :attr:`group` trials
        whose inputs are bitwise equal (one array of (M, 1) without :attr:`shares_inputs`)."""
        m = u.shape[0]
        if not self.shares_inputs or self.group == 1 or m == 0:
            return [np.arange(m)[:, None]] if m else []
        bits = np.ascontiguousarray(u).reshape(m, -1).view(np.uint64)
        _, first, inverse = np.unique(bits, axis=0, return_index=True, return_inverse=True)
        by_size: dict[int, list[np.ndarray]] = {}
        for label in np.argsort(first):                        # in the order of the trials
            members = np.flatnonzero(inverse.ravel() == label)
            for start in range(0, members.size, self.group):
                chunk = members[start:start + self.group]
                by_size.setdefault(chunk.size, []).append(chunk)
        return [np.array(chunks) for _, chunks in sorted(by_size.items())]

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
    ``mapaccum``; bitwise :meth:`KKLObserver.simulate`. The step skips the model-based injection
    where the input is 0 (:func:`skip_at_zero_input`), and where the memory does work of its own
    (:func:`split_step`) that work is done once per group of trials with the same inputs and
    reused while the memory and the next input repeat those of the previous sample.

    Parameters
    ----------
    observer : KKLObserver
    compiler, n_threads, group, profile
        See :class:`CompiledEstimator`.
    shortcuts : bool
        False: the step as it is folded over the samples, trial by trial (1000 steps of the
        observer step per protocol trial: the per-step cost the shortcuts are measured against).
    """

    def __init__(self, observer: KKLObserver, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None, group: int = GROUP, profile: Optional[Profile] = None,
                 shortcuts: bool = True) -> None:
        from ..observer.kkl import KKLObserver

        if not isinstance(observer, KKLObserver):
            raise TypeError(f"observer: expected a kklcasadi.KKLObserver, received {type(observer).__name__}.")
        super().__init__(observer.nx, observer.nu, observer.ny, observer.dt, compiler=compiler,
                         n_threads=n_threads, group=group, profile=profile)
        self.observer = observer
        self.shortcuts = bool(shortcuts)
        step, self.carries = observer.step, False
        injection = observer.model_injection
        if shortcuts and injection is not None:
            reused = reuse_decoded(step, injection, observer.decode)
            if reused is not None:
                step, of_xhat = reused
                step, self.carries = skip_at_zero_input(step, of_xhat), True
            step = skip_at_zero_input(step, injection)
        self.step = step
        y0 = observer.memory_init.sparsity_jac(0, 0).nnz() > 0        # the first memory reads y_0
        self.split = None if y0 or not shortcuts else split_step(step)
        self.shares_inputs = self.split is not None

    def trajectory(self, n: int, group: int = 1) -> ca.Function:
        obs = self.observer
        if group != 1 and self.split is None:
            raise ValueError(f"group: expected 1 for an observer whose trials share no work, received {group!r}.")
        y, u, z0 = ca.MX.sym("y", obs.ny, group * n), ca.MX.sym("u", obs.nu, n), ca.MX.sym("z0", obs.nz)
        w0 = obs.memory_init(y[:, 0], u[:, 0])
        name = (f"{_c_name(obs.system.name)}_{_c_name(obs.method)}_n{n}" + (f"_g{group}" if group > 1 else "")
                + ("" if self.shortcuts else "_plain"))
        first = ca.repmat(obs.decode(z0, w0), 1, group)
        carried = [first] if self.carries else []                # the estimate a step reads (reuse_decoded)
        if self.split is None:
            states = list(range(2 + len(carried)))
            steps = self.step.mapaccum("trajectory", n - 1, states, states)
            xhat = steps(z0, w0, *carried, y[:, :n - 1], y[:, 1:], u[:, 1:])[2]
        else:
            states = list(range(4 + len(carried)))
            # two levels of unrolled steps (the default tens: three), each copying the states it stores
            steps = self._group_step(group).mapaccum("trajectory", n - 1, states, states, {"base": 32})
            rows, cols = obs.memory_shape
            key0 = ca.DM.nan(rows * cols + obs.nu)                  # no previous memory: compute at the first step
            s0 = ca.DM.zeros(self.split.shared.size1_out(0))
            xhat = steps(ca.repmat(z0, 1, group), w0, key0, s0, *carried, y[:, :group * (n - 1)], y[:, group:],
                         u[:, 1:])[4]
        return ca.Function(name, [y, u, z0], [ca.horzcat(first, xhat)], ["y", "u", "s0"], ["xhat"])

    def _group_step(self, group: int) -> ca.Function:
        """One sample of ``group`` trials with the same inputs, the shared part memoised.

        ``(Z (nz, group), w, key, s, [Xhat (nx, group)], Y (ny, group), Y_next (ny, group), u_next)
        -> (Z_next, w_next, key_next, s_next, Xhat_next)``; ``key = [vec(w); u_next]`` of the sample
        whose shared part ``s`` is (NaN before the first); ``Xhat``, the previous estimates, where
        the step reads them (:func:`reuse_decoded`).
        """
        obs, split = self.observer, self.split
        rows, cols = obs.memory_shape
        Z, w = ca.MX.sym("Z", obs.nz, group), ca.MX.sym("w", rows, cols)
        key, s = ca.MX.sym("key", rows * cols + obs.nu), ca.MX.sym("s", split.shared.size1_out(0))
        X = [ca.MX.sym("Xhat", obs.nx, group)] if self.carries else []
        Y, Y_next, u_next = ca.MX.sym("Y", obs.ny, group), ca.MX.sym("Y_next", obs.ny, group), ca.MX.sym("u", obs.nu)
        reuse = ca.Function("reuse", [s, w, u_next], [s])
        compute = ca.Function("compute", [s, w, u_next], [split.shared(w, u_next)])
        memo = ca.Function.if_else("shared_memo", reuse, compute)
        key_next = ca.vertcat(ca.vec(w), u_next)
        s_next = memo(ca.mmin(key_next == key), s, w, u_next)
        trials = [split.core(Z[:, j], w, *[x[:, j] for x in X], Y[:, j], Y_next[:, j], u_next, s_next)
                  for j in range(group)]
        return ca.Function("group_step", [Z, w, key, s, *X, Y, Y_next, u_next],
                           [ca.horzcat(*[z for z, _ in trials]), split.w_next(s_next, (rows, cols)), key_next, s_next,
                            ca.horzcat(*[x for _, x in trials])])

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
    compiler, n_threads, profile
        See :class:`CompiledEstimator`.
    """

    def __init__(self, ekf: EKF, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None, profile: Optional[Profile] = None) -> None:
        from ..estimators.ekf import EKF

        if not isinstance(ekf, EKF):
            raise TypeError(f"ekf: expected a kklcasadi.estimators.ekf.EKF, received {type(ekf).__name__}.")
        system = ekf.system
        super().__init__(system.nx, system.nu, system.ny, ekf.dt, compiler=compiler, n_threads=n_threads,
                         profile=profile)
        self.ekf = ekf

    def trajectory(self, n: int, group: int = 1) -> ca.Function:
        if group != 1:
            raise ValueError(f"group: expected 1 (the EKF's trials share no work), received {group!r}.")
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


class CompiledRecord(CompiledEstimator):
    """An observer's estimates with its latent and the covariance of its head, compiled and mapped over trials.

    Each trial's Function gives, per sample, the rows ``[xhat (nx); z (nz); vec(P) (nx^2)]`` (``P`` only where the
    observer has a covariance head, :attr:`~kklcasadi.observer.kkl.KKLObserver.step_covariance`); calling it returns
    those rows as ``(M, N, rows)``, and :meth:`record` splits them. The same Functions as
    :meth:`KKLObserver.simulate` (``z_0 = 0``, ``memory_init``, ``decode``, ``covariance`` at the first sample,
    then the step folded), so compiled with :class:`Compiler`'s flags it gives the same values bitwise.

    Parameters
    ----------
    observer : KKLObserver
    compiler, n_threads, profile
        See :class:`CompiledEstimator`.
    """

    def __init__(self, observer: KKLObserver, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None, profile: Optional[Profile] = None) -> None:
        from ..observer.kkl import KKLObserver

        if not isinstance(observer, KKLObserver):
            raise TypeError(f"observer: expected a kklcasadi.KKLObserver, received {type(observer).__name__}.")
        self.observer = observer
        self.covariance = observer.covariance is not None
        rows = observer.nx + observer.nz + (observer.nx ** 2 if self.covariance else 0)
        super().__init__(rows, observer.nu, observer.ny, observer.dt, compiler=compiler, n_threads=n_threads,
                         profile=profile)

    def trajectory(self, n: int, group: int = 1) -> ca.Function:
        if group != 1:
            raise ValueError(f"group: expected 1, received {group!r}.")
        obs = self.observer
        nx = obs.nx
        y, u, z0 = ca.MX.sym("y", obs.ny, n), ca.MX.sym("u", obs.nu, n), ca.MX.sym("z0", obs.nz)
        w0 = obs.memory_init(y[:, 0], u[:, 0])
        x0 = obs.decode(z0, w0)
        step = obs.step if not self.covariance else obs.step_covariance
        out = step.mapaccum("trajectory", n - 1, [0, 1], [0, 1])(z0, w0, y[:, :n - 1], y[:, 1:], u[:, 1:])
        rows = [ca.horzcat(x0, out[2]), ca.horzcat(z0, out[0])]
        if self.covariance:
            rows.append(ca.horzcat(ca.vec(obs.covariance(z0, w0, x0)), ca.reshape(out[3], nx * nx, n - 1)))
        name = f"{_c_name(obs.system.name)}_{_c_name(obs.method)}_record_n{n}"
        return ca.Function(name, [y, u, z0], [ca.vertcat(*rows)], ["y", "u", "s0"], ["record"])

    def initial_state(self) -> np.ndarray:
        """``z_0 = 0`` (nz,)."""
        return np.zeros(self.observer.nz)

    def record(self, t: Any, y: Any, u: Any) -> tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
        """``xhat (M, N, nx)``, ``z (M, N, nz)`` and ``cov (M, N, nx, nx)`` (None without a head) of M trials."""
        rows = self(t, y, u)
        nx, nz = self.observer.nx, self.observer.nz
        cov = None
        if self.covariance:                                   # vec is column-major: P[i, j] at row i + nx j
            cov = rows[..., nx + nz:].reshape(rows.shape[:2] + (nx, nx)).swapaxes(-1, -2)
        return rows[..., :nx], rows[..., nx:nx + nz], cov


def observer_estimator(observer: KKLObserver, *, compiler: Optional[Compiler] = Compiler(),
                       n_threads: Optional[int] = None, group: int = GROUP, profile: Optional[Profile] = None,
                       shortcuts: bool = True) -> CompiledObserver:
    """The fast estimator of an observer: its trajectory compiled, mapped over trials.

    Parameters
    ----------
    observer : KKLObserver
    compiler : Compiler or None
        None: the CasADi VM (the reference, ``observer.simulate``'s path).
    n_threads : int, optional
        Worker threads over trials (default: the CPU count).
    group : int
        Largest group of trials with the same inputs run together (:class:`CompiledEstimator`).
    profile : optional
        See :class:`CompiledEstimator`.
    shortcuts : bool
        False: the plain step folded (:class:`CompiledObserver`).

    Returns
    -------
    CompiledObserver
        ``est(t (N,), y (M, N, ny), u (M, N, nu)) -> xhat (M, N, nx)``.
    """
    return CompiledObserver(observer, compiler=compiler, n_threads=n_threads, group=group, profile=profile,
                            shortcuts=shortcuts)


def ekf_estimator(ekf: EKF, *, compiler: Optional[Compiler] = Compiler(), n_threads: Optional[int] = None,
                  profile: Optional[Profile] = None) -> CompiledEKF:
    """The fast estimator of an EKF (see :func:`observer_estimator`); the filter is unchanged."""
    return CompiledEKF(ekf, compiler=compiler, n_threads=n_threads, profile=profile)


def pf_estimator(system: Any, dt: float, *, compiler: Optional[Compiler] = Compiler(),
                 n_threads: Optional[int] = None, profile: Optional[Profile] = None, **options: Any) -> ParticleFilter:
    """A :class:`~kklcasadi.estimators.pf.ParticleFilter` whose per-sample Functions are compiled by ``compiler``.

    The libraries are cached with the observers' (:class:`Compiler`), instead of the filter's own
    just-in-time build into a temporary directory; the values are the same bitwise.

    Parameters
    ----------
    system : System
    dt : float
    compiler : Compiler or None
        None: the CasADi VM.
    n_threads : int, optional
        Worker threads over trials (default: the CPU count).
    profile : Profile, optional
        Gets the time spent building and compiling as the phase ``compile``.
    **options
        The filter's other options (``n_particles``, ``process_std``, ``measurement_std``,
        ``substeps``, ``seed``, ...).

    Returns
    -------
    ParticleFilter
        A protocol estimator: ``pf(t, y, u) -> xhat``.
    """
    from ..estimators.pf import ParticleFilter

    if compiler is not None and not isinstance(compiler, Compiler):
        raise TypeError(f"compiler: expected a kklcasadi.evaluation.compiled.Compiler or None, received "
                        f"{type(compiler).__name__}.")
    children = os.times()
    with phase(profile, "compile"):
        pf = ParticleFilter(system, dt, compile=_vm if compiler is None else compiler.compile, n_threads=n_threads,
                            **options)
    if profile is not None:
        profile.add("compile", 0.0, _children_cpu(children))
    return pf


def _vm(f: ca.Function) -> ca.Function:
    return f


def precompile(estimators: Sequence[CompiledEstimator], n: int, *, groups: Sequence[int] = (1,),
               jobs: Optional[int] = None, meanwhile: Optional[Callable[[], Any]] = None) -> Any:
    """Build and compile the trajectories of ``estimators`` for ``n`` samples, ``jobs`` compilers at a time.

    CasADi writes the sources in this thread; the C compilers then run on ``jobs`` threads (default:
    the CPU count) while this thread runs ``meanwhile()`` (e.g. simulating the trials); the
    libraries are loaded when both are done. Estimators without a compiler (VM) and trajectories
    already built are left as they are. Each estimator's ``profile`` gets a ``compile`` phase: the
    time this thread spent writing sources and waiting for the compilers, and the CPU time of both.

    Parameters
    ----------
    estimators : sequence of CompiledEstimator
    n : int
        Samples per trial.
    groups : sequence of int
        Sizes of the groups of trials with the same inputs that the calls will run (2 for the
        noise-free and noisy cells in one call); an estimator whose trials share no work compiles
        the size 1 only, the others each size up to their :attr:`CompiledEstimator.group`.
    jobs : int, optional
        Compilers at a time.
    meanwhile : callable, optional
        Run in this thread while the compilers run.

    Returns
    -------
    object
        What ``meanwhile()`` returned (None without it).
    """
    pending = []
    for est in estimators:
        sizes = sorted({min(int(g), est.group) for g in groups}) if est.shares_inputs else [1]
        for size in sizes:
            if (n, size) in est._functions or est.compiler is None:
                continue
            if not est.compiler.available():
                est.function(n, size)                              # the VM, with the compiler's warning
                continue
            wall, cpu = time.perf_counter(), time.process_time()
            build = est.compiler.build(est.trajectory(n, size))
            pending.append((est, size, build, time.perf_counter() - wall, time.process_time() - cpu))
    children = os.times()
    with ThreadPoolExecutor(max(1, jobs or os.cpu_count() or 1)) as pool:
        futures = [pool.submit(build.run) for _, _, build, _, _ in pending]
        result = meanwhile() if meanwhile is not None else None
        waited = time.perf_counter()
        for future in futures:
            future.result()
        waited = time.perf_counter() - waited
    compilers = _children_cpu(children)
    for est, size, build, wall, cpu in pending:
        est._functions[n, size] = build.load()
        share = 1 / len(pending)
        if est.profile is not None:
            est.profile.add("compile", wall + waited * share, cpu + compilers * share)
    return result


def _children_cpu(before: os.times_result) -> float:
    """CPU seconds of the child processes (the C compiler) waited for since ``before``."""
    after = os.times()
    return after.children_user + after.children_system - before.children_user - before.children_system


def _c_name(text: str) -> str:
    """``text`` with every character that is not a letter, digit or underscore replaced by ``_``."""
    return "".join(c if c.isalnum() or c == "_" else "_" for c in text)
