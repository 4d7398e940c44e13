"""Training data: Phase-1 (autonomous) latent labels and PDE points, Phase-2 (input-driven) samples.

Phase-1 labels ``z = T(x)`` come from simulating the plant at ``u = 0`` backward and then forward
together with the latent system ``zdot = A z + B h(x)``, long enough that the initial latent is
forgotten: the decay bound ``kappa exp(-lam t_b) |z0 - T(x)|`` is below ``tol`` (docs/design.md
"Phase-1 labels"; see :func:`phase1_labels`). Where backward runs escape (a damped plant runs away
in reversed time) the exact labels would sit where the forward flow ends; ``labels="auto"``
detects the escapes and freezes the past where it leaves twice the box instead. Every set of
labels is measured against the X0 box (:class:`LabelReport`: per state and on a grid), and
training refuses labels that do not cover it.

The input window convention (shared by training, evaluation, export and C) lives in
:func:`input_windows`: ``w_k`` holds the last ``window`` input samples up to and including ``u_k``,
oldest first; before ``t = 0`` it is filled with ``u_0``.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from typing import NamedTuple, Sequence

import casadi as ca
import numpy as np

from ..validation import Text, error, finite_array, finite_number, one_of
from . import signals as sig
from .design import Design
from .simulate import TrajectoryBatch, simulate_batch, time_grid
from .systems import System
from .windows import input_windows

__all__ = ["Phase1Data", "PDEPoints", "Phase2Data", "LabelReport", "phase1", "phase1_labels", "label_coverage",
           "pde_points", "phase2", "driven_labels", "input_windows", "LABEL_KINDS"]

log = logging.getLogger(__name__)


class Phase1Data(NamedTuple):
    """Autonomous samples: states ``x`` (M, nx), their latent labels ``z = T(x)`` (M, nz), outputs ``y`` (M, ny)."""

    x: np.ndarray
    z: np.ndarray
    y: np.ndarray


class PDEPoints(NamedTuple):
    """PDE collocation points: ``x`` (M, nx), exact ``f = f(x, 0)`` (M, nx) and ``y = h(x)`` (M, ny)."""

    x: np.ndarray
    f: np.ndarray
    y: np.ndarray


#: Largest domain (scale of the X0 box) the automatic choice of :func:`phase1` holds a past in.
MAX_DOMAIN_SCALE = 1000.0


def _latent_system(system: System, design: Design, *, driven: bool = False) -> System:
    """The plant with the latent system ``zdot = A z + B h(x)``.

    ``driven``: ``xdot = f(x, u)`` under the plant's input. Otherwise the plant runs at ``u = 0``
    gated by a scalar input ``g`` in {0, 1}: ``xdot = g f(x, 0)`` (``g = 0`` freezes the plant while
    the latent state settles).
    """
    if design.ny != system.ny:
        raise error("design", f"ny = {system.ny} (the outputs of system {system.name!r})", Text(f"ny = {design.ny}"))
    xz = ca.SX.sym("xz", system.nx + design.nz)
    x, z = xz[:system.nx], xz[system.nx:]
    y = system.h(x)
    zdot = ca.mtimes(ca.DM(design.A), z) + ca.mtimes(ca.DM(design.B), y)
    box = np.vstack([system.x0_box, np.tile([-1.0, 1.0], (design.nz, 1))])
    if driven:
        u = ca.SX.sym("u", system.nu)
        return System(f"{system.name}_driven_kkl", xz, u, ca.vertcat(system.f(x, u), zdot), y, box)
    gate = ca.SX.sym("g")
    return System(f"{system.name}_kkl", xz, gate, ca.vertcat(gate * system.f(x, 0), zdot), y, box)


def _reversed(system: System) -> System:
    """The plant at ``u = 0`` in reversed time, ``xdot = -f(x, 0)``."""
    x = ca.SX.sym("x", system.nx)
    u = ca.SX.sym("u", system.nu)
    return System(f"{system.name}_reversed", x, u, -system.f(x, 0), system.h(x), system.x0_box)


#: Label kinds of :func:`phase1`.
LABEL_KINDS = ("auto", "exact", "frozen", "forward", "cold")
#: Bins per state of the per-state coverage (:func:`label_coverage`).
COVERAGE_BINS = 10
#: Below these the labels do not cover the box (:attr:`LabelReport.poor`): the share of a state's bins
#: holding a label, and the share of occupied grid cells.
MIN_STATE_COVERAGE, MIN_GRID_COVERAGE = 0.5, 0.1


@dataclass(frozen=True)
class LabelReport:
    """How Phase-1 labels were made and how well they cover the X0 box.

    Attributes
    ----------
    kind : str
        The label kind used (``"exact"``, ``"frozen"``, ``"forward"`` or ``"cold"``; ``"auto"`` picks one).
    runs : int
        Trajectories simulated.
    escaped : int
        Backward runs that left the domain (their past frozen at the exit; 0 where no backward pass ran).
    burn_in : float
        Seconds simulated before the kept window (forward labels), 0 otherwise.
    per_state : tuple of float
        Per state, the share of :data:`COVERAGE_BINS` equal bins of its box range holding a label.
    grid : float
        The share of the cells of a grid over the box (``cells_per_axis`` per state) holding a label.
    cells_per_axis : int
    """

    kind: str
    runs: int
    escaped: int
    burn_in: float
    per_state: tuple
    grid: float
    cells_per_axis: int

    @property
    def poor(self) -> bool:
        """Whether the labels miss too much of the box (:data:`MIN_STATE_COVERAGE`, :data:`MIN_GRID_COVERAGE`)."""
        return min(self.per_state) < MIN_STATE_COVERAGE or self.grid < MIN_GRID_COVERAGE

    def to_card(self) -> dict:
        """The card entry ``coverage`` (``docs/model-format.md``)."""
        return {"labels": self.kind, "runs": int(self.runs), "escaped": int(self.escaped),
                "burn_in": float(self.burn_in), "per_state": [float(c) for c in self.per_state],
                "grid": float(self.grid),
                "cells_per_axis": int(self.cells_per_axis)}

    def summary(self) -> str:
        """One line: the kind, the escapes and the coverage."""
        states = ", ".join(f"x{i + 1} {100 * c:.0f} %" for i, c in enumerate(self.per_state))
        escaped = f", {self.escaped} of {self.runs} backward runs escaped" if self.escaped else ""
        burn = f", burn-in {self.burn_in:.3g} s" if self.burn_in else ""
        return (f"{self.kind} labels ({self.runs} runs{escaped}{burn}) cover {states} of the box's ranges and "
                f"{100 * self.grid:.0f} % of a {self.cells_per_axis}^{len(self.per_state)} grid over it")


def label_coverage(x: np.ndarray, box: np.ndarray, *, cells: int, bins: int = COVERAGE_BINS
                   ) -> tuple[tuple, float, int]:
    """How well states ``x`` cover a box: per state and on a grid.

    Parameters
    ----------
    x : numpy.ndarray, shape (M, nx)
        Labelled states (those outside the box count for nothing).
    box : numpy.ndarray, shape (nx, 2)
    bins : int
        Equal bins per state for the per-state share.
    cells : int
        About how many cells the grid has: ``k = max(2, floor(cells^(1/nx)))`` per state (phase-1
        labels: one per trajectory, so that starts spread evenly over the box alone would fill most).

    Returns
    -------
    per_state : tuple of float, length nx
        Per state, the share of its ``bins`` bins that hold a state of ``x``.
    grid : float
        The share of the ``k^nx`` grid cells that hold a state of ``x``.
    k : int
        Cells per axis.
    """
    x = np.asarray(x, dtype=float)
    box = np.asarray(box, dtype=float)
    nx = box.shape[0]
    unit = (x - box[:, 0]) / (box[:, 1] - box[:, 0])          # the box is [0, 1]^nx
    inside = np.all((unit >= 0) & (unit <= 1), axis=1)
    per_state = []
    for i in range(nx):
        u = unit[(unit[:, i] >= 0) & (unit[:, i] <= 1), i]
        per_state.append(np.unique(np.minimum((u * bins).astype(int), bins - 1)).size / bins)
    k = max(2, int(np.floor(cells ** (1.0 / nx) + 1e-9)))
    occupied = np.unique(np.minimum((unit[inside] * k).astype(int), k - 1), axis=0)
    return tuple(per_state), len(occupied) / float(k) ** nx, k


def phase1(system: System, design: Design, n_traj: int = 200, seed: int = 0, *, t_keep: float = 10.0,
           dt: float = 0.05, tol: float = 1e-7, domain_scale: float | None = None, box_scale: float = 1.0,
           labels: str = "exact", starts: np.ndarray | None = None, burn_in_tol: float = 1e-3,
           progress: bool = False) -> Phase1Data:
    """States over the X0 box and their latent labels ``z = T(x)`` under ``u = 0``.

    The labels of :func:`phase1_labels` without its report (same parameters).
    """
    return phase1_labels(system, design, n_traj, seed, t_keep=t_keep, dt=dt, tol=tol, domain_scale=domain_scale,
                         box_scale=box_scale, labels=labels, starts=starts, burn_in_tol=burn_in_tol,
                         progress=progress)[0]


def phase1_labels(system: System, design: Design, n_traj: int = 200, seed: int = 0, *, t_keep: float = 10.0,
                  dt: float = 0.05, tol: float = 1e-7, domain_scale: float | None = None, box_scale: float = 1.0,
                  labels: str = "exact", starts: np.ndarray | None = None, burn_in_tol: float = 1e-3,
                  progress: bool = False) -> tuple[Phase1Data, LabelReport]:
    """States over the X0 box, their latent labels ``z = T(x)`` under ``u = 0``, and how well they cover the box.

    Each trajectory starts at a Latin-hypercube state ``x0`` (or at ``starts``), runs backward in
    time for ``t_b`` (or until it leaves the domain, the X0 box scaled by ``domain_scale``), and then
    forward from
    there with the latent system, ``t_keep`` seconds past ``x0``. The forward pass starts from the
    latent equilibrium ``z = -A^{-1} B h(x_b)``; a trajectory that left the domain is held frozen at
    its exit state until its remaining backward time has passed. So the labels are those of the
    plant frozen outside the domain (which makes ``T`` well defined where backward solutions escape,
    as for FitzHugh-Nagumo, Van der Pol or Roessler) and agree with the true map wherever the past
    stays inside (``labels="frozen"``). With ``labels="exact"`` (default) a frozen trajectory is
    released at once instead, so that its kept samples, ``t_b`` or more after the release, agree
    with the true map to ``tol`` too (they then lie further along the flow than ``x0``).

    ``labels="forward"`` runs no backward pass: each trajectory starts at ``x0`` with the latent
    at its equilibrium ``z = -A^{-1} B h(x0)``, runs a burn-in set by the latent's slowest pole
    (``2 kappa exp(-lam t_b) <= burn_in_tol``), and keeps the ``t_keep`` seconds after it: the
    latents an observer sees once it has forgotten its start, on the states the plant reaches from
    the box. Use them where backward solutions escape (a damped plant runs away in reversed time,
    and the released exact labels then sit where the forward flow ends, near its equilibrium).
    ``labels="cold"`` is the burn-in-free case started at ``z = 0``: all samples are kept. These are
    the latents a cold-started observer (z(0) = 0, as in the benchmark) actually sees; use them
    where backward solutions escape at once and every forward solution settles, so that neither
    exact nor frozen labels cover the operating region (FitzHugh-Nagumo: the backward flow is stiff
    and unstable, its frozen labels are noise). ``labels="auto"`` runs the backward pass and keeps
    the exact labels where no backward run escapes, else makes forward labels.

    Every kind is then measured (:func:`label_coverage`): the report says which kind was used, how
    many backward runs escaped and how well the labelled states cover the X0 box.

    Parameters
    ----------
    system : System
    design : Design
    n_traj : int
        Trajectories, started from a Latin hypercube over the (scaled) X0 box.
    seed : int
        Seed of the Latin hypercube.
    t_keep : float
        Labelled horizon per trajectory, sampled every ``dt``: ``round(t_keep / dt)`` samples each.
    dt : float
        Label spacing (seconds; the plant is simulated on this grid), its own setting: the
        observer's sample time does not enter the labels, so the budget is ``n_traj`` runs of
        ``t_keep`` seconds at any observer ``dt``.
    tol : float
        Relative label accuracy: the burn-in ``t_b`` makes ``kappa exp(-lam t_b) * 2 <= tol``,
        2 bounding ``|z0 - T(x_b)|`` relative to the latent bound ``kappa |B| max|y| / lam``.
    domain_scale : float, optional
        Size of the domain (scale of the X0 box about its centre) outside which the past is frozen.
        Default: 2 for ``labels="frozen"``; for ``"exact"`` the smallest scale >= 2 (at most
        :data:`MAX_DOMAIN_SCALE`) that holds every backward run that stays within that cap. So on a
        stable plant, whose past grows without escaping, the labelled windows start at the sampled
        states and cover the box, instead of being released at once and kept far along the flow,
        near the equilibrium.
    box_scale : float
        Scale of the sampling box about its centre.
    labels : {"exact", "frozen", "forward", "cold", "auto"}
        How the past is treated (see above).
    starts : numpy.ndarray, shape (M, nx), optional
        The starting states instead of a Latin hypercube over the box (``n_traj`` is then M), e.g.
        states an input-driven plant visits.
    burn_in_tol : float
        Relative accuracy of forward labels (their burn-in, see above).
    progress : bool
        Show a progress bar (the trajectories are simulated in chunks).

    Returns
    -------
    Phase1Data
        ``x`` (M, nx), ``z`` (M, nz), ``y`` (M, ny), ``M = n_traj * round(t_keep / dt)`` minus
        trajectories that failed (reported with a warning).
    LabelReport
        The kind used, the escaped backward runs, the burn-in and the coverage of the X0 box.
    """
    if not isinstance(design, Design):
        raise error("design", "a kklcasadi.Design", Text(type(design).__name__), kind=TypeError)
    if not 0 < finite_number(tol, "tol") < 1:
        raise error("tol", "a number in (0, 1)", tol)
    if not 0 < finite_number(burn_in_tol, "burn_in_tol") < 1:
        raise error("burn_in_tol", "a number in (0, 1)", burn_in_tol)
    if domain_scale is not None and finite_number(domain_scale, "domain_scale") < 1:
        raise error("domain_scale", "a number >= 1 (the domain contains the X0 box)", domain_scale)
    one_of(labels, "labels", LABEL_KINDS)
    if starts is None:
        x0 = system.sample_box(n_traj, seed, scale=box_scale)
    else:
        x0 = finite_array(starts, "starts")
        if x0.ndim != 2 or x0.shape[1] != system.nx or len(x0) == 0:
            raise error("starts", f"states of shape (M, {system.nx}), M >= 1", Text(f"shape {x0.shape}"))
        n_traj = len(x0)
    n_keep = time_grid(t_keep, dt).size
    run = _chunked(progress, "phase-1 labels")
    escaped = 0
    if labels in ("exact", "frozen", "auto"):
        back = _backward(system, design, x0, dt, tol, domain_scale, labels)
        escaped = int(back.frozen.sum())
        if escaped:
            log.info("%d of %d backward runs left the domain; their past is frozen at the exit state",
                     escaped, n_traj)
        if labels == "auto" and escaped:
            if progress:
                print(f"phase-1 labels: {escaped} of {n_traj} backward runs of {system.name!r} escaped; making "
                      "frozen labels (the past frozen where it leaves twice the box) instead of exact ones", flush=True)
            labels = "frozen"
            back = _backward(system, design, x0, dt, tol, domain_scale, labels)
            escaped = int(back.frozen.sum())
        elif labels == "auto":
            labels = "exact"
    if labels in ("forward", "cold"):
        n_burn = 0 if labels == "cold" else int(np.ceil(design.forgetting_time(2.0, burn_in_tol) / dt))
        z0 = (np.zeros((n_traj, design.nz)) if labels == "cold"
              else design.latent_equilibrium(system.h_batch(x0)))
        n_total = n_burn + n_keep
        fwd = run(_latent_system(system, design), np.hstack([x0, z0]), [np.ones(n_total)] * n_traj,
                  n_total * dt, dt)
    else:
        n_burn = 0
        # A frozen past leaves a label error kappa exp(-lam t) |T_frozen - T| at time t after unfreezing.
        # "exact": unfreeze at once, so every kept sample is t_b or more after it (error below tol too);
        # "frozen": hold the exit state until the kept window starts at x0 (labels of the frozen plant).
        n_back = back.n_back
        n_total = n_back + n_keep
        gates = [np.ones(n_total) if labels == "exact" else np.r_[np.zeros(n_back - (k - 1)), np.ones(n_keep + k - 1)]
                 for k in back.n_in]
        fwd = run(_latent_system(system, design), np.hstack([back.x_b, design.latent_equilibrium(
            system.h_batch(back.x_b))]), gates, n_total * dt, dt)
    result = _kept(system, design, fwd, n_keep, n_traj)
    per_state, grid, k = label_coverage(result.x, system.x0_box, cells=n_traj)
    return result, LabelReport(labels, n_traj, escaped, n_burn * dt, per_state, grid, k)


class _Backward(NamedTuple):
    n_back: int             # backward samples
    n_in: np.ndarray        # (n_traj,) samples of each backward run inside the domain
    frozen: np.ndarray      # (n_traj,) runs that left the domain
    x_b: np.ndarray         # (n_traj, nx) where each forward pass starts


def _backward(system: System, design: Design, x0: np.ndarray, dt: float, tol: float, domain_scale: float | None,
              labels: str) -> _Backward:
    """The backward pass of exact and frozen labels (see :func:`phase1_labels`)."""
    n_traj = len(x0)
    centre = system.x0_box.mean(axis=1)
    unit = 0.5 * (system.x0_box[:, 1] - system.x0_box[:, 0])
    y_ref = float(np.max(np.abs(system.h_batch(x0)))) or 1.0
    growth = 1.0
    for _attempt in range(6):
        # |z_b - T(x_b)| <= 2 * latent_bound(max |y| over the past); labels scale like latent_bound(y_ref)
        n_back = int(np.ceil(design.forgetting_time(2.0 * growth, tol) / dt))
        # Backward pass: only the starting point is sought, so RK4 is enough; escapes end in inf/NaN.
        back = simulate_batch(_reversed(system), x0, sig.Zero(system.nu), (n_back + 1) * dt, dt, method="rk",
                              blowup=np.inf)
        reach = np.max(np.abs(back.x - centre) / unit, axis=(1, 2))      # scale each past needs; NaN if it escapes
        if domain_scale is not None:
            scale = domain_scale
        elif labels in ("exact", "auto"):
            held = reach[np.isfinite(reach) & (reach <= MAX_DOMAIN_SCALE)]
            scale = float(max(2.0, 1.01 * held.max())) if held.size else 2.0
        else:
            scale = 2.0
        inside = np.all(np.abs(back.x - centre) <= scale * unit, axis=2)  # (n_traj, n_back + 1); NaN -> False
        n_in = np.where(inside.all(axis=1), n_back + 1, np.argmin(inside, axis=1))  # samples before the exit
        y_past = float(np.max(np.abs(np.where(inside[..., None], back.y, 0.0))))
        if y_past <= growth * y_ref:
            break
        growth = 1.5 * y_past / y_ref       # margin: the bound only enters through its logarithm
    else:
        raise RuntimeError(f"phase1: outputs keep growing into the past of {system.name!r} (|y| up to {y_past:.3g}); "
                           "lower domain_scale so that the past is frozen earlier")
    return _Backward(n_back, n_in, n_in <= n_back, back.x[np.arange(n_traj), n_in - 1])


def _chunked(progress: bool, label: str, chunk: int = 32):
    """``simulate_batch`` over chunks of trajectories, with a progress bar when ``progress``."""
    if not progress:
        return simulate_batch

    def run(system: System, x0: np.ndarray, inputs: list, T: float, dt: float) -> TrajectoryBatch:
        from tqdm.auto import tqdm

        parts = []
        with tqdm(total=len(x0), desc=label, unit="traj") as bar:
            for i in range(0, len(x0), chunk):
                parts.append(simulate_batch(system, x0[i:i + chunk], inputs[i:i + chunk], T, dt))
                bar.update(len(parts[-1].x))
        return TrajectoryBatch(parts[0].t, np.concatenate([p.x for p in parts]), np.concatenate([p.u for p in parts]),
                               np.concatenate([p.y for p in parts]), np.concatenate([p.ok for p in parts]))

    return run


def _kept(system: System, design: Design, fwd: TrajectoryBatch, n_keep: int, n_traj: int) -> Phase1Data:
    """The last ``n_keep`` samples of every trajectory that did not fail, as Phase1Data."""
    if not fwd.ok.all():
        warnings.warn(f"phase1: dropped {int((~fwd.ok).sum())} of {n_traj} trajectories whose simulation failed",
                      RuntimeWarning, stacklevel=3)
    xz = fwd.x[fwd.ok, -n_keep:, :].reshape(-1, system.nx + design.nz)
    y = fwd.y[fwd.ok, -n_keep:, :].reshape(-1, system.ny)
    return Phase1Data(xz[:, :system.nx].copy(), xz[:, system.nx:].copy(), y.copy())


def pde_points(system: System, n: int = 10000, seed: int = 1, *, box_scale: float = 1.0) -> PDEPoints:
    """Latin-hypercube collocation points over the X0 box with exact ``f(x, 0)`` and ``h(x)``."""
    x = system.sample_box(n, seed, scale=box_scale)
    f = system.f_batch(x)
    y = system.h_batch(x)
    return PDEPoints(x, f, y)


@dataclass(frozen=True, eq=False)
class Phase2Data:
    """Input-driven samples for every (initial state, input signal) pair that stayed bounded.

    Attributes
    ----------
    t : (N,) sample times
    x, xdot : (P, N, nx) states and exact ``f(x_k, u_k)``
    y : (P, N, ny) noise-free outputs
    u : (P, N, nu) inputs (zero-order hold)
    window : int
        Input window length; windows follow :func:`input_windows`.
    pairs : (P, 2) int
        ``(initial-state index, signal index)`` of each kept trajectory.
    signals : tuple of Signal
        The sampled input signals.
    dropped : tuple of (int, int)
        Pairs whose simulation failed or blew up (reported with a warning, not kept).
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    u: np.ndarray
    xdot: np.ndarray
    window: int
    pairs: np.ndarray
    signals: tuple
    dropped: tuple

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0])

    @property
    def n_samples(self) -> int:
        """Samples with a next window available: ``P * (N - 1)``."""
        return self.x.shape[0] * (self.x.shape[1] - 1)

    def batch(self, index: np.ndarray) -> dict[str, np.ndarray]:
        """Gather flat samples ``index`` (< n_samples) into arrays (the paper's eq. (6)).

        Returns
        -------
        dict
            ``x`` (B, nx), ``y`` (B, ny), ``u`` (B, nu), ``xdot`` (B, nx), ``w`` (B, window, nu)
            the window at ``t_k`` and ``w_next`` (B, window, nu) the window at ``t_k+1``.
        """
        index = np.asarray(index)
        if index.size and (index.min() < 0 or index.max() >= self.n_samples):
            raise error("index", f"flat sample indices in [0, {self.n_samples})",
                        Text(f"range [{index.min()}, {index.max()}]"))
        p, k = np.divmod(index, self.x.shape[1] - 1)
        windows = input_windows(self.u, self.window)
        return {"x": self.x[p, k], "y": self.y[p, k], "u": self.u[p, k], "xdot": self.xdot[p, k],
                "w": windows[p, k], "w_next": windows[p, k + 1]}


