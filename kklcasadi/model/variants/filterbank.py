"""A linear latent filter bank of the measurement and the input, and its learned decoder (torch-free).

The observer of this module (method ``bank``) keeps a linear latent state driven by the measured
output, the applied input and a constant,

    zdot = A z + By y(t) + Bu u_k + c,        z(0) = 0,

and decodes the state with a static map of the latent, the newest measurement and the current
input, ``xhat_k = D(z_k, y_k, u_k)``. Over ``[t_k, t_k+1]`` the output is interpolated linearly
between ``y_k`` and ``y_k+1`` (first-order hold, docs/protocol.md) and the input held at ``u_k``; the
discretisation is exact (:meth:`FilterBank.discretise`):

    z_k+1 = Ad z_k + Gy y_k + Gy_next y_k+1 + Gu u_k + g.

:meth:`FilterBank.design` builds ``A`` block-diagonal from first-order low-pass filters
``p / (s + p)`` of each output and input channel (unit DC gain, so every latent has the scale of
its signal), optional second-order resonators, and an optional *clock* ``c' = a (1 - c)`` that
tells the decoder how long the observer has run (the latent starts at 0, as the protocol's
``z(0) = 0`` asks, and the slow filters take seconds to forget it).

The decoder is an MLP (the arrays of :mod:`kklcasadi.model.files`, prefix ``decoder``) on the
feature vector ``[z; y_k; u_k]`` followed by a per-state output transform: where
``asinh_scale[i] > 0`` the network predicts ``asinh(x_i / asinh_scale[i])`` and
``xhat_i = asinh_scale[i] * sinh(v_i)`` (a log-like scale for a state whose magnitude spans
decades, such as Roessler's x3; odd, so it allows either sign), elsewhere ``xhat_i = v_i``.

The decoder may be an ensemble of ``members`` MLPs of one architecture (prefixes ``decoder``,
``decoder_1``, ...: :func:`member_prefixes`): the mean of their outputs ``v`` goes through the
output transform, and :func:`spread` measures how far they disagree.

The latent may end in model copies of the plant (:class:`kklcasadi.model.variants.copies.ModelCopies`,
arrays ``copies/*``): their latents follow the filters' in ``z`` and the decoder reads them as it reads
the filters (:func:`latent_size`, :func:`latent_run`).

:func:`estimate` is the reference implementation of the whole estimator over many trials at once
(numpy); :func:`decoder_function` and :meth:`FilterBank.step_function` build the same maps as
CasADi Functions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np

from ...nets import builders as casadi_nets
from ...nets.hold import FOHMatrices, foh_matrices
from ...nets.numpy_mlp import mlp_numpy
from ...nets.specs import DECODER, MLPSpec, check_arrays
from ...plant.systems import System
from .copies import ModelCopies, copy_count

__all__ = ["FilterBank", "Angles", "NO_ANGLES", "dc_gains", "decoder_features", "decoder_targets",
           "decoder_outputs", "decode", "decoder_function", "decoder_expression", "estimate", "bank_arrays",
           "bank_from_arrays", "observer_step", "latent_size", "latent_run", "latent_step", "ASINH_SCALE",
           "member_prefixes", "spread", "spread_expression", "feature_expression"]

#: Array name of the per-state output transform scales (0: identity, > 0: asinh scale).
ASINH_SCALE = "decoder/asinh_scale"


def _matrix(value: Any, shape: tuple[int | None, int | None], arg: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 1 and len(shape) == 2 and shape[1] == 1:
        arr = arr[:, None]
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
        raise ValueError(f"{arg} must have shape {tuple('?' if s is None else s for s in shape)}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{arg} must be finite")
    out = arr.copy()
    out.setflags(write=False)
    return out


def _poles(values: Sequence[float], arg: str) -> np.ndarray:
    p = np.asarray(values, dtype=float).ravel()
    if not np.all(np.isfinite(p)) or np.any(p <= 0):
        raise ValueError(f"{arg} must be finite positive pole speeds (rad/s), got {p.tolist()}")
    if np.unique(p).size != p.size:
        raise ValueError(f"{arg} must be distinct, got {p.tolist()}")
    return p


@dataclass(frozen=True, eq=False)
class FilterBank:
    """Linear latent ``zdot = A z + By y + Bu u + c`` (A Hurwitz), ``z(0) = 0``.

    Parameters
    ----------
    A : array_like, shape (nz, nz)
        Hurwitz.
    By : array_like, shape (nz, ny)
    Bu : array_like, shape (nz, nu)
    c : array_like, shape (nz,)
        Constant drive (the clock; zeros for none).

    Raises
    ------
    ValueError
        On inconsistent shapes, non-finite entries or an ``A`` that is not Hurwitz.
    """

    A: np.ndarray
    By: np.ndarray
    Bu: np.ndarray
    c: np.ndarray

    def __post_init__(self) -> None:
        A = _matrix(self.A, (None, None), "A")
        nz = A.shape[0]
        if A.shape != (nz, nz) or nz == 0:
            raise ValueError(f"A must be a non-empty square matrix, got shape {A.shape}")
        if np.max(np.linalg.eigvals(A).real) >= 0:
            raise ValueError(f"A must be Hurwitz; max Re eig(A) = {np.max(np.linalg.eigvals(A).real):.6g}")
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "By", _matrix(self.By, (nz, None), "By"))
        object.__setattr__(self, "Bu", _matrix(self.Bu, (nz, None), "Bu"))
        object.__setattr__(self, "c", _matrix(self.c, (nz,), "c"))

    @classmethod
    def design(cls, ny: int, nu: int, y_poles: Sequence[float], u_poles: Sequence[float] = (),
               *, y_resonators: Sequence[tuple[float, float]] = (), clock: float | None = None) -> FilterBank:
        """Block-diagonal bank: unit-DC-gain filters of every output and input channel.

        Parameters
        ----------
        ny, nu : int
            Output and input sizes.
        y_poles : sequence of float
            Speeds ``p`` (rad/s) of the first-order filters ``p / (s + p)`` of each output channel.
        u_poles : sequence of float
            The same for each input channel.
        y_resonators : sequence of (zeta, omega)
            Second-order filters of each output channel, ``omega^2 / (s^2 + 2 zeta omega s + omega^2)``
            as the states ``(q, qdot / omega)``; ``0 < zeta``, ``omega > 0`` rad/s.
        clock : float, optional
            Rate ``a`` of the clock latent ``c' = a (1 - c)``, ``c(0) = 0``; ``None`` for no clock.

        Returns
        -------
        FilterBank
            Latents ordered: output filters (channel-major), resonators, input filters, clock.
        """
        for value, arg in ((ny, "ny"), (nu, "nu")):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{arg} must be a non-negative integer, got {value!r}")
        py = _poles(y_poles, "y_poles")
        pu = _poles(u_poles, "u_poles") if len(u_poles) else np.zeros(0)
        blocks: list[np.ndarray] = []
        by_rows: list[np.ndarray] = []
        bu_rows: list[np.ndarray] = []
        c_rows: list[np.ndarray] = []

        def add(block: np.ndarray, by: np.ndarray, bu: np.ndarray, cc: np.ndarray) -> None:
            blocks.append(block)
            by_rows.append(by)
            bu_rows.append(bu)
            c_rows.append(cc)

        for j in range(ny):
            for p in py:
                e = np.zeros((1, ny))
                e[0, j] = p
                add(np.array([[-p]]), e, np.zeros((1, nu)), np.zeros(1))
        for zeta, omega in y_resonators:
            if not (np.isfinite(zeta) and np.isfinite(omega) and zeta > 0 and omega > 0):
                raise ValueError(f"each resonator needs zeta > 0 and omega > 0, got {(zeta, omega)}")
            for j in range(ny):
                e = np.zeros((2, ny))
                e[1, j] = omega
                add(np.array([[0.0, omega], [-omega, -2.0 * zeta * omega]]), e, np.zeros((2, nu)), np.zeros(2))
        for j in range(nu):
            for p in pu:
                e = np.zeros((1, nu))
                e[0, j] = p
                add(np.array([[-p]]), np.zeros((1, ny)), e, np.zeros(1))
        if clock is not None:
            if not (np.isfinite(clock) and clock > 0):
                raise ValueError(f"clock must be a rate > 0 (1/s) or None, got {clock!r}")
            add(np.array([[-float(clock)]]), np.zeros((1, ny)), np.zeros((1, nu)), np.array([float(clock)]))
        n = sum(b.shape[0] for b in blocks)
        A = np.zeros((n, n))
        i = 0
        for b in blocks:
            A[i:i + b.shape[0], i:i + b.shape[0]] = b
            i += b.shape[0]
        return cls(A, np.vstack(by_rows), np.vstack(bu_rows), np.concatenate(c_rows))

    @property
    def nz(self) -> int:
        return self.A.shape[0]

    @property
    def ny(self) -> int:
        return self.By.shape[1]

    @property
    def nu(self) -> int:
        return self.Bu.shape[1]

    def discretise(self, dt: float) -> FOHMatrices:
        """Exact discretisation over one sample period (``y`` first-order hold, ``u`` held):
        :func:`kklcasadi.nets.hold.foh_matrices`.

        Parameters
        ----------
        dt : float
            Sample period (> 0).
        """
        return foh_matrices(self.A, self.By, dt, Bu=self.Bu, c=self.c)

    def run(self, y: Any, u: Any, dt: float) -> np.ndarray:
        """Latent trajectories from ``z_0 = 0`` for many trials at once.

        Parameters
        ----------
        y : array_like, shape (M, N, ny) or (N, ny)
        u : array_like, shape (M, N, nu) or (N, nu)
        dt : float

        Returns
        -------
        numpy.ndarray, shape (M, N, nz) or (N, nz)
        """
        y, u, single = _trials(y, u, self.ny, self.nu)
        m = self.discretise(dt)
        n = y.shape[1]
        z = np.zeros((y.shape[0], n, self.nz))
        drive = y[:, :-1] @ m.Gy.T + y[:, 1:] @ m.Gy_next.T + u[:, :-1] @ m.Gu.T + m.g
        AdT = m.Ad.T
        for k in range(n - 1):
            z[:, k + 1] = z[:, k] @ AdT + drive[:, k]
        return z[0] if single else z

    def step_function(self, dt: float, name: str = "bank_latent_step") -> ca.Function:
        """CasADi ``(z, y, y_next, u) -> z_next``: one exact sample interval (see :meth:`discretise`)."""
        m = self.discretise(dt)
        z, u = ca.MX.sym("z", self.nz), ca.MX.sym("u", self.nu)
        y, y_next = ca.MX.sym("y", self.ny), ca.MX.sym("y_next", self.ny)
        z_next = (ca.mtimes(ca.DM(m.Ad), z) + ca.mtimes(ca.DM(m.Gy), y) + ca.mtimes(ca.DM(m.Gy_next), y_next)
                  + ca.mtimes(ca.DM(m.Gu), u) + ca.DM(m.g))
        return ca.Function(name, [z, y, y_next, u], [z_next], ["z", "y", "y_next", "u"], ["z_next"])


def _trials(y: Any, u: Any, ny: int, nu: int) -> tuple[np.ndarray, np.ndarray, bool]:
    y = np.asarray(y, dtype=float)
    u = np.asarray(u, dtype=float)
    single = y.ndim == 2
    if single:
        y, u = y[None], u[None]
    if y.ndim != 3 or y.shape[2] != ny or y.shape[1] < 2:
        raise ValueError(f"y must have shape (N, ny) or (M, N, ny) with ny = {ny} and N >= 2, got {y.shape}")
    if u.shape != y.shape[:2] + (nu,):
        raise ValueError(f"u must have shape {y.shape[:2] + (nu,)} to match y, got {u.shape}")
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(u))):
        raise ValueError("y and u must be finite")
    return y, u, single


@dataclass(frozen=True)
class Angles:
    """How the decoder reads angle outputs and writes angle states, continuous on the circle.

    An angle is defined modulo ``2 pi``; the observer is fed the unwrapped measurement (so the
    filters see a continuous signal), and the decoder is given only what does not change when
    the whole history of an angle output moves by ``2 pi``.

    Attributes
    ----------
    outputs : tuple of int
        Angle outputs ``j``. The decoder reads ``z - g_j y_j`` in place of ``z`` (``g_j = -A^-1 By[:, j]``,
        the latents' DC gains to ``y_j``: each filter's deviation from its output) and
        ``(sin y_j, cos y_j)`` in place of ``y_j``.
    measured : tuple of (int, int)
        ``(i, j)``: angle state ``i`` is output ``j`` (``h_j(x) = x_i``). The decoder predicts the
        deviation ``v_i`` and ``xhat_i = y_j + v_i``, fitted to ``wrap(x_i - y_j)``.
    free : tuple of (int, float)
        ``(i, c)``: an angle state that no output measures. Its two outputs ``v_i`` and
        ``v_{nx + k}`` (``k`` its place in ``free``) are fitted to ``cos(x_i - c)`` and
        ``sin(x_i - c)``, and ``xhat_i = c + atan2(v_{nx + k}, v_i)``, within ``c +- pi`` (``c``: the
        centre of its X0 box row).
    """

    outputs: tuple[int, ...] = ()
    measured: tuple[tuple[int, int], ...] = ()
    free: tuple[tuple[int, float], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "outputs", tuple(int(j) for j in self.outputs))
        object.__setattr__(self, "measured", tuple((int(i), int(j)) for i, j in self.measured))
        object.__setattr__(self, "free", tuple((int(i), float(c)) for i, c in self.free))
        states = [i for i, _ in self.measured] + [i for i, _ in self.free]
        if len(set(states)) != len(states) or len(set(self.outputs)) != len(self.outputs):
            raise ValueError(f"angles: expected distinct outputs and states, received {self}.")
        if any(j not in self.outputs for _, j in self.measured):
            raise ValueError(f"angles: a measured angle state must be an angle output, received {self}.")
        if any(i < 0 for i in states) or any(j < 0 for j in self.outputs) or not all(
                np.isfinite(c) for _, c in self.free):
            raise ValueError(f"angles: expected indices >= 0 and finite centres, received {self}.")

    @classmethod
    def of(cls, system: System) -> Angles:
        """The layout of a plant's ``angle_outputs`` and ``angle_states``: an angle state is
        ``measured`` by the angle output whose expression is that state's symbol."""
        outputs = tuple(system.angle_outputs)
        measured, free = [], []
        for i in system.angle_states:
            js = [j for j in outputs if ca.is_equal(system.y_expr[j], system.x_sym[i])]
            if js:
                measured.append((i, js[0]))
            else:
                free.append((i, float(np.mean(system.x0_box[i]))))
        return cls(outputs, tuple(measured), tuple(free))

    def __bool__(self) -> bool:
        return bool(self.outputs or self.measured or self.free)

    def n_features(self, nz: int, ny: int, nu: int) -> int:
        """The decoder's input size: ``nz + ny + len(outputs) + nu``."""
        return nz + ny + len(self.outputs) + nu

    def n_outputs(self, nx: int) -> int:
        """The decoder network's output size: ``nx + len(free)``."""
        return nx + len(self.free)

    def to_card(self) -> dict:
        """The card entry ``{"outputs": [j], "measured": [[i, j]], "free": [[i, c]]}``."""
        return {"outputs": list(self.outputs), "measured": [list(m) for m in self.measured],
                "free": [list(f) for f in self.free]}

    @classmethod
    def from_card(cls, entry: Any) -> Angles:
        """Inverse of :meth:`to_card` (``ValueError`` on a malformed entry)."""
        if not (isinstance(entry, Mapping) and set(entry) == {"outputs", "measured", "free"}):
            raise ValueError("angles: expected an object with the keys outputs, measured and free, "
                             f"received {entry!r}.")
        pairs = [entry["measured"], entry["free"]]
        if not (isinstance(entry["outputs"], list) and all(isinstance(p, list) and all(
                isinstance(q, list) and len(q) == 2 for q in p) for p in pairs)):
            raise ValueError(f"angles: expected lists of indices and of pairs, received {entry!r}.")
        return cls(tuple(entry["outputs"]), tuple(tuple(m) for m in entry["measured"]),
                   tuple(tuple(f) for f in entry["free"]))


