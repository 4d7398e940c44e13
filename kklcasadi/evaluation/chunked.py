"""Long records through a compiled step, one chunk at a time: working memory independent of their length.

:class:`ChunkedObserver` and :class:`ChunkedEKF` run one trajectory of any length ``N`` through a
Function of a fixed number of steps (:data:`CHUNK`; fewer for a short record), compiled once per
machine by the :class:`~kklcasadi.evaluation.compiled.Compiler` (gcc, cached on disk; the CasADi VM
with the compiler's one-line :class:`~kklcasadi.evaluation.compiled.CompilerWarning` where there is no
C compiler). Each call carries the estimator's state (the observer's ``z``, memory ``w`` and, where
its step reads it, the previous estimate; the EKF's ``[x; vec(P)]``) from the end of one chunk to the
start of the next; the last chunk is padded by repeating its last sample, and the padded steps'
outputs are dropped (a step reads only the samples up to its own). The work arrays of one call are
those of one chunk, where the CasADi VM's ``mapaccum`` over a whole record held every intermediate
value of every step; what grows with ``N`` is the result (the estimates, the latent states, the
flags).

With :data:`BITWISE` the estimates are bitwise :meth:`KKLObserver.simulate`'s and
:meth:`EKF.simulate`'s (the same operations on the same values: the observer's step with the
evaluation path's shortcuts, which are bitwise the plain step, and the C library's exp/tanh); with
`FAST` (the default) the vectorised exp/tanh and fused multiply-adds keep each step within 1e-12 of the VM's, as
``kklcasadi evaluate``'s default. The domain monitor's flags are the observer's ``domain_check``,
compiled with the step.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, Optional

import casadi as ca
import numpy as np
from tqdm.auto import tqdm

from ..observer.codegen import fast_kernels
from ..observer.compiled import BITWISE, CHUNK, chunk_size
from ..validation import positive_int
from .compiled import CompiledObserver, Compiler

if TYPE_CHECKING:
    from ..estimators.ekf import EKF
    from ..observer.kkl import KKLObserver

__all__ = ["ChunkedObserver", "ChunkedEKF", "CHUNK", "FAST", "BITWISE"]

#: The default compiler of the chunks: the axpy mat-vec kernels (fused multiply-adds where the CPU has FMA) and the
#: vectorised exp/tanh (within FUSED_TOLERANCE, 1e-12 relative, of the VM per step, as ``kklcasadi evaluate``'s
#: default).
FAST = Compiler(postprocess=fast_kernels)


class _Chunked(ABC):
    """A trajectory of any length, ``chunk`` steps per call of one compiled Function.

    Subclasses give :meth:`_function` (``chunk`` steps from a state), :meth:`_start` (the first sample
    and the state after it) and :meth:`_carry` (the state after a chunk, from its outputs).
    """

    def __init__(self, nu: int, ny: int, dt: float, *, compiler: Optional[Compiler], chunk: int) -> None:
        if compiler is not None and not isinstance(compiler, Compiler):
            raise TypeError(f"compiler: expected a kklcasadi.evaluation.compiled.Compiler or None, received "
                            f"{type(compiler).__name__}.")
        self.nu, self.ny, self.dt = nu, ny, float(dt)
        self.compiler = compiler
        self.chunk = positive_int(chunk, "chunk")
        self._compiled: dict[int, ca.Function] = {}

    @abstractmethod
    def _function(self, n: int) -> ca.Function:
        """``(state..., y (ny, n + 1), u (nu, n + 1)) -> per-step outputs (., n)``: the steps ``k -> k + 1``
        for ``k < n`` from the samples ``0 .. n`` (the observer's step reads ``y_k``, ``y_k+1`` and
        ``u_k+1``, the EKF's ``u_k`` and ``y_k+1``)."""

    @abstractmethod
    def _start(self, y0: np.ndarray, u0: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The state after the first sample and the first sample's outputs (columns of 1)."""

    @abstractmethod
    def _carry(self, outputs: list[np.ndarray], steps: int) -> list[np.ndarray]:
        """The state after the first ``steps`` steps of a chunk, from its outputs."""

    def size(self, n: int) -> int:
        """Steps per call for a record of ``n`` samples (:func:`~kklcasadi.observer.compiled.chunk_size`)."""
        return chunk_size(n, self.chunk)

    def function(self, size: int) -> ca.Function:
        """The Function of ``size`` steps as it runs: compiled (cached on disk and here), or the VM's
        without a compiler (:class:`~kklcasadi.evaluation.compiled.Compiler`'s warning)."""
        if size not in self._compiled:
            f = self._function(size)
            self._compiled[size] = f if self.compiler is None else self.compiler.compile(f)
        return self._compiled[size]

    def run(self, y: Any, u: Any, *, progress: bool = False) -> list[np.ndarray]:
        """The per-sample outputs of one trajectory, ``(N, .)`` each.

        Parameters
        ----------
        y : array_like, shape (N, ny)
            Measurements, finite, on the estimator's grid.
        u : array_like, shape (N, nu)
            Inputs, held over ``[t_k, t_k+1)``.
        progress : bool
            A progress bar over the samples (tqdm).
        """
        y, u = self._samples(y, u)
        n = y.shape[0]
        state, first = self.start(y[0], u[0])
        outputs = [np.empty((n, o.shape[1])) for o in first]
        for out, value in zip(outputs, first):
            out[0] = value[0]
        with tqdm(total=n, unit="sample", disable=not progress, unit_scale=True) as bar:
            bar.update(1)
            for k in range(0, n - 1, self.size(n)):
                state, rest = self.advance(state, y[k:], u[k:], n, steps=min(self.size(n), n - 1 - k))
                for out, value in zip(outputs, rest):
                    out[k + 1:k + 1 + value.shape[0]] = value
                bar.update(rest[0].shape[0])
        return outputs

    def _samples(self, y: Any, u: Any) -> tuple[np.ndarray, np.ndarray]:
        y, u = np.asarray(y, dtype=float), np.asarray(u, dtype=float)
        if y.ndim != 2 or y.shape[1] != self.ny or y.shape[0] < 1:
            raise ValueError(f"y: expected shape (N, {self.ny}) with N >= 1, received {y.shape}.")
        if u.shape != (y.shape[0], self.nu):
            raise ValueError(f"u: expected shape ({y.shape[0]}, {self.nu}), received {u.shape}.")
        return y, u

    def start(self, y0: np.ndarray, u0: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The state after the first sample, and that sample's outputs, ``(1, .)`` each."""
        state, first = self._start(np.asarray(y0, dtype=float), np.asarray(u0, dtype=float))
        return state, [np.asarray(value)[:, 0][None, :] for value in first]

    def advance(self, state: list[np.ndarray], y: np.ndarray, u: np.ndarray, n: int, *,
                steps: Optional[int] = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The steps from ``y[0], u[0]`` (the last sample already run) over the samples after it, a chunk per
        call (the calls' size that of a record of ``n`` samples, :meth:`size`): the state after the last
        step, and the outputs of the samples after the first, ``(len(y) - 1, .)`` each (``steps`` of them,
        default all). A record run in pieces that overlap by one sample gives :meth:`run`'s values."""
        total = y.shape[0] - 1 if steps is None else steps
        c = self.size(n)
        f = self.function(c)
        pieces: list[list[np.ndarray]] = []
        for k in range(0, total, c):
            m = min(c, total - k)                                      # steps k -> k + 1 .. k + m
            y_part, u_part = y[k:k + m + 1], u[k:k + m + 1]
            if m < c:                                                  # pad: repeat the last sample
                y_part = np.concatenate([y_part, np.repeat(y_part[-1:], c - m, axis=0)])
                u_part = np.concatenate([u_part, np.repeat(u_part[-1:], c - m, axis=0)])
            result = [np.asarray(r) for r in f.call([*state, y_part.T, u_part.T])]
            pieces.append([value[:, :m].T for value in self._per_step(result)])
            state = self._carry(result, m)
        if not pieces:
            return state, []
        return state, [np.concatenate(parts) if len(parts) > 1 else parts[0] for parts in zip(*pieces)]

    def _per_step(self, result: list[np.ndarray]) -> list[np.ndarray]:
        """The chunk's outputs as ``(., chunk)`` columns, one per step (the default: as they come)."""
        return result


class ChunkedObserver(_Chunked):
    """A :class:`~kklcasadi.observer.kkl.KKLObserver` over a long record, a chunk at a time.

    Parameters
    ----------
    observer : KKLObserver
    compiler : Compiler or None
        How the chunk is compiled: :data:`FAST` (default, within 1e-12 per step of the VM) or
        :data:`BITWISE`; None: the CasADi VM.
    chunk : int
        Steps per call (:data:`CHUNK`).

    Notes
    -----
    The step is :class:`~kklcasadi.evaluation.compiled.CompiledObserver`'s (the model-based injection
    skipped where the input is exactly 0, the previous estimate reused where the injection decodes it
    again): bitwise the plain step.
    """

    def __init__(self, observer: KKLObserver, *, compiler: Optional[Compiler] = FAST, chunk: int = CHUNK) -> None:
        shortcuts = CompiledObserver(observer, compiler=None)
        super().__init__(observer.nu, observer.ny, observer.dt, compiler=compiler, chunk=chunk)
        self.observer = observer
        self.step, self.carries = shortcuts.step, shortcuts.carries

    def _function(self, n: int) -> ca.Function:
        obs = self.observer
        rows, cols = obs.memory_shape
        z, w = ca.MX.sym("z", obs.nz), ca.MX.sym("w", rows, cols)
        carried = [ca.MX.sym("xhat", obs.nx)] if self.carries else []
        y, u = ca.MX.sym("y", obs.ny, n + 1), ca.MX.sym("u", obs.nu, n + 1)
        states = list(range(2 + len(carried)))
        monitored = self._monitored_step()
        steps = (self.step if monitored is None else monitored).mapaccum("chunk", n, states, states)
        results = steps(z, w, *carried, y[:, :n], y[:, 1:], u[:, 1:])
        z_all, w_all, xhat = results[:3]
        outputs, names = [xhat, z_all, w_all], ["xhat", "z", "w"]
        if obs.domain_check is not None:
            outputs.append(obs.domain_check.map(n)(z_all, w_all, xhat) if monitored is None else results[3])
            names.append("in_domain")
        name = f"{_c_name(obs.system.name)}_{_c_name(obs.method)}_chunk{n}"
        return ca.Function(name, [z, w, *carried, y, u], outputs,
                           ["z0", "w0", *(["xhat0"] if carried else []), "y", "u"], names)

    def _monitored_step(self) -> Optional[ca.Function]:
        """The step with its domain flag, the estimate and the ensemble's spread from one evaluation of the
        members (:attr:`KKLObserver.decoded`: the same values as the step's estimate and the domain check's spread,
        the members run once where the step and the check would each run them); None where the check tests no
        spread (or the step reads its previous estimate)."""
        obs = self.observer
        if obs.decoded is None or obs.domain_check_of_spread is None or self.carries:
            return None
        args = [ca.MX.sym(name, self.step.sparsity_in(i)) for i, name in enumerate(self.step.name_in())]
        z_next, w_next = self.step.call(args, True)[:2]          # its own estimate is left out of the graph
        xhat, spread = obs.decoded(z_next, w_next)
        flag = obs.domain_check_of_spread(z_next, w_next, xhat, spread)
        return ca.Function("step_monitored", args, [z_next, w_next, xhat, flag], self.step.name_in(),
                           self.step.name_out() + ["in_domain"])

    def _start(self, y0: np.ndarray, u0: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        obs = self.observer
        z0 = np.zeros(obs.nz)
        w0 = np.asarray(obs.memory_init(y0, u0))
        xhat0 = np.asarray(obs.decode(z0, w0))
        state = [z0, w0] + ([xhat0] if self.carries else [])
        first = [xhat0, z0[:, None]]
        if obs.domain_check is not None:
            first.append(np.asarray(obs.domain_check(z0, w0, xhat0)))
        return state, first

    def run(self, y: Any, u: Any, *, progress: bool = False) -> list[np.ndarray]:
        """``[xhat (N, nx), z (N, nz)]``, and the domain monitor's flags ``(N, 1)`` (1.0 or 0.0) where the
        model records a domain or a decoder-input monitor; see :meth:`_Chunked.run`."""
        return super().run(y, u, progress=progress)

    def _per_step(self, result: list[np.ndarray]) -> list[np.ndarray]:
        return [result[0], result[1]] + result[3:]

    def _carry(self, outputs: list[np.ndarray], steps: int) -> list[np.ndarray]:
        xhat, z, w_all = outputs[:3]
        cols = self.observer.memory_shape[1]
        return [z[:, steps - 1], w_all[:, (steps - 1) * cols:steps * cols]] + ([xhat[:, steps - 1]] if self.carries
                                                                               else [])

    def estimate(self, y: Any, u: Any, *, progress: bool = False) -> tuple[np.ndarray, np.ndarray,
                                                                          Optional[np.ndarray]]:
        """``xhat (N, nx)``, ``z (N, nz)`` and the domain monitor's flags ``(N,)`` of one record, as
        :meth:`KKLObserver.simulate` gives them (None where the model records no domain).

        The flags are the observer's ``domain_check`` per sample, compiled with the step (the decoder
        ensemble's spread and the decoder-input monitor cost as much as the step itself in the VM).
        """
        outputs = self.run(y, u, progress=progress)
        flags = outputs[2][:, 0] > 0.5 if len(outputs) > 2 else None
        return outputs[0], outputs[1], flags


class ChunkedEKF(_Chunked):
    """An :class:`~kklcasadi.estimators.ekf.EKF` over a long record, a chunk at a time; :meth:`EKF.simulate`'s
    ``xhat`` (bitwise with :data:`BITWISE`: the filter calls no exp or tanh of its own, so :data:`FAST`
    differs only where the plant's model does).

    Parameters
    ----------
    ekf : EKF
    compiler, chunk
        See :class:`ChunkedObserver`.
    """

    def __init__(self, ekf: EKF, *, compiler: Optional[Compiler] = FAST, chunk: int = CHUNK) -> None:
        system = ekf.system
        super().__init__(system.nu, system.ny, ekf.dt, compiler=compiler, chunk=chunk)
        self.ekf, self.nx = ekf, system.nx

    def _function(self, n: int) -> ca.Function:
        nx = self.nx
        s, y, u = ca.MX.sym("s", nx + nx * nx), ca.MX.sym("y", self.ny, n + 1), ca.MX.sym("u", self.nu, n + 1)
        states = self.ekf.step.mapaccum("ekf_chunk", n)(s, ca.vertcat(u[:, :n], y[:, 1:]))     # u_k held
        return ca.Function(f"{_c_name(self.ekf.system.name)}_ekf_chunk{n}", [s, y, u], [states], ["s0", "y", "u"],
                           ["s"])

    def _start(self, y0: np.ndarray, u0: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        x0, P0 = (np.asarray(a) for a in self.ekf.update(self.ekf.x0, self.ekf.P0, y0))
        return [np.concatenate([x0[:, 0], P0.ravel(order="F")])], [x0]

    def run(self, y: Any, u: Any, *, progress: bool = False) -> list[np.ndarray]:
        """``[xhat (N, nx)]``, the filtered estimates after each ``y_k``; see :meth:`_Chunked.run`."""
        return super().run(y, u, progress=progress)

    def _per_step(self, result: list[np.ndarray]) -> list[np.ndarray]:
        return [result[0][:self.nx]]

    def _carry(self, outputs: list[np.ndarray], steps: int) -> list[np.ndarray]:
        return [outputs[0][:, steps - 1]]


def _c_name(text: str) -> str:
    """``text`` with every character that is not a letter, digit or underscore replaced by ``_``."""
    return "".join(c if c.isalnum() or c == "_" else "_" for c in text)
