"""The observer's trajectories through its step compiled to C, a chunk of samples per call: what
:meth:`KKLObserver.simulate <kklcasadi.observer.kkl.KKLObserver.simulate>` runs where a C compiler is present.

:class:`CompiledTrajectory` folds the observer's ``step`` (``step_covariance`` where the model has a
covariance head) over at most :data:`CHUNK` samples per call of one Function, compiled once per machine
by :data:`BITWISE` (:class:`kklcasadi.compiler.Compiler`: gcc, cached on disk; the mat-vec kernels of
:func:`~kklcasadi.observer.codegen.kernels.axpy_matvec` and the C library's exp/tanh), mapped over the
trials on threads. Each call carries ``(z, w)`` from the end of one chunk to the start of the next; the
last chunk is padded by repeating its last sample and the padded steps are dropped (a step reads only
the samples up to its own). These are the operations of the CasADi VM's ``mapaccum`` on the same values,
so the results are the VM's bit for bit; a record of any length compiles one of a few sizes (:func:`chunk_size`).
"""

from __future__ import annotations

from typing import Any, Optional

import casadi as ca
import numpy as np

from ..compiler import Compiler, c_name
from ..model.variants.inflation import fold
from ..validation import positive_int
from .codegen.kernels import axpy_matvec

__all__ = ["CompiledTrajectory", "chunk_size", "CHUNK", "BITWISE"]

#: Most steps per compiled call (a shorter record runs the smallest power of two >= 64 that holds it).
CHUNK = 4096
#: The axpy mat-vec kernels and the C library's exp/tanh: bitwise the CasADi VM.
BITWISE = Compiler(postprocess=axpy_matvec)


def chunk_size(n: int, chunk: int = CHUNK) -> int:
    """Steps per call for a record of ``n`` samples: ``chunk``, or for a shorter record the smallest power
    of two >= 64 that holds its ``n - 1`` steps (few sizes to compile, little padding)."""
    return min(chunk, max(64, 1 << max(0, n - 2).bit_length()))