#: No angles: the decoder reads ``[z; y; u]`` and writes ``x``.
NO_ANGLES = Angles()


def dc_gains(bank: FilterBank) -> np.ndarray:
    """The latents' steady-state gains to the outputs, ``-A^-1 By`` (nz, ny): 1 for a unit-gain filter
    of that output, 0 for latents of other signals."""
    return -np.linalg.solve(bank.A, bank.By)


def decoder_features(z: np.ndarray, y: np.ndarray, u: np.ndarray, *, angles: Angles = NO_ANGLES,
                     gains: np.ndarray | None = None) -> np.ndarray:
    """The decoder's input along the last axis: ``[z; y; u]``, or with angle outputs
    ``[z - G_a y_a; y_other; sin y_a; cos y_a; u]`` (:class:`Angles`).

    Parameters
    ----------
    z : numpy.ndarray, shape (..., nz)
    y : numpy.ndarray, shape (..., ny)
    u : numpy.ndarray, shape (..., nu)
    angles : Angles
    gains : numpy.ndarray, shape (nz, ny)
        :func:`dc_gains` of the bank (needed with angle outputs).

    Returns
    -------
    numpy.ndarray, shape (..., nz + ny + len(angles.outputs) + nu)
    """
    if not angles.outputs:
        return np.concatenate([z, y, u], axis=-1)
    a = list(angles.outputs)
    other = [j for j in range(y.shape[-1]) if j not in angles.outputs]
    ya = y[..., a]
    return np.concatenate([z - ya @ np.asarray(gains)[:, a].T, y[..., other], np.sin(ya), np.cos(ya), u], axis=-1)


