"""The learned decoder of the ``bank`` variant (torch-free): ``xhat_k = D(z_k, y_k, u_k)``.

The ``bank`` observer decodes the state with a static map of its latent (the filter bank of
:mod:`kklcasadi.model.variants.filterbank`), the newest measurement and the current input.

The decoder is an MLP (the arrays of :mod:`kklcasadi.model.files`, prefix ``decoder``) on the
feature vector ``[z; y_k; u_k]`` followed by a per-state output transform: where
``asinh_scale[i] > 0`` the network predicts ``asinh(x_i / asinh_scale[i])`` and
``xhat_i = asinh_scale[i] * sinh(v_i)`` (a log-like scale for a state whose magnitude spans
decades, such as Roessler's x3; odd, so it allows either sign), elsewhere ``xhat_i = v_i``.

The decoder may be an ensemble of ``members`` MLPs of one architecture (prefixes ``decoder``,
``decoder_1``, ...: :func:`member_prefixes`): the mean of their outputs ``v`` goes through the

The decoder's functions take its typed spec (:class:`DecoderSpec`: the network, the angle layout, the
ensemble's size) and the arrays. :func:`estimate` is the reference implementation of the whole estimator
over many trials at once (numpy); :func:`decoder_function` and :meth:`FilterBank.step_function` build the
same maps as CasADi Functions; :func:`decoder_expression`, :func:`spread_expression` and :func:`latent_step`
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np

from ...nets import builders as casadi_nets
from ...nets.numpy_mlp import mlp_numpy
from ...nets.specs import DECODER, MLPSpec, check_arrays
from ...plant.systems import System
from ...validation import error
from .copies import ModelCopies
from .ekfblock import EKFBlock
from .filterbank import FilterBank, as_trials, bank_from_arrays, check_copies, latent_run, latent_size, latent_step

__all__ = ["Angles", "NO_ANGLES", "DecoderSpec", "dc_gains", "latent_gains", "decoder_features", "decoder_targets",
           "decoder_outputs", "decode", "decoder_function", "decoder_expression", "estimate", "observer_step",
           "ASINH_SCALE", "member_prefixes", "spread", "spread_expression", "feature_expression",
           "decoder_and_spread_expression"]

#: Array name of the per-state output transform scales (0: identity, > 0: asinh scale).
ASINH_SCALE = "decoder/asinh_scale"


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
            raise error("angles", "lists of indices and of pairs", entry)
        return cls(tuple(entry["outputs"]), tuple(tuple(m) for m in entry["measured"]),
                   tuple(tuple(f) for f in entry["free"]))


#: No angles: the decoder reads ``[z; y; u]`` and writes ``x``.
NO_ANGLES = Angles()


def dc_gains(bank: FilterBank) -> np.ndarray:
    """The latents' steady-state gains to the outputs, ``-A^-1 By`` (nz, ny): 1 for a unit-gain filter
    of that output, 0 for latents of other signals."""
    return -np.linalg.solve(bank.A, bank.By)


def latent_gains(bank: FilterBank, nz: int, states: int | Sequence[int] | None, angles: Angles) -> np.ndarray:
    """The gains ``G`` (nz, ny) of the decoder's features ``z - G_a y_a``: the filters' :func:`dc_gains`, then
    on the model copies' rows (``nz - bank.nz``, blocks of the states a copy carries) 1 where the copy's state
    is a measured angle (``angles.measured``) of that output, else 0: a copy's angle follows its measurement
    turn for turn (the plant's field is periodic in it), so ``z - G_a y_a`` does not change when ``y_a``
    moves by ``2 pi``.

    ``states`` are the plant states each copy carries, in its latent order (an int ``nx``: all of them,
    :attr:`kklcasadi.model.variants.copies.ModelCopies.states`; None: no copies).

    Raises
    ------
    ValueError
        ``nz - bank.nz`` is not a whole number of copies of ``states``.
    """
    carried = None if states is None else tuple(range(states)) if isinstance(states, (int, np.integer)) \
        else tuple(states)
    width = 0 if carried is None else len(carried)
    extra = nz - bank.nz
    if extra < 0 or (not width and extra) or (width and extra % width) or (carried is not None and not width):
        raise error("nz", f"the filters' {bank.nz} latents and whole model copies of "
                    f"{'nx = ' + str(width) if carried == tuple(range(width)) else width} states", nz)
    gains = np.zeros((nz, bank.ny))
    gains[:bank.nz] = dc_gains(bank)
    row = {i: k for k, i in enumerate(carried or ())}
    for k in range(extra // width if width else 0):
        for i, j in angles.measured:
            if i in row:
                gains[bank.nz + k * width + row[i], j] = 1.0
    return gains


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
        :func:`latent_gains` of the latent (needed with angle outputs).

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
        raise error("members", "a positive integer (decoder networks averaged)", members)
    return (DECODER,) + tuple(f"{DECODER}_{j}" for j in range(1, int(members)))


@dataclass(frozen=True)
class DecoderSpec:
    """The typed spec of a bank's decoder: its network, its angle layout and its ensemble's size.

    A loaded model gives it (:attr:`kklcasadi.model.variants.bank.BankSpec.decoder_spec`), so does a fit
    (``BankFit.decoder_spec``); :meth:`from_card` reads a card's decoder entry.

    Attributes
    ----------
    mlp : MLPSpec
        Every member's network, ``[features] -> [nx + len(angles.free)]``.
    angles : Angles
        How angle outputs are read and angle states written.
    members : int
        Networks of the ensemble (their outputs averaged; prefixes :func:`member_prefixes`).
    copy_states : tuple of int or None
        The plant states each model copy in the latent carries (None: all ``nx``, or no copies), which the gains
        of angle outputs follow (:func:`latent_gains`).
    """

    mlp: MLPSpec
    angles: Angles = NO_ANGLES
    members: int = 1
    copy_states: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.mlp, MLPSpec):
            raise TypeError(f"mlp: expected an MLPSpec, received {type(self.mlp).__name__}.")
        if not isinstance(self.angles, Angles):
            raise TypeError(f"angles: expected an Angles, received {type(self.angles).__name__}.")
        member_prefixes(self.members)

    @classmethod
    def from_card(cls, arch: Mapping[str, Any], *, angles: Angles = NO_ANGLES, members: int = 1) -> DecoderSpec:
        """The spec of a card's decoder entry ``{"sizes": [...], "activation": ...}``."""
        return cls(MLPSpec.from_card(arch, "architecture.decoder", DECODER), angles, members)

    @property
    def nx(self) -> int:
        return self.mlp.n_out - len(self.angles.free)

    @property
    def carried(self) -> int | tuple[int, ...]:
        """What :func:`latent_gains` takes of the copies: their :attr:`copy_states`, or ``nx`` (all)."""
        return self.nx if self.copy_states is None else self.copy_states

    def check(self, arrays: Mapping[str, Any]) -> np.ndarray:
        """Check the decoder's arrays (every member's MLP and ``decoder/asinh_scale``); return the scales (nx,)."""
        nx = self.nx
        shapes = {ASINH_SCALE: (nx,)}
        for prefix in member_prefixes(self.members):
            shapes.update(self.mlp.array_shapes(prefix))
        check_arrays(arrays, shapes, "bank arrays")
        scale = np.asarray(arrays[ASINH_SCALE], dtype=float)
        if not np.all(np.isfinite(scale)) or np.any(scale < 0):
            raise ValueError(f"{ASINH_SCALE} must be finite and >= 0 (0: no transform), got {scale.tolist()}")
        angle_states = [i for i, _ in self.angles.measured] + [i for i, _ in self.angles.free]
        if any(i >= nx for i in angle_states) or np.any(scale[angle_states] > 0):
            raise ValueError(f"angle states {angle_states} must be states (nx = {nx}) without an asinh scale")
        return scale


def _spread_scale(arrays: Mapping[str, Any]) -> np.ndarray:
    """The unit of each network output in the members' spread: the first member's output std."""
    return np.asarray(arrays[f"{DECODER}/out_std"], dtype=float)


def _features(arrays: Mapping[str, Any], spec: DecoderSpec, z: Any, y: np.ndarray, u: Any) -> np.ndarray:
    z = np.asarray(z, dtype=float)
    gains = latent_gains(bank_from_arrays(arrays), z.shape[-1], spec.carried, spec.angles) if spec.angles.outputs \
        else None
    f = decoder_features(z, y, np.asarray(u, dtype=float), angles=spec.angles, gains=gains)
    if f.shape[-1] != spec.mlp.n_in:
        raise ValueError(f"features must have {spec.mlp.n_in} entries along the last axis, got shape {f.shape}")
    return f


def decode(spec: DecoderSpec, arrays: Mapping[str, Any], z: Any, y: Any, u: Any) -> np.ndarray:
    """Evaluate the decoder with its input and output maps in numpy (float64).

    With ``spec.members`` > 1 the decoder is an ensemble: the mean of the members' network outputs
    ``v`` goes through the output map.

    Parameters
    ----------
    spec : DecoderSpec
        The network (``sizes [nz + ny + len(angles.outputs) + nu, ..., nx + len(angles.free)]``, every
        member's), the angle layout and the ensemble's size.
    arrays : Mapping[str, array_like]
        ``bank/*`` (the gains of angle outputs), the MLP arrays of each member (prefixes
        :func:`member_prefixes`) and ``decoder/asinh_scale`` (nx,); checked.
    z : array_like, shape (..., nz)
    y : array_like, shape (..., ny)
    u : array_like, shape (..., nu)

    Returns
    -------
    numpy.ndarray, shape (..., nx)
    """
    scale = spec.check(arrays)
    y = np.asarray(y, dtype=float)
    f = _features(arrays, spec, z, y, u)
    v = [mlp_numpy(spec.mlp, arrays, prefix, f) for prefix in member_prefixes(spec.members)]
    return decoder_outputs(sum(v[1:], v[0]) / len(v), y, scale, spec.angles)


def spread(spec: DecoderSpec, arrays: Mapping[str, Any], z: Any, y: Any, u: Any) -> np.ndarray:
    """How far a decoder ensemble's members disagree: ``sqrt(mean_j sum_i ((v_ji - vbar_i) / s_i)^2)``.

    ``v_j`` is member j's network output, ``vbar`` their mean and ``s`` the first member's output
    std (:func:`decode`'s arguments; ``spec.members`` >= 2).

    Returns
    -------
    numpy.ndarray, shape (...)
    """
    if spec.members < 2:
        raise error("members", "at least 2 networks for a spread", spec.members)
    spec.check(arrays)
    f = _features(arrays, spec, z, np.asarray(y, dtype=float), u)
    v = np.stack([mlp_numpy(spec.mlp, arrays, prefix, f) for prefix in member_prefixes(spec.members)])
    d = (v - v.mean(axis=0)) / _spread_scale(arrays)
    return np.sqrt((d ** 2).sum(axis=-1).mean(axis=0))


def decoder_function(spec: DecoderSpec, arrays: Mapping[str, Any], name: str = "bank_decoder", *,
                     ekf: EKFBlock | None = None) -> ca.Function:
    """CasADi ``(z, y, u) -> xhat``: the decoder MLP with its input and output maps (see :func:`decode`).

    Parameters
    ----------
    spec : DecoderSpec
    arrays : Mapping[str, array_like]
        ``bank/*`` arrays (for the sizes nz, ny, nu and the gains), each member's MLP arrays and
        ``decoder/asinh_scale`` (nx,); checked.
    name : str
        Function name.
    ekf : EKFBlock or None
        The latent's augmented EKF block, if any (it has no arrays; it sizes ``z``).

    Returns
    -------
    ca.Function
        Inputs ``z`` (nz,), ``y`` (ny,), ``u`` (nu,); output ``xhat`` (nx,).
    """
    spec.check(arrays)
    bank = bank_from_arrays(arrays)
    nz = latent_size(arrays, ekf)
    if spec.mlp.n_in != spec.angles.n_features(nz, bank.ny, bank.nu):
        raise ValueError(f"decoder input size {spec.mlp.n_in} != nz + ny + len(angle outputs) + nu = "
                         f"{spec.angles.n_features(nz, bank.ny, bank.nu)}")
    z, y, u = ca.MX.sym("z", nz), ca.MX.sym("y", bank.ny), ca.MX.sym("u", bank.nu)
    out = decoder_expression(spec, arrays, bank, z, y, u, mlp_name=f"{name}_mlp")
    return ca.Function(name, [z, y, u], [out], ["z", "y", "u"], ["xhat"])


def feature_expression(bank: FilterBank, z: ca.MX, y: ca.MX, u: ca.MX, *, angles: Angles = NO_ANGLES,
                       states: int | Sequence[int] | None = None) -> ca.MX:
    """:func:`decoder_features` at CasADi symbols: the decoder's input (nz + ny + len(angles.outputs) + nu, 1)
    (``bank`` and the states the model copies carry give the gains of angle outputs, :func:`latent_gains`)."""
    if not angles.outputs:
        return ca.vertcat(z, y, u)
    a = list(angles.outputs)
    other = [j for j in range(bank.ny) if j not in angles.outputs]
    ya = ca.vertcat(*[y[j] for j in a])
    gains = latent_gains(bank, z.size1(), states, angles)[:, a]
    return ca.vertcat(z - ca.mtimes(ca.DM(gains), ya), *[y[j] for j in other], ca.sin(ya),
                      ca.cos(ya), u)


def _member_expressions(spec: DecoderSpec, arrays: Mapping[str, Any], bank: FilterBank, z: ca.MX, y: ca.MX,
                        u: ca.MX, mlp_name: str) -> list:
    """Each member's network output ``v_j`` at the symbols."""
    feats = feature_expression(bank, z, y, u, angles=spec.angles, states=spec.carried)
    names = [mlp_name] + [f"{mlp_name}_{j}" for j in range(1, spec.members)]
    return [casadi_nets.mlp_function(spec.mlp, arrays, prefix, label)(feats)
            for prefix, label in zip(member_prefixes(spec.members), names)]


def decoder_expression(spec: DecoderSpec, arrays: Mapping[str, Any], bank: FilterBank, z: ca.MX, y: ca.MX,
                       u: ca.MX, *, mlp_name: str = "decoder_mlp") -> ca.MX:
    """The decoder's CasADi expression ``xhat (nx, 1)`` at the symbols ``z`` (nz,), ``y`` (ny,), ``u`` (nu,)
    (what :func:`decoder_function` wraps; the ``bank`` variant builds its decoder from it). ``arrays`` are
    taken as checked (:meth:`DecoderSpec.check`); ``bank`` gives the gains of angle outputs."""
    v = _member_expressions(spec, arrays, bank, z, y, u, mlp_name)
    return _decoded(spec, arrays, _mean(spec, v), y)


def _mean(spec: DecoderSpec, v: list) -> Any:
    """The members' mean output."""
    return v[0] if spec.members == 1 else sum(v[1:], v[0]) / spec.members


def _decoded(spec: DecoderSpec, arrays: Mapping[str, Any], mean: Any, y: ca.MX) -> ca.MX:
    """The estimate from the members' mean output."""
    return decoder_outputs(mean, y, np.asarray(arrays[ASINH_SCALE], dtype=float), spec.angles, lib=ca)


def _spread_of(arrays: Mapping[str, Any], v: list, mean: Any) -> ca.MX:
    """The members' spread about their mean output, in units of the first member's output std."""
    unit = ca.DM(1.0 / _spread_scale(arrays))
    return ca.sqrt(sum(ca.sumsqr((vj - mean) * unit) for vj in v) / len(v))


def decoder_and_spread_expression(spec: DecoderSpec, arrays: Mapping[str, Any], bank: FilterBank, z: ca.MX,
                                  y: ca.MX, u: ca.MX, *, mlp_name: str = "decoder_mlp") -> tuple[ca.MX, ca.MX]:
    """:func:`decoder_expression` and :func:`spread_expression` from one evaluation of the members: the same two
    values, each member's network run once for both (the domain monitor's spread test costs no second decode)."""
    if spec.members < 2:
        raise error("members", "at least 2 networks for a spread", spec.members)
    v = _member_expressions(spec, arrays, bank, z, y, u, mlp_name)
    mean = _mean(spec, v)
    return _decoded(spec, arrays, mean, y), _spread_of(arrays, v, mean)


def spread_expression(spec: DecoderSpec, arrays: Mapping[str, Any], bank: FilterBank, z: ca.MX, y: ca.MX,
                      u: ca.MX, *, mlp_name: str = "decoder_mlp") -> ca.MX:
    """:func:`spread` as a CasADi expression (1, 1) at the symbols ``z``, ``y``, ``u`` (``arrays`` as in
    :func:`decoder_expression`)."""
    if spec.members < 2:
        raise error("members", "at least 2 networks for a spread", spec.members)
    v = _member_expressions(spec, arrays, bank, z, y, u, mlp_name)
    return _spread_of(arrays, v, _mean(spec, v))


def observer_step(spec: DecoderSpec, arrays: Mapping[str, Any], dt: float, name: str = "step", *,
                  copies: ModelCopies | None = None, ekf: EKFBlock | None = None) -> ca.Function:
    """The whole observer step in the signature of :attr:`kklcasadi.observer.kkl.KKLObserver.step` (window 1).

    ``(z, w, y, y_next, u_next) -> (z_next, w_next, xhat_next)`` with ``w = u_k`` (1, nu), the input
    held over the interval: ``z_next`` from :func:`latent_step`, ``w_next = u_next``,
    ``xhat_next = D(z_next, y_next, u_next)``.

    Parameters
    ----------
    spec, arrays
        As in :func:`decoder_function`.
    dt : float
        Sample period.
    name : str
        Function name.
    copies : ModelCopies or None
        The latent's model copies (required where ``arrays`` has ``copies/*``).
    ekf : EKFBlock or None
        The latent's augmented EKF block, if any.
    """
    check_copies(arrays, copies)
    bank = bank_from_arrays(arrays)
    latent = latent_step(bank, dt, copies=copies, ekf=ekf)
    dec = decoder_function(spec, arrays, ekf=ekf)
    z, w = ca.MX.sym("z", latent_size(arrays, ekf)), ca.MX.sym("w", 1, bank.nu)
    y, y_next, u_next = ca.MX.sym("y", bank.ny), ca.MX.sym("y_next", bank.ny), ca.MX.sym("u_next", bank.nu)
    z_next = latent(z, y, y_next, w.T)
    return ca.Function(name, [z, w, y, y_next, u_next], [z_next, u_next.T, dec(z_next, y_next, u_next)],
                       ["z", "w", "y", "y_next", "u_next"], ["z_next", "w_next", "xhat_next"])


def estimate(spec: DecoderSpec, arrays: Mapping[str, Any], y: Any, u: Any, dt: float, *,
             copies: ModelCopies | None = None, ekf: EKFBlock | None = None) -> np.ndarray:
    """Reference implementation of the ``bank`` estimator: ``xhat_k = D(z_k, y_k, u_k)``, ``z_0 = 0``.

    Parameters
    ----------
    spec : DecoderSpec
        The decoder (a model's: :attr:`kklcasadi.model.variants.bank.BankSpec.decoder_spec`).
    arrays : Mapping[str, array_like]
        ``bank/*`` (see :func:`bank_arrays`) and ``decoder/*`` arrays.
    y : array_like, shape (M, N, ny) or (N, ny)
        Measurements ``y_k`` (angle outputs unwrapped).
    u : array_like, shape (M, N, nu) or (N, nu)
        Inputs ``u_k`` held over ``[t_k, t_k+1)``.
    dt : float
        Sample period.
    copies : ModelCopies or None
        The latent's model copies (required where ``arrays`` has ``copies/*``).
    ekf : EKFBlock or None
        The latent's augmented EKF block, if any.

    Returns
    -------
    numpy.ndarray, shape (M, N, nx) or (N, nx)
    """
    check_copies(arrays, copies)
    bank = bank_from_arrays(arrays)
    y, u, single = as_trials(y, u, bank.ny, bank.nu)
    xhat = decode(spec, arrays, latent_run(bank, y, u, dt, copies=copies, ekf=ekf), y, u)
    return xhat[0] if single else xhat
