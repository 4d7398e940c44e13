"""The ``bank`` decoder's fit (torch): the MLP ``[z; y_k; u_k] -> x_k`` on the operational samples.

* :func:`fit_bank_decoder` -- fit the decoder MLP on the samples of :func:`kklcasadi.model.operational.operational_data`
  with an optional asinh output transform per state and the angle layout of
  :class:`kklcasadi.model.variants.bankdecoder.Angles`, and return the model arrays of ``bank``.
* :func:`torch_decoder` -- the decoder of such arrays in torch.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, Mapping

import numpy as np
import torch

from ..model.operational import OperationalData
from ..model.variants import bankdecoder as bd
from ..model.variants import filterbank as fb
from ..nets.specs import DECODER
from ..plant.runs import RolloutConfig
from ..validation import Text, error, positive_number
from .config import LoopConfig
from .loop import ArrayDataset, FitResult, fit, torch_dtype
from .nets import MLP

__all__ = ["DecoderConfig", "fit_bank_decoder", "base_residual", "BankFit", "LOSSES", "config_record",
           "fold_whitening", "whitening", "torch_decoder"]

Tensor = torch.Tensor

#: Training losses of :func:`fit_bank_decoder`.
LOSSES = ("mse", "smape", "mse+smape")


@dataclass(frozen=True)
class DecoderConfig:
    """Decoder architecture and its optimisation.

    Attributes
    ----------
    hidden : tuple of int
        Hidden layer widths.
    activation : str
    loss : {"mse", "smape", "mse+smape"}
        ``mse``: mean square error of the normalised (transformed) outputs; ``smape``: the
        protocol's SMAPE of ``xhat`` (with ``smape_eps`` in the denominator); ``mse+smape``: their
        sum with weight ``smape_weight`` on the SMAPE term.
    smape_eps, smape_weight : float
    asinh_scale : tuple of float or None
        Per-state output transform scale (0: none); ``None`` for none at all.
    whiten : bool
        Train on whitened features (the whitening is folded into the first layer afterwards).
    skip : bool
        Give the network a linear skip path (:class:`kklcasadi.nets.specs.MLPSpec`; zero at the start):
        off the fitted states the estimate keeps the slope of that path where the tanh layers level
        off (docs/design.md, "Runs").
    loop : LoopConfig
    dtype : {"float32", "float64"}
        Training precision; the returned arrays are float64 either way.
    """

    hidden: tuple[int, ...] = (256, 256, 256)
    activation: str = "tanh"
    loss: str = "mse"
    smape_eps: float = 1e-3
    smape_weight: float = 0.01
    asinh_scale: tuple[float, ...] | None = None
    whiten: bool = True
    skip: bool = False
    loop: LoopConfig = field(default_factory=lambda: LoopConfig(epochs=30, batch_size=1024, lr=1e-3,
                                                                  schedule="cosine", val_fraction=0.05))
    dtype: str = "float32"

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise error("loss", f"one of {LOSSES}", self.loss)
        positive_number(self.smape_weight, "smape_weight", "the weight of the SMAPE term of loss 'mse+smape'")
        if not self.hidden or not all(isinstance(h, int) and h > 0 for h in self.hidden):
            raise error("hidden", "a non-empty tuple of positive widths", self.hidden)
        torch_dtype(self.dtype)
        if not isinstance(self.skip, bool):
            raise error("skip", "True or False (a linear skip path in the decoder)", self.skip, kind=TypeError)


def whitening(f: np.ndarray, floor: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Mean (d,) and symmetric whitening matrix W (d, d): ``cov((f - mean) W^T) = I`` up to the floor."""
    mean = f.mean(axis=0)
    cov = np.cov((f - mean).T)
    cov = np.atleast_2d(cov)
    vals, vecs = np.linalg.eigh(cov)
    vals = np.maximum(vals, floor * vals.max())
    return mean, (vecs / np.sqrt(vals)) @ vecs.T