def decoder_targets(x: np.ndarray, y: np.ndarray, scale: np.ndarray, angles: Angles = NO_ANGLES) -> np.ndarray:
    """What the decoder network is fitted to: the inverse of :func:`decoder_outputs`.

    Parameters
    ----------
    x : numpy.ndarray, shape (..., nx)
    y : numpy.ndarray, shape (..., ny)
    scale : numpy.ndarray, shape (nx,)
        ``asinh`` scales (0: none).
    angles : Angles

    Returns
    -------
    numpy.ndarray, shape (..., nx + len(angles.free))
    """
    v = np.where(scale > 0, np.arcsinh(x / np.where(scale > 0, scale, 1.0)), x)
    for i, j in angles.measured:
        v[..., i] = np.angle(np.exp(1j * (x[..., i] - y[..., j])))
    extra = []
    for i, c in angles.free:
        v[..., i] = np.cos(x[..., i] - c)
        extra.append(np.sin(x[..., i] - c)[..., None])
    return np.concatenate([v, *extra], axis=-1)


def decoder_outputs(v: Any, y: Any, scale: np.ndarray, angles: Angles = NO_ANGLES, *, lib: Any = np) -> Any:
    """The state estimate from the network's output ``v``: ``s_i sinh(v_i)`` where ``s_i > 0``,
    ``y_j + v_i`` for a measured angle, ``c + atan2(v_{nx+k}, v_i)`` for a free one, else ``v_i``.

    ``lib`` is ``numpy`` (arrays ``(..., n)``) or ``casadi`` (column vectors); ``torch`` tensors use
    :func:`kklcasadi.train.decoder.torch_decoder`.
    """
    nx = scale.size
    measured, free = dict(angles.measured), {i: (k, c) for k, (i, c) in enumerate(angles.free)}
    if lib is np:
        out = np.where(scale > 0, scale * np.sinh(v[..., :nx]), v[..., :nx])
        for i, j in measured.items():
            out[..., i] = y[..., j] + v[..., i]
        for i, (k, c) in free.items():
            out[..., i] = c + np.arctan2(v[..., nx + k], v[..., i])
        return out
    rows = []
    for i, s in enumerate(scale):
        if i in measured:
            rows.append(y[measured[i]] + v[i])
        elif i in free:
            rows.append(free[i][1] + ca.atan2(v[nx + free[i][0]], v[i]))
        else:
            rows.append(float(s) * ca.sinh(v[i]) if s > 0 else v[i])
    return ca.vertcat(*rows)