def phase2(system: System, n_traj: int = 20, signals: Sequence[sig.Signal] | int = 20, *, window: int = 100,
           T: float = 20.0, dt: float = 0.05, seed: int = 0, regime: str = "train",
           kinds: Sequence[str] = ("constant", "sinusoid", "square"), method: str = "cvodes") -> Phase2Data:
    """Simulate every pair (initial state, input signal) and collect the paper's eq. (6) samples.

    Parameters
    ----------
    system : System
    n_traj : int
        Initial states from a Latin hypercube over X0 (seeded by ``seed``).
    signals : sequence of Signal or int
        The inputs, or how many to draw from ``kinds`` (cycled) with :func:`kklcasadi.plant.signals.sample`
        in ``regime`` using ``numpy.random.default_rng(seed)`` (in the plant's input units where it declares a
        ``u_box``: :func:`kklcasadi.plant.signals.in_box`).
    window : int
        Input window length in samples.
    T, dt : float
        Horizon and sample period of each simulation.

    Returns
    -------
    Phase2Data
    """
    rng = np.random.default_rng(seed)
    if isinstance(signals, (int, np.integer)):
        if signals < 1:
            raise error("signals", "a positive count or a sequence of signals", int(signals))
        if not kinds:
            raise error("kinds", "at least one signal kind", kinds)
        signals = [sig.in_box(sig.sample(kinds[i % len(kinds)], rng, regime, nu=system.nu), system.u_box)
                   for i in range(int(signals))]
    signals = tuple(signals)
    for j, s in enumerate(signals):
        if not callable(s):
            raise error(f"signals[{j}]", "a signal u(t) (a callable)", Text(type(s).__name__), kind=TypeError)
    x0 = system.sample_box(n_traj, seed)
    pairs = np.array([(i, j) for i in range(n_traj) for j in range(len(signals))])
    batch = simulate_batch(system, x0[pairs[:, 0]], [signals[j] for j in pairs[:, 1]], T, dt, method=method)
    dropped = tuple(map(tuple, pairs[~batch.ok].tolist()))
    if dropped:
        warnings.warn(f"phase2: dropped {len(dropped)} of {len(pairs)} trajectories that failed or blew up: "
                      f"(state, signal) pairs {list(dropped)[:10]}", RuntimeWarning, stacklevel=2)
    x, u, y = batch.x[batch.ok], batch.u[batch.ok], batch.y[batch.ok]
    p, n = x.shape[:2]
    xdot = system.f_batch(x.reshape(-1, system.nx), u.reshape(-1, system.nu))
    return Phase2Data(batch.t, x, y, u, xdot.reshape(p, n, system.nx), int(window), pairs[batch.ok], signals, dropped)