def fold_whitening(arrays: Mapping[str, np.ndarray], mean: np.ndarray, white: np.ndarray, *,
                   prefix: str = DECODER) -> dict[str, np.ndarray]:
    """Fold an input whitening into an MLP trained on ``(f - mean) W^T`` (with unit input normalisation).

    ``W0 ((f - mean) W^T)^T = (W0 W) (f - mean)``, so the returned arrays have ``W0 <- W0 W``
    (and ``Wskip <- Wskip W`` with the skip path), ``in_mean <- mean``, ``in_std <- 1`` and evaluate the
    same map on the raw features ``f``.

    Parameters
    ----------
    arrays : Mapping[str, numpy.ndarray]
        ``prefix/*`` arrays of the MLP trained on whitened features (``in_mean = 0``, ``in_std = 1``).
    mean : numpy.ndarray, shape (d,)
    white : numpy.ndarray, shape (d, d)
    prefix : str
        The MLP's array prefix (the decoder's, or the covariance head's).
    """
    d = white.shape[0]
    if not (np.allclose(arrays[f"{prefix}/in_mean"], 0.0) and np.allclose(arrays[f"{prefix}/in_std"], 1.0)):
        raise ValueError("fold_whitening expects an MLP with in_mean = 0 and in_std = 1")
    out = dict(arrays)
    for name in (f"{prefix}/W0", f"{prefix}/Wskip"):
        if name in arrays:
            out[name] = np.asarray(arrays[name]) @ white
    out[f"{prefix}/in_mean"] = np.asarray(mean, dtype=float).copy()
    out[f"{prefix}/in_std"] = np.ones(d)
    return out


def _torch_outputs(v: Tensor, y: Tensor, scale: np.ndarray, angles: bd.Angles) -> Tensor:
    """:func:`kklcasadi.model.variants.bankdecoder.decoder_outputs` in torch."""
    nx = scale.size
    s = torch.as_tensor(scale, dtype=v.dtype, device=v.device)
    pos = s > 0
    cols = list(torch.where(pos, torch.where(pos, s, torch.ones_like(s)) * torch.sinh(v[..., :nx]),
                            v[..., :nx]).unbind(-1))
    for i, j in angles.measured:
        cols[i] = y[..., j] + v[..., i]
    for k, (i, c) in enumerate(angles.free):
        cols[i] = c + torch.atan2(v[..., nx + k], v[..., i])
    return torch.stack(cols, dim=-1)


def torch_decoder(spec: bd.DecoderSpec, arrays: Mapping[str, np.ndarray]) -> Callable[[Tensor, Tensor, Tensor], Tensor]:
    """The bank decoder (one network, ``spec.members`` 1) in torch (float64):
    ``(z (..., nz), y (..., ny), u (..., nu)) -> xhat (..., nx)``.

    The same map as :func:`kklcasadi.model.variants.bankdecoder.decode` and
    :func:`kklcasadi.model.variants.bankdecoder.decoder_function`.
    """
    if spec.members != 1:
        raise error("spec", "the spec of one decoder network (members 1)", spec.members)
    angles = spec.angles
    mlp = MLP.from_arrays(arrays, DECODER, spec.mlp, dtype=torch.float64)
    scale = np.asarray(arrays[bd.ASINH_SCALE], dtype=float)
    a = list(angles.outputs)
    other = [j for j in range(np.asarray(arrays["bank/By"]).shape[1]) if j not in angles.outputs]
    filters = fb.bank_from_arrays(arrays)

    def apply(z: Tensor, y: Tensor, u: Tensor) -> Tensor:
        if a:
            ya = y[..., a]
            gains = torch.as_tensor(bd.latent_gains(filters, z.shape[-1], spec.carried, angles)[:, a])
            f = torch.cat([z - ya @ gains.T, y[..., other], torch.sin(ya), torch.cos(ya), u], dim=-1)
        else:
            f = torch.cat([z, y, u], dim=-1)
        return _torch_outputs(mlp(f), y, scale, angles)

    return apply


