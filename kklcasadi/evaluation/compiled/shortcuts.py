"""The shortcuts of a compiled observer trajectory: the work a step's inputs alone decide, done once.

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

from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import casadi as ca
import numpy as np

__all__ = ["SplitStep", "split_step", "skip_at_zero_input", "reuse_decoded"]


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