def member_prefixes(members: int) -> tuple[str, ...]:
    """Array prefixes of a decoder ensemble's ``members`` networks: ``decoder``, ``decoder_1``, ..."""
    if not (isinstance(members, (int, np.integer)) and not isinstance(members, bool) and members >= 1):
        raise ValueError(f"members: expected a positive integer (decoder networks averaged), received {members!r}.")
    return (DECODER,) + tuple(f"{DECODER}_{j}" for j in range(1, int(members)))


def _check_decoder(arrays: Mapping[str, Any], arch: Mapping[str, Any], angles: Angles,
                   members: int = 1) -> tuple[MLPSpec, np.ndarray]:
    spec = MLPSpec.from_card(arch, "architecture.decoder", DECODER)
    nx = spec.n_out - len(angles.free)
    shapes = {ASINH_SCALE: (nx,)}
    for prefix in member_prefixes(members):
        shapes.update(spec.array_shapes(prefix))
    check_arrays(arrays, shapes, "bank arrays")
    scale = np.asarray(arrays[ASINH_SCALE], dtype=float)
    if not np.all(np.isfinite(scale)) or np.any(scale < 0):
        raise ValueError(f"{ASINH_SCALE} must be finite and >= 0 (0: no transform), got {scale.tolist()}")
    angle_states = [i for i, _ in angles.measured] + [i for i, _ in angles.free]
    if any(i >= nx for i in angle_states) or np.any(scale[angle_states] > 0):
        raise ValueError(f"angle states {angle_states} must be states (nx = {nx}) without an asinh scale")
    return spec, scale