def driven_labels(system: System, design: Design, signals: Sequence[sig.Signal], n_traj: int = 50, seed: int = 0,
                  *, t_keep: float = 10.0, dt: float = 0.05, tol: float = 1e-7) -> Phase1Data:
    """Input-driven states and the latent state the observer converges to, ``z = T(x, t)``.

    Every pair (initial state, signal) is simulated with ``zdot = A z + B h(x)`` from
    ``z = -A^{-1} B h(x0)`` for a burn-in ``t_b`` (``2 kappa exp(-lam t_b) <= tol``) plus ``t_keep``
    seconds; the last ``t_keep`` seconds are kept. The signals are shifted in time by ``t_b`` so
    that the kept part sees them from ``t = 0``. These are the labels of the curriculum baseline.

    Returns
    -------
    Phase1Data
        ``x`` (M, nx), ``z`` (M, nz), ``y`` (M, ny); ``M = n_traj * len(signals) * round(t_keep / dt)``
        minus failed trajectories (reported with a warning).
    """
    n_keep = time_grid(t_keep, dt).size
    n_burn = int(np.ceil(design.forgetting_time(2.0, tol) / dt))
    x0 = system.sample_box(n_traj, seed)
    pairs = [(i, j) for i in range(n_traj) for j in range(len(signals))]
    starts = x0[[i for i, _ in pairs]]
    z0 = design.latent_equilibrium(system.h_batch(starts))
    t = time_grid((n_burn + n_keep) * dt, dt) - n_burn * dt
    inputs = [signals[j](np.maximum(t, 0.0)) for _, j in pairs]
    batch = simulate_batch(_latent_system(system, design, driven=True), np.hstack([starts, z0]), inputs,
                           (n_burn + n_keep) * dt, dt)
    if not batch.ok.all():
        warnings.warn(f"driven_labels: dropped {int((~batch.ok).sum())} of {len(pairs)} trajectories that failed",
                      RuntimeWarning, stacklevel=2)
    keep = batch.x[batch.ok, -n_keep:].reshape(-1, system.nx + design.nz)
    y = batch.y[batch.ok, -n_keep:].reshape(-1, system.ny)
    return Phase1Data(keep[:, :system.nx].copy(), keep[:, system.nx:].copy(), y.copy())