@dataclass(frozen=True, eq=False)
class BankFit:
    """Result of :func:`fit_bank_decoder`.

    Attributes
    ----------
    arrays : dict
        ``bank/*``, ``decoder/*`` and ``decoder/asinh_scale`` arrays (float64).
    spec : DecoderSpec
        The decoder's network and angle layout (one member).
    fit : FitResult
    n_samples : int
    seconds : float
    domain : dict
        Per-state 0.1 / 50 / 99.9 percentiles of the training states (the domain the model covers).
    """

    arrays: dict
    spec: bd.DecoderSpec
    fit: FitResult
    n_samples: int
    seconds: float
    domain: dict


def base_residual(v: np.ndarray, offset: np.ndarray, angles: bd.Angles) -> np.ndarray:
    """What a decoder fitted over a base is fitted to: ``v - offset`` (both (N, n_out): the targets,
    :func:`kklcasadi.model.variants.bankdecoder.decoder_targets`, and the base's values), a measured angle's
    column (``angles.measured``) modulo ``2 pi`` on the branch of width ``2 pi`` about its circular mean (the
    decoder writes that angle modulo ``2 pi``; the branch keeps the residual continuous where the base's
    deviation and the target's, wrapped to ``(-pi, pi]``, differ by turns), moved by whole turns so that the
    deviation the decoder writes (``offset`` plus the residual) is within half a turn of 0 on average: the estimate
    ``y_j + v_i`` then lies by its measurement, not turns away (a copy whose reference angle is ``pi`` has an offset
    near ``-pi``, and its residual's circular mean near ``+-pi`` could land on either side)."""
    residual = v - offset
    for i, _ in angles.measured:
        centre = np.angle(np.mean(np.exp(1j * residual[:, i])))
        residual[:, i] = centre + np.angle(np.exp(1j * (residual[:, i] - centre)))
        turns = np.round(np.mean(offset[:, i] + residual[:, i]) / (2 * np.pi))
        if turns:                                        # none: the residual as before, bit for bit
            residual[:, i] -= 2 * np.pi * turns
    return residual


