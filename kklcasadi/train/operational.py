"""Operational decoders: fit the decoder on the latents the observer really sees.

The observer runs on simulated noisy trajectories (initial states from the X0 box, inputs from the
``train`` ranges of :mod:`kklcasadi.plant.signals`, process and measurement noise at the design level,
``z(0) = 0`` as in the benchmark), and the decoder is fitted to the true states along those runs.
For the linear filter-bank latent of :mod:`kklcasadi.model.variants.filterbank` the latent trajectory does not
depend on the decoder, so one pass suffices.

* :func:`rollouts` -- the noisy training trajectories (CasADi, mapped; no torch).
* :func:`fit_bank_decoder` -- fit the decoder MLP (torch) on ``[z; y_k; u_k] -> x_k`` with an
  optional asinh output transform per state, and return the model arrays of the ``bank`` method.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Mapping

import numpy as np
import torch

from ..model.variants import filterbank as fb
from ..nets.specs import DECODER, MLPSpec
from ..plant import signals as sig
from ..plant.simulate import TrajectoryBatch, simulate_batch
from ..plant.systems import System
from .config import LoopConfig
from .loop import ArrayDataset, FitResult, fit, torch_dtype
from .nets import MLP

__all__ = ["RolloutConfig", "DecoderConfig", "rollouts", "fit_bank_decoder", "BankFit", "LOSSES", "config_record",
           "fold_whitening", "torch_decoder"]

Tensor = torch.Tensor

#: Training losses of :func:`fit_bank_decoder`.
LOSSES = ("mse", "smape", "mse+smape")


@dataclass(frozen=True)
class RolloutConfig:
    """Noisy operational trajectories.

    Attributes
    ----------
    n_traj : int
        Number of runs, spread evenly over ``kinds`` (round-robin).
    T, dt : float
        Horizon and sample period (docs/protocol.md: 50 s, 0.05 s).
    process_std, measurement_std : float
        Noise levels the decoder is fitted for.
    kinds : tuple of str
        Input kinds, drawn with :func:`kklcasadi.plant.signals.sample` from ``regime``.
    regime : str
        Parameter ranges (``train``; never the protocol's test draws).
    method, substeps : str, int
        Plant integrator (see :func:`kklcasadi.plant.simulate.step_function`).
    box_scale : float
        Scale of the X0 box (about its centre) the initial states are drawn from.
    """

    n_traj: int = 2000
    T: float = 50.0
    dt: float = 0.05
    process_std: float = 0.1
    measurement_std: float = 0.1
    kinds: tuple[str, ...] = sig.BENCHMARK_KINDS
    regime: str = "train"
    method: str = "rk"
    substeps: int = 4
    box_scale: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.n_traj, int) or self.n_traj < 1:
            raise ValueError(f"n_traj must be a positive integer, got {self.n_traj!r}")
        if self.regime not in sig.REGIMES:
            raise ValueError(f"unknown regime {self.regime!r}; known: {', '.join(sig.REGIMES)}")
        bad = [k for k in self.kinds if k not in sig.BENCHMARK_KINDS]
        if bad or not self.kinds:
            raise ValueError(f"kinds must be a non-empty subset of {sig.BENCHMARK_KINDS}, got {self.kinds!r}")
        if not (self.box_scale > 0):
            raise ValueError(f"box_scale must be > 0, got {self.box_scale!r}")


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
    stride : int
        Keep every ``stride``-th sample of each run (all of the first ``dense_time`` seconds).
    dense_time : float
        Initial stretch of each run kept at every sample (the transient from ``z = 0``).
    whiten : bool
        Train on whitened features (the whitening is folded into the first layer afterwards).
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
    stride: int = 2
    dense_time: float = 5.0
    whiten: bool = True
    loop: LoopConfig = field(default_factory=lambda: LoopConfig(epochs=30, batch_size=1024, lr=1e-3,
                                                                  schedule="cosine", val_fraction=0.05))
    dtype: str = "float32"

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {self.loss!r}")
        if not isinstance(self.stride, int) or self.stride < 1:
            raise ValueError(f"stride must be a positive integer, got {self.stride!r}")
        if not self.hidden or not all(isinstance(h, int) and h > 0 for h in self.hidden):
            raise ValueError(f"hidden must be a non-empty tuple of positive widths, got {self.hidden!r}")
        torch_dtype(self.dtype)


@dataclass(frozen=True, eq=False)
class BankFit:
    """Result of :func:`fit_bank_decoder`.

    Attributes
    ----------
    arrays : dict
        ``bank/*``, ``decoder/*`` and ``decoder/asinh_scale`` arrays (float64).
    arch : dict
        The decoder's card entry.
    fit : FitResult
    n_samples : int
    seconds : float
    domain : dict
        Per-state 0.1 / 50 / 99.9 percentiles of the training states (the domain the model covers).
    """

    arrays: dict
    arch: dict
    fit: FitResult
    n_samples: int
    seconds: float
    domain: dict


def rollouts(system: System, config: RolloutConfig, seed: int) -> TrajectoryBatch:
    """Simulate the operational training runs (failed runs are dropped).

    Parameters
    ----------
    system : System
    config : RolloutConfig
    seed : int
        Seeds the initial states (Latin hypercube), the input parameters and the noise.

    Returns
    -------
    TrajectoryBatch
        ``x`` (M, N, nx), ``y`` (M, N, ny), ``u`` (M, N, nu) with ``M <= n_traj`` (only ``ok`` runs).
    """
    rng = np.random.default_rng([seed, 1])
    x0 = system.sample_box(config.n_traj, seed, scale=config.box_scale)
    inputs = [sig.sample(config.kinds[i % len(config.kinds)], rng, config.regime, nu=system.nu)
              for i in range(config.n_traj)]
    seeds = np.random.SeedSequence([seed, 2]).spawn(config.n_traj)
    batch = simulate_batch(system, x0, inputs, config.T, config.dt, process_std=config.process_std,
                           measurement_std=config.measurement_std, seed=seeds, method=config.method,
                           substeps=config.substeps)
    ok = batch.ok
    return TrajectoryBatch(batch.t, batch.x[ok], batch.u[ok], batch.y[ok], ok[ok])


def _keep_mask(n: int, dt: float, stride: int, dense_time: float) -> np.ndarray:
    k = np.arange(n)
    return (k * dt < dense_time) | (k % stride == 0)


def _transform(x: np.ndarray, scale: np.ndarray) -> np.ndarray:
    return np.where(scale > 0, np.arcsinh(x / np.where(scale > 0, scale, 1.0)), x)


def _whitening(f: np.ndarray, floor: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Mean (d,) and symmetric whitening matrix W (d, d): ``cov((f - mean) W^T) = I`` up to the floor."""
    mean = f.mean(axis=0)
    cov = np.cov((f - mean).T)
    cov = np.atleast_2d(cov)
    vals, vecs = np.linalg.eigh(cov)
    vals = np.maximum(vals, floor * vals.max())
    return mean, (vecs / np.sqrt(vals)) @ vecs.T


def fold_whitening(arrays: Mapping[str, np.ndarray], mean: np.ndarray, white: np.ndarray) -> dict[str, np.ndarray]:
    """Fold an input whitening into an MLP trained on ``(f - mean) W^T`` (with unit input normalisation).

    ``W0 ((f - mean) W^T)^T = (W0 W) (f - mean)``, so the returned arrays have ``W0 <- W0 W``,
    ``in_mean <- mean``, ``in_std <- 1`` and evaluate the same map on the raw features ``f``.

    Parameters
    ----------
    arrays : Mapping[str, numpy.ndarray]
        ``decoder/*`` arrays of the MLP trained on whitened features (``in_mean = 0``, ``in_std = 1``).
    mean : numpy.ndarray, shape (d,)
    white : numpy.ndarray, shape (d, d)
    """
    d = white.shape[0]
    if not (np.allclose(arrays[f"{DECODER}/in_mean"], 0.0) and np.allclose(arrays[f"{DECODER}/in_std"], 1.0)):
        raise ValueError("fold_whitening expects an MLP with in_mean = 0 and in_std = 1")
    out = dict(arrays)
    out[f"{DECODER}/W0"] = np.asarray(arrays[f"{DECODER}/W0"]) @ white
    out[f"{DECODER}/in_mean"] = np.asarray(mean, dtype=float).copy()
    out[f"{DECODER}/in_std"] = np.ones(d)
    return out


def torch_decoder(arrays: Mapping[str, np.ndarray], arch: Mapping[str, object]) -> Callable[[Tensor], Tensor]:
    """The bank decoder in torch (float64): ``features (..., nz + ny + nu) -> xhat (..., nx)``.

    The same map as :func:`kklcasadi.model.variants.filterbank.decode` and
    :func:`kklcasadi.model.variants.filterbank.decoder_function`.
    """
    mlp = MLP.from_arrays(arrays, DECODER, MLPSpec.from_card(arch, "architecture", DECODER), dtype=torch.float64)
    scale = torch.as_tensor(np.asarray(arrays[fb.ASINH_SCALE], dtype=float))
    pos = scale > 0
    safe = torch.where(pos, scale, torch.ones_like(scale))

    def apply(features: Tensor) -> Tensor:
        v = mlp(features)
        return torch.where(pos, safe * torch.sinh(v), v)

    return apply


def fit_bank_decoder(bank: fb.FilterBank, train: TrajectoryBatch, config: DecoderConfig, *, seed: int = 0,
                     progress: bool = False) -> BankFit:
    """Fit the decoder ``[z_k; y_k; u_k] -> x_k`` on operational runs of the bank observer.

    Parameters
    ----------
    bank : FilterBank
    train : TrajectoryBatch
        Noisy runs (see :func:`rollouts`); the latent is run on them from ``z = 0``.
    config : DecoderConfig
    seed : int
        Seeds torch, the split and the shuffles.
    progress : bool
        Show a progress bar.

    Returns
    -------
    BankFit
    """
    t0 = time.perf_counter()
    nx = train.x.shape[2]
    scale = np.zeros(nx) if config.asinh_scale is None else np.asarray(config.asinh_scale, dtype=float)
    if scale.shape != (nx,) or np.any(scale < 0):
        raise ValueError(f"asinh_scale must have nx = {nx} entries >= 0, got {config.asinh_scale!r}")
    dt = float(train.t[1] - train.t[0])
    z = bank.run(train.y, train.u, dt)
    keep = _keep_mask(train.t.size, dt, config.stride, config.dense_time)
    feats = fb.decoder_features(z[:, keep], train.y[:, keep], train.u[:, keep]).reshape(-1, bank.nz + bank.ny + bank.nu)
    x = train.x[:, keep].reshape(-1, nx)
    v = _transform(x, scale)
    sizes = (feats.shape[1], *config.hidden, nx)
    dtype = torch_dtype(config.dtype)
    torch.manual_seed(seed)
    mlp = MLP(sizes, config.activation).to(torch.float64)
    if config.whiten:
        f_mean, white = _whitening(feats)
    else:
        f_mean, white = feats.mean(axis=0), np.diag(1.0 / (feats.std(axis=0) + 1e-12))
    mlp.set_normalisation(np.zeros(sizes[0]), np.ones(sizes[0]), v.mean(axis=0), v.std(axis=0) + 1e-12)
    mlp = mlp.to(dtype)
    data = ArrayDataset({"f": (feats - f_mean) @ white.T, "v": v, "x": x}, dtype=dtype)
    out_std = torch.as_tensor(mlp.out_std.detach().clone())
    scale_t = torch.as_tensor(scale, dtype=dtype)
    pos = scale_t > 0
    safe = torch.where(pos, scale_t, torch.ones_like(scale_t))

    def loss_fn(batch: Mapping[str, Tensor], epoch: int) -> tuple[Tensor, dict[str, float]]:
        pred = mlp(batch["f"])
        parts: dict[str, float] = {}
        total = pred.new_zeros(())
        if config.loss in ("mse", "mse+smape"):
            mse = (((pred - batch["v"]) / out_std) ** 2).mean()
            parts["mse"] = mse.item()
            total = total + mse
        if config.loss in ("smape", "mse+smape"):
            xhat = torch.where(pos, safe * torch.sinh(pred), pred)
            xt = batch["x"]
            sm = (2.0 * (xt - xhat).abs() / (xt.abs() + xhat.abs() + config.smape_eps)).mean()
            parts["smape"] = sm.item()
            total = total + (sm if config.loss == "smape" else config.smape_weight * sm)
        return total, parts

    result = fit(list(mlp.parameters()), loss_fn, data, config.loop, name="bank decoder", seed=seed,
                 progress=progress)
    arrays = fold_whitening(mlp.to(torch.float64).to_arrays(DECODER), f_mean, white)
    arrays[fb.ASINH_SCALE] = scale.copy()
    arrays.update(fb.bank_arrays(bank))
    pct = np.percentile(train.x.reshape(-1, nx), [0.1, 50.0, 99.9], axis=0)
    domain = {"x_p0.1": pct[0].tolist(), "x_p50": pct[1].tolist(), "x_p99.9": pct[2].tolist()}
    return BankFit(arrays, mlp.spec.to_card(), result, int(len(x)), time.perf_counter() - t0, domain)


def config_record(rollout: RolloutConfig, decoder: DecoderConfig) -> dict:
    """JSON-able record of the two configurations (for a model card)."""
    return {"rollouts": asdict(rollout), "decoder": {**asdict(decoder), "loop": asdict(decoder.loop)}}