def _spread_scale(arrays: Mapping[str, Any]) -> np.ndarray:
    """The unit of each network output in the members' spread: the first member's output std."""
    return np.asarray(arrays[f"{DECODER}/out_std"], dtype=float)


def _features(arrays: Mapping[str, Any], spec: MLPSpec, z: Any, y: np.ndarray, u: Any, angles: Angles) -> np.ndarray:
    gains = dc_gains(bank_from_arrays(arrays)) if angles.outputs else None
    f = decoder_features(np.asarray(z, dtype=float), y, np.asarray(u, dtype=float), angles=angles, gains=gains)
    if f.shape[-1] != spec.n_in:
        raise ValueError(f"features must have {spec.n_in} entries along the last axis, got shape {f.shape}")
    return f


def decode(arrays: Mapping[str, Any], arch: Mapping[str, Any], z: Any, y: Any, u: Any, *,
           angles: Angles = NO_ANGLES, members: int = 1) -> np.ndarray:
    """Evaluate the decoder with its input and output maps in numpy (float64).

    With ``members`` > 1 the decoder is an ensemble: the mean of the members' network outputs
    ``v`` goes through the output map.

    Parameters
    ----------
    arrays : Mapping[str, array_like]
        ``bank/*`` (the gains of angle outputs), the MLP arrays of each member (prefixes
        :func:`member_prefixes`) and ``decoder/asinh_scale`` (nx,).
    arch : Mapping
        ``{"sizes": [nz + ny + len(angles.outputs) + nu, ..., nx + len(angles.free)], "activation": ...}``
        (every member's).
    z : array_like, shape (..., nz)
    y : array_like, shape (..., ny)
    u : array_like, shape (..., nu)
    angles : Angles
    members : int
        Networks of the ensemble.

    Returns
    -------
    numpy.ndarray, shape (..., nx)
    """
    spec, scale = _check_decoder(arrays, arch, angles, members)
    y = np.asarray(y, dtype=float)
    f = _features(arrays, spec, z, y, u, angles)
    v = [mlp_numpy(spec, arrays, prefix, f) for prefix in member_prefixes(members)]
    return decoder_outputs(sum(v[1:], v[0]) / len(v), y, scale, angles)