class CompiledTrajectory:
    """An observer's steps over trials of any length, compiled, a chunk of samples per call.

    Parameters
    ----------
    observer : KKLObserver
    compiler : Compiler
        How the chunk is compiled (default :data:`BITWISE`: the VM's values bit for bit).
    chunk : int
        Most steps per call (:data:`CHUNK`).
    """

    def __init__(self, observer: Any, *, compiler: Compiler = BITWISE, chunk: int = CHUNK) -> None:
        if not isinstance(compiler, Compiler):
            raise TypeError(f"compiler: expected a kklcasadi.compiler.Compiler, received {type(compiler).__name__}.")
        self.observer, self.compiler, self.chunk = observer, compiler, positive_int(chunk, "chunk")
        self.covariance = observer.step_covariance is not None
        self.inflation = self.covariance and observer.inflation is not None     # the step carries m
        monitor = observer.monitor
        self.spread = monitor is not None and monitor.spec.spread is not None       # the domain check's spread test
        self._functions: dict[int, ca.Function] = {}

    def function(self, size: int) -> ca.Function:
        """``(z (nz, 1), w, y (ny, size + 1), u (nu, size + 1)[, m (nm, 1)]) -> (z (nz, size), w (rows, cols size),
        xhat (nx, size)[, P (nx, nx size)][, m (nm, size)][, spread (1, size)])``: the steps ``k -> k + 1`` for
        ``k < size`` (with the covariance head and its inflation's state ``m``, and the decoder ensemble's spread
        where the domain monitor tests it), compiled (cached on disk and here)."""
        if size not in self._functions:
            obs = self.observer
            step = self._step()
            z, w = ca.MX.sym("z", obs.nz), ca.MX.sym("w", *obs.memory_shape)
            y, u = ca.MX.sym("y", obs.ny, size + 1), ca.MX.sym("u", obs.nu, size + 1)
            carried = [ca.MX.sym("m", obs.inflation_start.size)] if self.inflation else []
            out = fold(step, "chunk", size)(z, w, y[:, :size], y[:, 1:], u[:, 1:], *carried)
            outputs = list(out)
            names = ["z", "w", "xhat"] + (["P"] if self.covariance else []) + (["m"] if self.inflation else [])
            if self.spread and obs.decoded is None:
                outputs.append(obs.spread.map(size)(out[0], out[1]))
            if self.spread:
                names.append("spread")
            name = f"{c_name(obs.system.name)}_{c_name(obs.method)}_simulate{size}"
            f = ca.Function(name, [z, w, y, u, *carried], outputs, ["z0", "w0", "y", "u"] + (["m0"] if carried else []),
                            names)
            self._functions[size] = self.compiler.compile(f)
        return self._functions[size]

    def _step(self) -> ca.Function:
        """The step (with the covariance head), and where the domain monitor tests the ensemble's spread, the
        spread as its last output, the estimate and the spread from one evaluation of the members
        (:attr:`~kklcasadi.observer.kkl.KKLObserver.decoded`: the same values, the members run once)."""
        obs = self.observer
        step = obs.step_covariance if self.covariance else obs.step
        if not self.spread or obs.decoded is None:
            return step
        if self.covariance and obs.step_covariance_spread is not None:     # the inflation's spread test has it
            return obs.step_covariance_spread
        args = [ca.MX.sym(name, step.sparsity_in(i)) for i, name in enumerate(step.name_in())]
        z_next, w_next, own, *covariance = step.call(args, True)
        xhat, spread = obs.decoded(z_next, w_next)
        covariance = ca.graph_substitute(covariance, [own], [xhat]) if covariance else []   # of the same estimate
        return ca.Function("step_spread", args, [z_next, w_next, xhat, *covariance, spread], step.name_in(),
                           step.name_out() + ["spread"])

    def run(self, z0: np.ndarray, w0: np.ndarray, y: np.ndarray, u: np.ndarray, *, n_threads: int = 1
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Optional[np.ndarray], Optional[np.ndarray]]:
        """The states and estimates after each step of ``M`` trials.

        Parameters
        ----------
        z0 : numpy.ndarray, shape (nz, M)
        w0 : numpy.ndarray, shape (rows, M cols)
            The trials' first memories side by side (``memory_init`` mapped over the trials).
        y, u : numpy.ndarray, shapes (M, N, ny) and (M, N, nu)
            Finite samples, ``N >= 2``.
        n_threads : int
            Threads over the trials.

        Returns
        -------
        z : (M, N - 1, nz)
        w : (M, N - 1, rows, cols)
        xhat : (M, N - 1, nx)
        P : (M, N - 1, nx, nx) or None
            The covariance of each estimate (a model with a covariance head).
        spread : (M, N - 1) or None
            The decoder ensemble's spread at each step (where the domain monitor tests it).
        """
        obs = self.observer
        m, n = y.shape[:2]
        rows, cols = obs.memory_shape
        size = chunk_size(n, self.chunk)
        f = self.function(size)
        if m > 1:
            f = f.map(m, "thread", max(1, min(n_threads, m)))
        z = np.empty((m, n - 1, obs.nz))
        w = np.empty((m, n - 1, rows, cols))
        xhat = np.empty((m, n - 1, obs.nx))
        P = np.empty((m, n - 1, obs.nx, obs.nx)) if self.covariance else None
        spread = np.empty((m, n - 1)) if self.spread else None
        z_k, w_k = z0, w0
        carried = [np.tile(obs.inflation_start[:, None], (1, m))] if self.inflation else []   # the inflation's start
        for k in range(0, n - 1, size):
            steps = min(size, n - 1 - k)                               # steps k -> k + 1 .. k + steps
            parts = []
            for values in (y, u):
                part = values[:, k:k + steps + 1]
                if steps < size:                                       # pad: repeat the last sample
                    part = np.concatenate([part, np.repeat(part[:, -1:], size - steps, axis=1)], axis=1)
                parts.append(part.transpose(2, 0, 1).reshape(values.shape[2], m * (size + 1)))
            out = [np.asarray(a) for a in f.call([z_k, w_k, *parts, *carried])]
            z[:, k:k + steps] = out[0].reshape(obs.nz, m, size).transpose(1, 2, 0)[:, :steps]
            w[:, k:k + steps] = out[1].reshape(rows, m, size, cols).transpose(1, 2, 0, 3)[:, :steps]
            xhat[:, k:k + steps] = out[2].reshape(obs.nx, m, size).transpose(1, 2, 0)[:, :steps]
            if P is not None:
                P[:, k:k + steps] = out[3].reshape(obs.nx, m, size, obs.nx).transpose(1, 2, 0, 3)[:, :steps]
            if spread is not None:
                spread[:, k:k + steps] = out[-1].reshape(m, size)[:, :steps]
            if carried:
                carried = [out[4].reshape(-1, m, size)[:, :, steps - 1]]
            z_k = z[:, k + steps - 1].T
            w_k = w[:, k + steps - 1].transpose(1, 0, 2).reshape(rows, m * cols)
        return z, w, xhat, P, spread
