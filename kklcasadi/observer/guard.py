"""The sample guard: one absurd sample does not poison the rest of a run.

An observer's latent filters every sample it is fed: one value of ``1e308`` (a corrupt field, a
unit slip, a sensor's error code) makes it infinite, and a NaN never leaves it. A guarded run
(:func:`guarded_simulate` in Python, the generated C ``main`` alike) screens every sample and
every step with the same rule:

1. **Held sample.** A sample ``(y_k, u_k)`` with a value that is not finite, or outside its
   **guard box**, is not fed to the latent: the last sample fed is used again in its place
   (before the first one, the middle of the guard box, ``u = 0`` where unbounded), and the row
   is flagged :data:`HELD`. The guard box of the outputs is their range over the states the
   model was trained on (:func:`kklcasadi.plant.envelope.output_ranges` over :func:`training_box`) widened by
   :data:`GUARD_WIDTHS` times its width on each side; the inputs' is the plant's ``u_box`` widened
   alike (unbounded for a plant that declares none), unbounded too where a range is zero.
2. **Restart.** A step whose latent ``z_k`` or estimate ``xhat_k`` is not finite, or whose
   latent lies outside the card's latent box widened in the same way (where the card records a
   domain), restarts the observer at that sample as at the start of a run (``z_k = 0``, ``w_k =
   init(y_k, u_k)``, ``xhat_k = decode(z_k, w_k)``), and the row is flagged :data:`RESTARTED`.

A run without flags is exactly :meth:`KKLObserver.simulate`'s (the same steps in the same
order, bitwise). The guard is far wider than the domain monitor (``in_domain``): it catches
absurd samples, the monitor flags estimates outside the trained domain.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..plant.envelope import output_ranges
from ..validation import Text, error, nonnegative_number
from .kkl import Estimate, KKLObserver, _check_time

__all__ = ["SampleGuard", "guarded_simulate", "training_box", "GUARD_WIDTHS", "HELD", "RESTARTED"]

#: How many widths of the trained range beyond each of its ends a sample or latent may lie.
GUARD_WIDTHS = 10.0
#: Status bit of a row whose sample was not fed to the latent (the last one fed was used again).
HELD = 1
#: Status bit of a row where the observer restarted (its step left the latent's guard box).
RESTARTED = 2
#: Steps per ``mapaccum`` call of a guarded run (a restart reruns at most one chunk).
_CHUNK = 4096


def training_box(observer: KKLObserver) -> np.ndarray:
    """The states the model was trained on, (nx, 2): the card's recorded domain, else the plant's X0 box."""
    domain = observer.domain
    if domain is None:
        return observer.system.x0_box
    return np.column_stack([domain.x_lo, domain.x_hi])


def _widened(lo: np.ndarray, hi: np.ndarray, widths: float) -> tuple[np.ndarray, np.ndarray]:
    """``[lo, hi]`` widened by ``widths`` times its width on each side; unbounded where the width is 0."""
    width = hi - lo
    bounded = width > 0
    return (np.where(bounded, lo - widths * width, -np.inf), np.where(bounded, hi + widths * width, np.inf))


@dataclass(frozen=True, eq=False)
class SampleGuard:
    """The guard boxes of a run (see the module): ``-inf``/``inf`` where unbounded.

    Attributes
    ----------
    y_lo, y_hi : numpy.ndarray, shape (ny,)
    u_lo, u_hi : numpy.ndarray, shape (nu,)
    z_lo, z_hi : numpy.ndarray, shape (nz,)
    y_fill, u_fill : numpy.ndarray
        The sample used in place of held ones before the first sample fed: the middle of the box
        (0 where unbounded).
    """

    y_lo: np.ndarray
    y_hi: np.ndarray
    u_lo: np.ndarray
    u_hi: np.ndarray
    z_lo: np.ndarray
    z_hi: np.ndarray

    @classmethod
    def of(cls, observer: KKLObserver, *, widths: float = GUARD_WIDTHS) -> SampleGuard:
        """The guard of ``observer``'s model: its trained output range and latent box widened by ``widths``."""
        if not isinstance(observer, KKLObserver):
            raise error("observer", "a KKLObserver", Text(type(observer).__name__), kind=TypeError)
        widths = nonnegative_number(widths, "widths")
        ranges = output_ranges(observer.system, training_box(observer))
        y_lo, y_hi = _widened(ranges[:, 0], ranges[:, 1], widths)
        u_box = observer.system.u_box
        if u_box is None:
            u_lo, u_hi = np.full(observer.nu, -np.inf), np.full(observer.nu, np.inf)
        else:
            u_lo, u_hi = _widened(u_box[:, 0], u_box[:, 1], widths)
        if observer.domain is None:
            z_lo, z_hi = np.full(observer.nz, -np.inf), np.full(observer.nz, np.inf)
        else:
            z_lo, z_hi = _widened(np.asarray(observer.domain.z_lo, float), np.asarray(observer.domain.z_hi, float),
                                  widths)
        return cls(y_lo, y_hi, u_lo, u_hi, z_lo, z_hi)

    @staticmethod
    def _middle(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        bounded = np.isfinite(lo) & np.isfinite(hi)
        middle = np.zeros(lo.shape)
        middle[bounded] = 0.5 * (lo[bounded] + hi[bounded])
        return middle

    @property
    def y_fill(self) -> np.ndarray:
        return self._middle(self.y_lo, self.y_hi)

    @property
    def u_fill(self) -> np.ndarray:
        return self._middle(self.u_lo, self.u_hi)

    def accepts(self, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Whether each sample may be fed: finite and inside the boxes, (N,) for ``y`` (N, ny), ``u`` (N, nu)."""
        with np.errstate(invalid="ignore"):
            return (np.all((y >= self.y_lo) & (y <= self.y_hi) & np.isfinite(y), axis=1)
                    & np.all((u >= self.u_lo) & (u <= self.u_hi) & np.isfinite(u), axis=1))

    def keeps(self, z: np.ndarray, xhat: np.ndarray) -> np.ndarray:
        """Whether each step's result may stand: finite, the latent inside its box, (N,)."""
        with np.errstate(invalid="ignore"):
            return (np.all((z >= self.z_lo) & (z <= self.z_hi), axis=1) & np.all(np.isfinite(z), axis=1)
                    & np.all(np.isfinite(xhat), axis=1))


def _samples(values: Any, argument: str, n: int, dim: int) -> np.ndarray:
    """``values`` as float64 (n, dim); NaN and inf allowed (the guard screens them)."""
    array = np.asarray(values, dtype=np.float64)
    if array.ndim == 1 and dim == 1:
        array = array[:, None]
    if array.shape != (n, dim):
        raise error(argument, f"shape (N, {dim}) with N = {n} (the length of t)", Text(f"shape {np.shape(values)}"))
    return array


def guarded_simulate(observer: KKLObserver, t: Any, y: Any, u: Any, *,
                     guard: SampleGuard | None = None) -> tuple[Estimate, np.ndarray]:
    """Run ``observer`` over one trajectory with the sample guard (see the module).

    Parameters
    ----------
    observer : KKLObserver
    t : array_like, shape (N,)
        Sample times spaced by ``observer.dt``.
    y : array_like, shape (N, ny)
        Measurements; non-finite or absurd samples are held, not fed.
    u : array_like, shape (N, nu)
        Inputs, held over ``[t_k, t_k+1)``; the same.
    guard : SampleGuard, optional
        Default :meth:`SampleGuard.of` ``(observer)``.

    Returns
    -------
    Estimate
        As :meth:`KKLObserver.simulate` (one trajectory).
    numpy.ndarray of int8, shape (N,)
        Per sample: 0, or the sum of :data:`HELD` and :data:`RESTARTED` for what the guard did.
    """
    if not isinstance(observer, KKLObserver):
        raise error("observer", "a KKLObserver", Text(type(observer).__name__), kind=TypeError)
    guard = SampleGuard.of(observer) if guard is None else guard
    if not isinstance(guard, SampleGuard):
        raise error("guard", "a SampleGuard or None", Text(type(guard).__name__), kind=TypeError)
    t = _check_time(t, observer.dt)
    n = t.size
    y, u = _samples(y, "y", n, observer.ny), _samples(u, "u", n, observer.nu)

    status = np.where(guard.accepts(y, u), 0, HELD).astype(np.int8)
    fed = np.maximum.accumulate(np.where(status == 0, np.arange(n), -1))     # the last sample fed, -1 before any
    y_fed = np.where(fed[:, None] >= 0, y[np.maximum(fed, 0)], guard.y_fill)
    u_fed = np.where(fed[:, None] >= 0, u[np.maximum(fed, 0)], guard.u_fill)

    rows, cols = observer.memory_shape
    z, xhat, w = np.empty((n, observer.nz)), np.empty((n, observer.nx)), np.empty((n, rows, cols))

    def start(k: int) -> None:                            # z_k = 0, w_k = init(y_k, u_k), xhat_k = decode(z_k, w_k)
        z[k] = 0.0
        w[k] = np.asarray(observer.memory_init(y_fed[k], u_fed[k]))
        xhat[k] = np.asarray(observer.decode(z[k], w[k])).ravel()

    start(0)
    runs: dict[int, Any] = {}
    k = 0
    while k < n - 1:
        m = min(_CHUNK, n - 1 - k)
        if m not in runs:
            runs[m] = observer.step.mapaccum("guarded", m, [0, 1], [0, 1])
        z_out, w_out, x_out = runs[m](z[k], w[k], y_fed[k:k + m].T, y_fed[k + 1:k + m + 1].T, u_fed[k + 1:k + m + 1].T)
        z_out, x_out = np.asarray(z_out).T, np.asarray(x_out).T
        kept = guard.keeps(z_out, x_out)
        good = m if kept.all() else int(np.argmin(kept))
        z[k + 1:k + 1 + good], xhat[k + 1:k + 1 + good] = z_out[:good], x_out[:good]
        w[k + 1:k + 1 + good] = np.asarray(w_out).reshape(rows, m, cols).transpose(1, 0, 2)[:good]
        k += good
        if good < m:                                      # the step into sample k + 1 left the guard: restart there
            k += 1
            status[k] |= RESTARTED
            start(k)
    flags = observer.in_domain(xhat, z, w if observer.monitor is not None else None)
    for array in (xhat, z, status) if flags is None else (xhat, z, status, flags):
        array.setflags(write=False)
    return Estimate(t, xhat, z, flags), status
