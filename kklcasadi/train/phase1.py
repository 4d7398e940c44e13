"""Phase 1 (the paper's Algorithm 1): the autonomous encoder ``T`` and decoder ``T*``.

Stage A fits ``T`` to the latent labels plus the PDE residual ``dT/dx f(x, 0) - A T(x) - B y``
(a JVP through the encoder, so it carries gradients into ``T``), with a linear warm-up of its
weight. Stage B fits ``T*`` to ``(T(x), x)``, optionally on ``T(x) + e`` with ``e`` the stationary
latent noise of the expected measurement noise (a minimum-mean-square decoder).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.linalg import solve_continuous_lyapunov

from ..model.card import Domain
from ..model.files import Model
from ..model.variants import MapsSpec
from ..nets.specs import DECODER, ENCODER
from ..plant import data as kdata
from ..plant.design import Design
from ..plant.systems import System
from ..validation import Text, error
from .config import Phase1Config
from .loop import ArrayDataset, FitResult, fit, torch_dtype
from .nets import MLP
from .registry import register
from .result import Trained

__all__ = ["Phase1Result", "train_phase1", "train_autonomous", "pde_residual", "latent_noise_covariance",
           "check_coverage"]

Tensor = torch.Tensor


@dataclass(frozen=True, eq=False)
class Phase1Result:
    encoder: MLP
    decoder: MLP
    encoder_fit: FitResult | None
    decoder_fit: FitResult
    n_labelled: int
    n_pde: int
    domain: Domain
    coverage: kdata.LabelReport


def check_coverage(report: kdata.LabelReport, system: System) -> None:
    """Refuse Phase-1 labels that do not cover the X0 box (:attr:`kklcasadi.plant.data.LabelReport.poor`).

    Raises
    ------
    ValueError
        One line: what the labels cover, and what to do instead.
    """
    if report.poor:
        raise error("labels", f"Phase-1 labels covering the X0 box of {system.name!r} (each state >= "
                    f"{100 * kdata.MIN_STATE_COVERAGE:.0f} % of its range, >= {100 * kdata.MIN_GRID_COVERAGE:.0f} % "
                    "of the grid cells)", Text(report.summary()),
                    "Use labels='auto' (frozen labels where backward runs escape) or 'frozen', more runs (n_traj), "
                    "or the bank observer, which needs no Phase-1 labels (kklcasadi train --method bank).")


def latent_noise_covariance(design: Design, measurement_std: float, dt: float) -> np.ndarray:
    """Stationary covariance ``S`` of the latent error driven by sampled measurement noise.

    Solves ``A S + S A^T + B R B^T dt = 0`` with ``R = measurement_std^2 I``.
    """
    R = measurement_std ** 2 * np.eye(design.ny)
    return solve_continuous_lyapunov(design.A, -design.B @ R @ design.B.T * dt)


def pde_residual(encoder: torch.nn.Module, x: Tensor, xdot: Tensor, y: Tensor, A: Tensor, B: Tensor
                 ) -> tuple[Tensor, Tensor]:
    """``(T(x), dT/dx xdot - A T(x) - B y)`` with the directional derivative as a forward-mode JVP.

    Gradients flow into the encoder's parameters through both outputs.
    """
    z, dz = torch.func.jvp(encoder, (x,), (xdot,))
    return z, dz - z @ A.T - y @ B.T


def train_phase1(system: System, design: Design, config: Phase1Config, *, dt: float = 0.05, seed: int = 0,
                 device: str = "cpu", progress: bool = True, workdir: str | Path | None = None,
                 resume: bool = False, encoder: MLP | None = None) -> Phase1Result:
    """Generate the Phase-1 data and train the encoder (stage A) and the decoder (stage B).

    With ``encoder`` given (a trained ``T``), stage A is skipped: only a new decoder is trained,
    e.g. for another measurement-noise level. The labels are spaced by ``config.label_dt``
    whatever the observer's ``dt`` (which sets only the decoder's latent noise), and refused when
    they do not cover the X0 box (:func:`check_coverage`).

    Returns
    -------
    Phase1Result
        The trained float64 networks (on the CPU) and the fits' histories.
    """
    dtype = torch_dtype(config.dtype)
    labelled, coverage = kdata.phase1_labels(system, design, config.n_traj, seed, t_keep=config.t_keep,
                                             dt=config.label_dt, box_scale=config.box_scale, labels=config.labels,
                                             burn_in_tol=config.burn_in_tol, progress=progress)
    if progress:
        print(f"phase-1 labels: {coverage.summary()}", flush=True)
    check_coverage(coverage, system)
    pde = kdata.pde_points(system, config.n_pde, seed + 1, box_scale=config.box_scale)
    n_lab, n_pde = len(labelled.x), len(pde.x)
    x = np.vstack([labelled.x, pde.x])
    arrays = {"x": x, "z": np.vstack([labelled.z, np.zeros((n_pde, design.nz))]),
              "y": np.vstack([labelled.y, pde.y]), "f": np.vstack([system.f_batch(labelled.x), pde.f]),
              "labelled": np.r_[np.ones(n_lab), np.zeros(n_pde)][:, None]}
    sizes = [system.nx] + [config.width] * config.depth + [design.nz]
    reuse = encoder is not None
    if encoder is None:
        encoder = MLP(sizes, config.activation).to(dtype)
        encoder.set_normalisation(x.mean(0), x.std(0), labelled.z.mean(0), labelled.z.std(0))
    encoder.to(device=device, dtype=dtype)
    A = torch.tensor(design.A, dtype=dtype, device=device)
    B = torch.tensor(design.B, dtype=dtype, device=device)
    z_scale = torch.as_tensor(labelled.z.std(0), dtype=dtype, device=device)
    x_scale = torch.as_tensor(labelled.x.std(0), dtype=dtype, device=device)

    def encoder_loss(batch: dict[str, Tensor], epoch: int) -> tuple[Tensor, dict[str, float]]:
        z, res = pde_residual(encoder, batch["x"], batch["f"], batch["y"], A, B)
        mask = batch["labelled"]
        mse = (((z - batch["z"]) / z_scale) ** 2 * mask).sum() / (mask.sum() * design.nz).clamp_min(1.0)
        pde_loss = ((res / z_scale) ** 2).mean()
        nu = (0.0 if coverage.kind in ("cold", "forward")          # labels that do not solve the PDE
              else config.nu_pde * min(1.0, (epoch + 1) / max(config.warmup_epochs, 1)))
        return mse + nu * pde_loss, {"mse": mse.item(), "pde": pde_loss.item()}

    ckpt = Path(workdir) if workdir is not None else None
    enc_fit = None
    if not reuse:
        enc_fit = fit(list(encoder.parameters()), encoder_loss, ArrayDataset(arrays, dtype=dtype, device=device),
                      config.encoder, name="phase1/encoder", seed=seed, progress=progress, resume=resume,
                      checkpoint=ckpt / "encoder.ckpt.npz" if ckpt else None)
    encoder.requires_grad_(False)

    # The decoder inverts T where T is known: on the labelled states. (At unlabelled PDE points the
    # encoder extrapolates and need not be injective; such pairs would blur the inverse.)
    x_dec = labelled.x
    with torch.no_grad():
        z_all = encoder(torch.as_tensor(x_dec, dtype=dtype, device=device)).cpu().numpy()
    decoder = MLP(list(encoder.spec.sizes)[::-1], config.activation).to(dtype)
    decoder.set_normalisation(z_all.mean(0), z_all.std(0), x_dec.mean(0), x_dec.std(0))
    decoder.to(device)
    if config.spectral_norm:
        for layer in decoder.layers:
            torch.nn.utils.parametrizations.spectral_norm(layer)
    chol = None
    if config.measurement_std > 0:
        S = latent_noise_covariance(design, config.measurement_std, dt)
        chol = torch.as_tensor(np.linalg.cholesky(S + 1e-15 * np.eye(design.nz)), dtype=dtype, device=device)

    def decoder_loss(batch: dict[str, Tensor], epoch: int) -> tuple[Tensor, dict[str, float]]:
        z = batch["z"]
        if chol is not None:
            z = z + torch.randn_like(z) @ chol.T
        loss = (((decoder(z) - batch["x"]) / x_scale) ** 2).mean()
        return loss, {}

    dec_fit = fit(list(decoder.parameters()), decoder_loss,
                  ArrayDataset({"x": x_dec, "z": z_all}, dtype=dtype, device=device), config.decoder,
                  name="phase1/decoder", seed=seed + 1, progress=progress, resume=resume,
                  checkpoint=ckpt / "decoder.ckpt.npz" if ckpt else None)
    if config.spectral_norm:
        for layer in decoder.layers:
            torch.nn.utils.parametrize.remove_parametrizations(layer, "weight", leave_parametrized=True)
    decoder.requires_grad_(False)
    return Phase1Result(encoder.cpu().double(), decoder.cpu().double(), enc_fit, dec_fit, n_lab, n_pde,
                        Domain.of(x_dec, z_all), coverage)


def train_autonomous(system: System, design: Design, base: Model | None, config: Phase1Config, *,
                     dt: float, seed: int, device: str, progress: bool, workdir: Path | None,
                     resume: bool) -> Trained:
    """The training hook of the ``autonomous`` variant (see :mod:`kklcasadi.model.variants`).

    With ``base`` (a Phase-1 model), its encoder and design are kept and only a new decoder is
    trained (e.g. for another noise level).
    """
    if not isinstance(config, Phase1Config):
        raise TypeError(f"config: expected a Phase1Config for 'autonomous', received {type(config).__name__}.")
    encoder = None
    if base is not None:
        design = Design(base.A, base.B)
        encoder = MLP.from_arrays(base.arrays, ENCODER, base.spec.architecture.encoder)
    result = train_phase1(system, design, config, dt=dt, seed=seed, device=device, progress=progress,
                          workdir=workdir, resume=resume, encoder=encoder)
    arrays = {**result.encoder.to_arrays(ENCODER), **result.decoder.to_arrays(DECODER)}
    fits = {ENCODER: result.encoder_fit, DECODER: result.decoder_fit}
    training = {"config": config, "data": {"labelled": result.n_labelled, "pde": result.n_pde,
                                           "labels": result.coverage.summary()},
                **{k: (f.summary() if f is not None else "kept from the base model") for k, f in fits.items()}}
    return Trained(arrays, MapsSpec(result.encoder.spec, result.decoder.spec), design, training,
                   {k: f.history for k, f in fits.items() if f is not None},
                   measurement_std=config.measurement_std, domain=result.domain, coverage=result.coverage)


register("autonomous", train_autonomous, Phase1Config)