def spread(arrays: Mapping[str, Any], arch: Mapping[str, Any], z: Any, y: Any, u: Any, *,
           angles: Angles = NO_ANGLES, members: int = 2) -> np.ndarray:
    """How far a decoder ensemble's members disagree: ``sqrt(mean_j sum_i ((v_ji - vbar_i) / s_i)^2)``.

    ``v_j`` is member j's network output, ``vbar`` their mean and ``s`` the first member's output
    std (:func:`decode`'s arguments; ``members`` >= 2).

    Returns
    -------
    numpy.ndarray, shape (...)
    """
    if members < 2:
        raise ValueError(f"members: expected at least 2 networks for a spread, received {members!r}.")
    spec, _ = _check_decoder(arrays, arch, angles, members)
    f = _features(arrays, spec, z, np.asarray(y, dtype=float), u, angles)
    v = np.stack([mlp_numpy(spec, arrays, prefix, f) for prefix in member_prefixes(members)])
    d = (v - v.mean(axis=0)) / _spread_scale(arrays)
    return np.sqrt((d ** 2).sum(axis=-1).mean(axis=0))


def decoder_function(arrays: Mapping[str, Any], arch: Mapping[str, Any], name: str = "bank_decoder", *,
                     angles: Angles = NO_ANGLES, members: int = 1) -> ca.Function:
    """CasADi ``(z, y, u) -> xhat``: the decoder MLP with its input and output maps (see :func:`decode`).

    Parameters
    ----------
    arrays : Mapping[str, array_like]
        ``bank/*`` arrays (for the sizes nz, ny, nu and the gains), each member's MLP arrays and
        ``decoder/asinh_scale`` (nx,).
    arch : Mapping
        The decoder's card entry.
    name : str
        Function name.
    angles : Angles
    members : int
        Networks of the ensemble (their outputs averaged).

    Returns
    -------
    ca.Function
        Inputs ``z`` (nz,), ``y`` (ny,), ``u`` (nu,); output ``xhat`` (nx,).
    """
    z, y, u = _symbols(arrays)
    out = decoder_expression(arrays, arch, z, y, u, angles=angles, mlp_name=f"{name}_mlp", members=members)
    return ca.Function(name, [z, y, u], [out], ["z", "y", "u"], ["xhat"])


def _symbols(arrays: Mapping[str, Any]) -> tuple[ca.MX, ca.MX, ca.MX]:
    bank = bank_from_arrays(arrays)
    return ca.MX.sym("z", latent_size(arrays)), ca.MX.sym("y", bank.ny), ca.MX.sym("u", bank.nu)


def feature_expression(arrays: Mapping[str, Any], z: ca.MX, y: ca.MX, u: ca.MX, *,
                       angles: Angles = NO_ANGLES) -> ca.MX:
    """:func:`decoder_features` at CasADi symbols: the decoder's input (nz + ny + len(angles.outputs) + nu, 1)."""
    if not angles.outputs:
        return ca.vertcat(z, y, u)
    bank = bank_from_arrays(arrays)
    a = list(angles.outputs)
    other = [j for j in range(bank.ny) if j not in angles.outputs]
    ya = ca.vertcat(*[y[j] for j in a])
    return ca.vertcat(z - ca.mtimes(ca.DM(dc_gains(bank)[:, a]), ya), *[y[j] for j in other], ca.sin(ya),
                      ca.cos(ya), u)


