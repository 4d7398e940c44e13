"""The KKL observer one sample at a time: a do-mpc-style step estimator (``make_step(y_k, u_k) -> xhat_k``) on
the observer's own Functions (``memory_init``, ``decode``, ``step``, the domain monitor and the covariance head),
what ``KKLObserver.estimator()`` returns and a control loop or a live system feeds.
"""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from ..estimate import check_sample

__all__ = ["Estimator", "HELD", "RESTARTED"]

#: Status bit of a guarded sample that was not fed to the latent (the last one fed was used again).
HELD = 1
#: Status bit of a guarded sample where the observer restarted (its step left the latent's guard box).
RESTARTED = 2


class Estimator:
    """Stateful form of a :class:`kklcasadi.KKLObserver`, for loops that receive one sample at a time (a
    :class:`kklcasadi.estimate.StepEstimator`).

    ``make_step(y_k, u_k)`` returns ``xhat_k``; the sequence equals :meth:`kklcasadi.KKLObserver.simulate`
    sample by sample. The first call initialises ``z_0 = 0`` and the window with ``u_0``.

    With a ``guard`` the steps follow :func:`kklcasadi.observer.guard.guarded_simulate`'s rule, sample
    by sample: a sample that is not finite or outside the guard's boxes is not fed (the last one fed
    is, :data:`HELD`), and a step whose latent or estimate is not finite or whose latent leaves its
    box restarts the observer at that sample (:data:`RESTARTED`); ``stats["status"]`` says which.
    Without one, a non-finite sample is refused (the state unchanged) and a finite absurd one is fed.

    Parameters
    ----------
    observer : kklcasadi.KKLObserver
    guard : SampleGuard, optional
        :class:`kklcasadi.observer.guard.SampleGuard` (or any object with its ``accepts``, ``keeps``,
        ``y_fill`` and ``u_fill``).

    Attributes
    ----------
    observer : kklcasadi.KKLObserver
    guard : SampleGuard or None
    k : int
        Samples taken since the start or the last :meth:`reset`.
    """

    def __init__(self, observer: Any, *, guard: Any = None) -> None:
        if not all(hasattr(observer, name) for name in ("memory_init", "decode", "step", "in_domain", "covariance")):
            raise TypeError(f"observer: expected a KKLObserver, received "
                            f"{type(observer).__name__}.")
        if guard is not None and not all(hasattr(guard, a) for a in ("accepts", "keeps", "y_fill", "u_fill")):
            raise TypeError(f"guard: expected a SampleGuard or None, received {type(guard).__name__}.")
        self.observer = observer
        self.guard = guard
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next :meth:`make_step` starts again from ``z = 0``."""
        self._z: Optional[np.ndarray] = None
        self._w: Optional[np.ndarray] = None
        self._y: Optional[np.ndarray] = None
        self.k = 0
        self._in_domain: Optional[bool] = None
        self._out_of_domain = 0
        self._cov: Optional[np.ndarray] = None
        self._m = self.observer.inflation_start        # the covariance inflation's state (where the card has one)
        self._fed: Optional[tuple[np.ndarray, np.ndarray]] = None
        self._status = 0
        self._held = 0
        self._restarts = 0

    @property
    def z(self) -> Optional[np.ndarray]:
        """Latent state ``z_k`` (nz,) after the last step, or None before the first."""
        return None if self._z is None else self._z.copy()

    @property
    def w(self) -> Optional[np.ndarray]:
        """Input memory ``w_k`` (``observer.memory_shape``; the window (window, nu) for windowed
        variants) after the last step, or None before the first."""
        return None if self._w is None else self._w.copy()

    @property
    def cov(self) -> Optional[np.ndarray]:
        """The covariance (nx, nx) of the last estimate's error (the model's covariance head), or None before the
        first step or without a head."""
        return None if self._cov is None else self._cov.copy()

    def make_step(self, y: Any, u: Any) -> np.ndarray:
        """Feed ``y_k`` and ``u_k`` (the input held from ``t_k``); return the estimate ``xhat_k``.

        Parameters
        ----------
        y : array_like, shape (ny,)
        u : array_like, shape (nu,)

        Returns
        -------
        numpy.ndarray, shape (nx,)
        """
        obs, guard = self.observer, self.guard
        y = check_sample(y, "y", obs.ny, self.k, finite=guard is None)
        u = check_sample(u, "u", obs.nu, self.k, finite=guard is None)
        status = 0
        if guard is not None:
            if guard.accepts(y[None], u[None])[0]:
                self._fed = (y, u)
            else:
                status = HELD
                y, u = self._fed if self._fed is not None else (guard.y_fill, guard.u_fill)
        started = self._z is None
        if started:
            z, w, xhat = self._start(y, u)
        else:
            z_next, w, xhat = obs.step(self._z, self._w, self._y, y, u)
            z, w, xhat = np.asarray(z_next).ravel(), np.asarray(w), np.asarray(xhat).ravel()
            if guard is not None and not guard.keeps(z[None], xhat[None])[0]:
                status |= RESTARTED
                started = True
                z, w, xhat = self._start(y, u)
        self._z, self._w, self._y = z, w, y
        self.k += 1
        self._status = status
        self._held += bool(status & HELD)
        self._restarts += bool(status & RESTARTED)
        inside = obs.in_domain(xhat, z, w)
        self._in_domain = None if inside is None else bool(inside)
        if obs.covariance is not None:
            self._cov = np.asarray(obs.covariance(z, w, xhat))
            if obs.inflation is not None:       # the residual's inflation: m = 1 at a run's start, as simulate
                if started:
                    self._m = obs.inflation_start
                else:
                    spread = [obs.spread(z, w)] if obs.inflation.n_in() == 6 else []   # its spread test's input
                    m_next, P = obs.inflation(self._m, y, xhat, self._cov, z, *spread)
                    self._m, self._cov = np.asarray(m_next)[:, 0], np.asarray(P)
        self._out_of_domain += inside is not None and not inside
        return xhat

    def _start(self, y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``z = 0``, ``w = init(y, u)``, ``xhat = decode(z, w)``: a run's first sample."""
        obs = self.observer
        z, w = np.zeros(obs.nz), np.asarray(obs.memory_init(y, u))
        return z, w, np.asarray(obs.decode(z, w)).ravel()

    @property
    def stats(self) -> dict:
        """What the last :meth:`make_step` did: ``k`` (samples taken), ``in_domain`` (whether the
        last estimate lies in the trained domain, None without a recorded domain),
        ``out_of_domain_steps`` (how many estimates so far did not), ``status`` (the guard's flags of
        the last sample: 0, or the sum of :data:`HELD` and :data:`RESTARTED`), ``held_steps`` and
        ``restarts`` (how many so far)."""
        return {"k": self.k, "in_domain": self._in_domain, "out_of_domain_steps": self._out_of_domain,
                "status": self._status, "held_steps": self._held, "restarts": self._restarts}