def fit_bank_decoder(bank: fb.FilterBank, data: OperationalData, config: DecoderConfig, *,
                     angles: bd.Angles = bd.NO_ANGLES, seed: int = 0, progress: bool = False,
                     base: np.ndarray | None = None, copy_states: tuple[int, ...] | None = None) -> BankFit:
    """Fit the decoder ``[z_k; y_k; u_k] -> x_k`` on operational samples of the bank observer.

    Parameters
    ----------
    bank : FilterBank
    data : OperationalData
        Samples of noisy runs (:func:`operational_data`, or :meth:`OperationalData.from_runs`).
    config : DecoderConfig
    angles : Angles
        How angle outputs are read and angle states written (:meth:`Angles.of` the plant).
    seed : int
        Seeds torch, the split and the shuffles.
    progress : bool
        Show a progress bar.
    base : numpy.ndarray, shape (n_out, n_features), optional
        A linear map of the decoder's features the network's output is a correction of: the network is fitted
        to the residual ``v - base f`` of its targets (normalised by the residual's own mean and std), and
        ``base`` is folded into its linear skip path (``config.skip`` must be set), so the arrays evaluate
        ``base f`` plus the fitted correction (:func:`kklcasadi.train.bank.copy_base`: a model copy's estimate).
        A measured angle's residual (``angles.measured``) is taken modulo ``2 pi`` on the branch about its
        circular mean, so the estimate is the angle modulo ``2 pi``.
    copy_states : tuple of int or None
        The states each model copy in the latent carries
        (:attr:`kklcasadi.model.variants.copies.ModelCopies.states`; None: all, or no copies).

    Returns
    -------
    BankFit
    """
    t0 = time.perf_counter()
    nx = data.x.shape[1]
    scale = np.zeros(nx) if config.asinh_scale is None else np.asarray(config.asinh_scale, dtype=float)
    if scale.shape != (nx,) or np.any(scale < 0):
        raise error("asinh_scale", f"nx = {nx} entries >= 0", config.asinh_scale)
    gains = None if not angles.outputs else bd.latent_gains(bank, data.z.shape[1],
                                                            nx if copy_states is None else copy_states, angles)
    feats = bd.decoder_features(data.z, data.y, data.u, angles=angles, gains=gains)
    v = bd.decoder_targets(data.x, data.y, scale, angles)
    sizes = (feats.shape[1], *config.hidden, v.shape[1])
    if base is not None:
        base = np.asarray(base, dtype=float)
        if base.shape != (v.shape[1], feats.shape[1]) or not np.all(np.isfinite(base)):
            raise error("base", f"a finite matrix of shape (outputs, features) = {(v.shape[1], feats.shape[1])}",
                        Text(f"shape {base.shape}"))
        if not config.skip:
            raise error("base", "None for a decoder without the linear skip path it is folded into (skip False)",
                        Text("a matrix"), "set DecoderConfig(skip=True)")
    offset = np.zeros_like(v) if base is None else feats @ base.T           # what the network corrects
    residual = v if base is None else base_residual(v, offset, angles)
    dtype = torch_dtype(config.dtype)
    torch.manual_seed(seed)
    mlp = MLP(sizes, config.activation, skip=config.skip).to(torch.float64)
    if config.whiten:
        f_mean, white = whitening(feats)
    else:
        f_mean, white = feats.mean(axis=0), np.diag(1.0 / (feats.std(axis=0) + 1e-12))
    mlp.set_normalisation(np.zeros(sizes[0]), np.ones(sizes[0]), residual.mean(axis=0), residual.std(axis=0) + 1e-12)
    mlp = mlp.to(dtype)
    uses_smape = config.loss in ("smape", "mse+smape")         # only the SMAPE term reads x and y: not gathered else
    data_set = ArrayDataset({"f": (feats - f_mean) @ white.T, "v": residual,
                             **({"x": data.x, "y": data.y, "b": offset} if uses_smape else {})}, dtype=dtype)
    out_std = torch.as_tensor(mlp.out_std.detach().clone())

    def loss_fn(batch: Mapping[str, Tensor], epoch: int) -> tuple[Tensor, dict[str, float]]:
        pred = mlp(batch["f"])
        parts: dict[str, float] = {}
        total = pred.new_zeros(())
        if config.loss in ("mse", "mse+smape"):
            mse = (((pred - batch["v"]) / out_std) ** 2).mean()
            parts["mse"] = mse.item()
            total = total + mse
        if uses_smape:
            xhat = _torch_outputs(pred + batch["b"], batch["y"], scale, angles)
            xt = batch["x"]
            sm = (2.0 * (xt - xhat).abs() / (xt.abs() + xhat.abs() + config.smape_eps)).mean()
            parts["smape"] = sm.item()
            total = total + (sm if config.loss == "smape" else config.smape_weight * sm)
        return total, parts

    result = fit(list(mlp.parameters()), loss_fn, data_set, config.loop, name="bank decoder", seed=seed,
                 progress=progress)
    arrays = fold_whitening(mlp.to(torch.float64).to_arrays(DECODER), f_mean, white)
    if base is not None:         # (layers + Wskip (f - m)) s + o + B f = (layers + (Wskip + B / s) (f - m)) s + o + B m
        arrays[f"{DECODER}/Wskip"] = arrays[f"{DECODER}/Wskip"] + base / arrays[f"{DECODER}/out_std"][:, None]
        arrays[f"{DECODER}/out_mean"] = arrays[f"{DECODER}/out_mean"] + base @ f_mean
    arrays[bd.ASINH_SCALE] = scale.copy()
    arrays.update(fb.bank_arrays(bank))
    pct = np.percentile(data.x, [0.1, 50.0, 99.9], axis=0)
    domain = {"x_p0.1": pct[0].tolist(), "x_p50": pct[1].tolist(), "x_p99.9": pct[2].tolist()}
    return BankFit(arrays, bd.DecoderSpec(mlp.spec, angles, copy_states=copy_states), result, int(len(v)),
                   time.perf_counter() - t0, domain)


def config_record(rollout: RolloutConfig, decoder: DecoderConfig) -> dict:
    """JSON-able record of the two configurations (for a model card)."""
    rollouts = asdict(replace(rollout, envelope=None))
    rollouts["envelope"] = None if rollout.envelope is None else rollout.envelope.to_card()
    return {"rollouts": rollouts, "decoder": {**asdict(decoder), "loop": asdict(decoder.loop)}}