def _member_expressions(arrays: Mapping[str, Any], arch: Mapping[str, Any], z: ca.MX, y: ca.MX, u: ca.MX,
                        angles: Angles, members: int, mlp_name: str) -> tuple[list, np.ndarray]:
    """Each member's network output ``v_j`` at the symbols, and the output scales."""
    bank = bank_from_arrays(arrays)
    spec, scale = _check_decoder(arrays, arch, angles, members)
    nz = latent_size(arrays)
    if spec.n_in != angles.n_features(nz, bank.ny, bank.nu):
        raise ValueError(f"decoder input size {spec.n_in} != nz + ny + len(angle outputs) + nu = "
                         f"{angles.n_features(nz, bank.ny, bank.nu)}")
    feats = feature_expression(arrays, z, y, u, angles=angles)
    names = [mlp_name] + [f"{mlp_name}_{j}" for j in range(1, members)]
    return [casadi_nets.mlp_function(spec, arrays, prefix, label)(feats)
            for prefix, label in zip(member_prefixes(members), names)], scale


def decoder_expression(arrays: Mapping[str, Any], arch: Mapping[str, Any], z: ca.MX, y: ca.MX, u: ca.MX, *,
                       angles: Angles = NO_ANGLES, mlp_name: str = "decoder_mlp", members: int = 1) -> ca.MX:
    """The decoder's CasADi expression ``xhat (nx, 1)`` at the symbols ``z`` (nz,), ``y`` (ny,), ``u`` (nu,)
    (what :func:`decoder_function` wraps; the ``bank`` variant builds its decoder from it)."""
    v, scale = _member_expressions(arrays, arch, z, y, u, angles, members, mlp_name)
    mean = v[0] if members == 1 else sum(v[1:], v[0]) / members
    return decoder_outputs(mean, y, scale, angles, lib=ca)


def spread_expression(arrays: Mapping[str, Any], arch: Mapping[str, Any], z: ca.MX, y: ca.MX, u: ca.MX, *,
                      angles: Angles = NO_ANGLES, members: int = 2, mlp_name: str = "decoder_mlp") -> ca.MX:
    """:func:`spread` as a CasADi expression (1, 1) at the symbols ``z``, ``y``, ``u``."""
    if members < 2:
        raise ValueError(f"members: expected at least 2 networks for a spread, received {members!r}.")
    v, _ = _member_expressions(arrays, arch, z, y, u, angles, members, mlp_name)
    mean = sum(v[1:], v[0]) / members
    unit = ca.DM(1.0 / _spread_scale(arrays))
    return ca.sqrt(sum(ca.sumsqr((vj - mean) * unit) for vj in v) / members)


def latent_step(arrays: Mapping[str, Any], dt: float, name: str = "latent_step", *,
                copies: ModelCopies | None = None) -> ca.Function:
    """CasADi ``(z, y, y_next, u) -> z_next`` (nz,): the filter bank's exact step (:meth:`FilterBank.step_function`)
    and the model copies' (:meth:`ModelCopies.step_function`), what :func:`latent_run` takes per sample."""
    _check_copies(arrays, copies)
    bank = bank_from_arrays(arrays)
    filters = bank.step_function(dt)
    if copies is None:
        return filters
    z, u = ca.MX.sym("z", bank.nz + copies.nz), ca.MX.sym("u", bank.nu)
    y, y_next = ca.MX.sym("y", bank.ny), ca.MX.sym("y_next", bank.ny)
    z_next = ca.vertcat(filters(z[:bank.nz], y, y_next, u), copies.step_function(dt)(z[bank.nz:], y, y_next, u))
    return ca.Function(name, [z, y, y_next, u], [z_next], ["z", "y", "y_next", "u"], ["z_next"])


def observer_step(arrays: Mapping[str, Any], arch: Mapping[str, Any], dt: float, name: str = "step", *,
                  angles: Angles = NO_ANGLES, members: int = 1, copies: ModelCopies | None = None) -> ca.Function:
    """The whole observer step in the signature of :attr:`kklcasadi.observer.kkl.KKLObserver.step` (window 1).

    ``(z, w, y, y_next, u_next) -> (z_next, w_next, xhat_next)`` with ``w = u_k`` (1, nu), the input
    held over the interval: ``z_next`` from :func:`latent_step`, ``w_next = u_next``,
    ``xhat_next = D(z_next, y_next, u_next)``.

    Parameters
    ----------
    arrays, arch, angles, members
        As in :func:`decoder_function`.
    dt : float
        Sample period.
    name : str
        Function name.
    copies : ModelCopies or None
        The latent's model copies (required where ``arrays`` has ``copies/*``).
    """
    bank = bank_from_arrays(arrays)
    latent = latent_step(arrays, dt, copies=copies)
    dec = decoder_function(arrays, arch, angles=angles, members=members)
    z, w = ca.MX.sym("z", latent_size(arrays)), ca.MX.sym("w", 1, bank.nu)
    y, y_next, u_next = ca.MX.sym("y", bank.ny), ca.MX.sym("y_next", bank.ny), ca.MX.sym("u_next", bank.nu)
    z_next = latent(z, y, y_next, w.T)
    return ca.Function(name, [z, w, y, y_next, u_next], [z_next, u_next.T, dec(z_next, y_next, u_next)],
                       ["z", "w", "y", "y_next", "u_next"], ["z_next", "w_next", "xhat_next"])


def bank_arrays(bank: FilterBank) -> dict[str, np.ndarray]:
    """The bank as arrays ``bank/A`` (nz, nz), ``bank/By`` (nz, ny), ``bank/Bu`` (nz, nu), ``bank/c`` (nz,)."""
    return {"bank/A": np.array(bank.A), "bank/By": np.array(bank.By), "bank/Bu": np.array(bank.Bu),
            "bank/c": np.array(bank.c)}


def bank_from_arrays(arrays: Mapping[str, Any]) -> FilterBank:
    """Inverse of :func:`bank_arrays` (validated)."""
    missing = [k for k in ("bank/A", "bank/By", "bank/Bu", "bank/c") if k not in arrays]
    if missing:
        raise ValueError(f"arrays lack the filter-bank entries {missing}")
    return FilterBank(arrays["bank/A"], arrays["bank/By"], arrays["bank/Bu"], arrays["bank/c"])


def latent_size(arrays: Mapping[str, Any]) -> int:
    """The latent's size: the filter bank's latents and the model copies' (``copies/gains``), if any."""
    return bank_from_arrays(arrays).nz + copy_count(arrays)


def _check_copies(arrays: Mapping[str, Any], copies: ModelCopies | None) -> None:
    n = copy_count(arrays)
    if n and copies is None:
        raise ValueError(f"copies: expected the ModelCopies of the arrays' copies/gains ({n} latents: "
                         "ModelCopies.from_arrays(arrays, system, substeps)), received None.")
    if copies is not None and copies.nz != n:
        raise ValueError(f"copies: expected model copies with {n} latents (the arrays' copies/gains), received "
                         f"{copies.nz}.")


def latent_run(bank: FilterBank, y: np.ndarray, u: np.ndarray, dt: float, *,
               copies: ModelCopies | None = None) -> np.ndarray:
    """The latent from ``z_0 = 0`` for many trials: the filter bank's, then the model copies'.

    Parameters
    ----------
    bank : FilterBank
    y : numpy.ndarray, shape (M, N, ny)
    u : numpy.ndarray, shape (M, N, nu)
    dt : float
    copies : ModelCopies or None
        The latent's model copies, if any (a model's: :meth:`kklcasadi.model.variants.bank.BankSpec.model_copies`).

    Returns
    -------
    numpy.ndarray, shape (M, N, nz)
    """
    z = bank.run(y, u, dt)
    return z if copies is None else np.concatenate([z, copies.run(y, u, dt)], axis=-1)


def estimate(arrays: Mapping[str, Any], arch: Mapping[str, Any], y: Any, u: Any, dt: float, *,
             angles: Angles = NO_ANGLES, members: int = 1, copies: ModelCopies | None = None) -> np.ndarray:
    """Reference implementation of the ``bank`` estimator: ``xhat_k = D(z_k, y_k, u_k)``, ``z_0 = 0``.

    Parameters
    ----------
    arrays : Mapping[str, array_like]
        ``bank/*`` (see :func:`bank_arrays`) and ``decoder/*`` arrays.
    arch : Mapping
        The decoder's card entry ``{"sizes": [...], "activation": ...}``.
    y : array_like, shape (M, N, ny) or (N, ny)
        Measurements ``y_k`` (angle outputs unwrapped).
    u : array_like, shape (M, N, nu) or (N, nu)
        Inputs ``u_k`` held over ``[t_k, t_k+1)``.
    dt : float
        Sample period.
    angles : Angles
        The decoder's angle layout (the card's ``architecture.bank.angles``).
    members : int
        Networks of the decoder ensemble (the card's ``architecture.bank.members``, default 1).
    copies : ModelCopies or None
        The latent's model copies (required where ``arrays`` has ``copies/*``).

    Returns
    -------
    numpy.ndarray, shape (M, N, nx) or (N, nx)
    """
    _check_copies(arrays, copies)
    bank = bank_from_arrays(arrays)
    y, u, single = _trials(y, u, bank.ny, bank.nu)
    xhat = decode(arrays, arch, latent_run(bank, y, u, dt, copies=copies), y, u, angles=angles, members=members)
    return xhat[0] if single else xhat
