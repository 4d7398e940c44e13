"""Phase 2 on a frozen Phase-1 model: HyperKKL_obs (Algorithm 2), HyperKKL_dyn (Algorithm 3) and
the curriculum baseline.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..model.card import Domain
from ..model.files import Model
from ..model.variants import DynModelSpec, MapsSpec, ObsModelSpec
from ..nets.specs import DECODER, ENCODER, lora_target_shapes
from ..plant import data as kdata
from ..plant import signals as sig
from ..plant.design import Design
from ..plant.systems import System
from .config import CurriculumConfig, DynConfig, ObsConfig
from .loop import ArrayDataset, fit, torch_dtype
from .nets import MLP, LoRAHyperNet, ObsInjection, mlp_forward_lora
from .phase1 import pde_residual
from .registry import register
from .result import Trained

__all__ = ["train_obs", "train_dyn", "train_curriculum", "Phase2Dataset", "model_based_injection"]

Tensor = torch.Tensor


class Phase2Dataset:
    """Flat samples of :class:`kklcasadi.plant.data.Phase2Data` (windows gathered per batch) plus extra arrays.

    ``extra`` arrays have one row per flat sample (``Phase2Data.n_samples``).
    """

    def __init__(self, p2: kdata.Phase2Data, extra: dict[str, np.ndarray] | None = None, *,
                 keys: tuple = ("x", "y", "u", "xdot", "w", "w_next"), dtype: torch.dtype = torch.float64,
                 device: str = "cpu") -> None:
        self.p2, self.keys, self.dtype, self.device = p2, keys, dtype, device
        self.extra = {k: torch.as_tensor(v, dtype=dtype, device=device) for k, v in (extra or {}).items()}
        for k, v in self.extra.items():
            if len(v) != p2.n_samples:
                raise ValueError(f"extra array {k!r} has {len(v)} rows, expected {p2.n_samples}")

    def __len__(self) -> int:
        return self.p2.n_samples

    def get(self, index: np.ndarray) -> dict[str, Tensor]:
        raw = self.p2.batch(np.asarray(index))
        out = {k: torch.as_tensor(np.ascontiguousarray(raw[k]), dtype=self.dtype, device=self.device)
               for k in self.keys}
        idx = torch.as_tensor(np.asarray(index), device=self.device)
        out.update({k: v[idx] for k, v in self.extra.items()})
        return out


def _flat(p2: kdata.Phase2Data, name: str) -> np.ndarray:
    """Per-sample rows of a (P, N, d) array of ``p2`` in the flat order of ``Phase2Data.batch``."""
    arr = getattr(p2, name)
    return arr[:, :-1].reshape(-1, arr.shape[-1])


def base_nets(base: Model, dtype: torch.dtype, device: str) -> tuple[MLP, MLP]:
    arch = base.spec.architecture
    return tuple(MLP.from_arrays(base.arrays, name, spec).to(dtype=dtype, device=device).requires_grad_(False)
                 for name, spec in ((ENCODER, arch.encoder), (DECODER, arch.decoder)))  # type: ignore[return-value]


def check_phase2(method: str, base: Model | None, config: Any, expected: type) -> Model:
    if base is None or base.method != "autonomous":
        found = "no base model" if base is None else f"method {base.method!r} at {base.path}"
        raise ValueError(f"base: expected an 'autonomous' (Phase-1) model for {method!r}, received {found}.")
    if type(config) is not expected:
        raise TypeError(f"config: expected a {expected.__name__} for {method!r}, received {type(config).__name__}.")
    return base


def _in_chunks(fn: Any, n: int, size: int = 65536) -> np.ndarray:
    return np.concatenate([fn(slice(i, min(i + size, n))) for i in range(0, n, size)])


def model_based_injection(system: System, encoder: MLP, decoder: MLP, z: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``dT/dx(xhat) (f(xhat, u) - f(xhat, 0))`` at ``xhat = T*(z)``, per row (torch JVP, exact ``f``).

    The same term the ``inject`` observer builds symbolically in CasADi.
    """
    dtype = encoder.layers[0].weight.dtype
    device = encoder.layers[0].weight.device

    def chunk(rows: slice) -> np.ndarray:
        with torch.no_grad():
            xhat = decoder(torch.as_tensor(z[rows], dtype=dtype, device=device))
            xh = xhat.double().cpu().numpy()
            df = system.f_batch(xh, u[rows]) - system.f_batch(xh)
            _, jv = torch.func.jvp(encoder, (xhat,), (torch.as_tensor(df, dtype=dtype, device=device),))
        return jv.double().cpu().numpy()

    return _in_chunks(chunk, len(z))


def phase2_data(system: System, cfg: Any, dt: float, seed: int) -> kdata.Phase2Data:
    return kdata.phase2(system, cfg.n_traj, cfg.n_signals, window=cfg.window, T=cfg.T, dt=dt, seed=seed + 101,
                        kinds=cfg.kinds)


def obs_residuals(system: System, design: Design, encoder: MLP, decoder: MLP, x: np.ndarray, y: np.ndarray,
                  u: np.ndarray, xdot: np.ndarray, on_inject: bool) -> tuple[np.ndarray, np.ndarray]:
    """The latents ``z = T(x)`` and what the obs injection must supply, ``dT/dx xdot - A z - B y``
    (minus the model-based term when ``on_inject``), per row of the flat samples."""
    dtype, device = encoder.layers[0].weight.dtype, encoder.layers[0].weight.device

    def targets(rows: slice) -> np.ndarray:
        with torch.no_grad():
            xt = torch.as_tensor(x[rows], dtype=dtype, device=device)
            z, zdot = torch.func.jvp(encoder, (xt,), (torch.as_tensor(xdot[rows], dtype=dtype, device=device),))
        return np.hstack([z.double().cpu().numpy(), zdot.double().cpu().numpy()])

    zz = _in_chunks(targets, len(x))
    z, zdot_true = zz[:, :design.nz], zz[:, design.nz:]
    residual = zdot_true - z @ design.A.T - y @ design.B.T
    if on_inject:
        residual = residual - model_based_injection(system, encoder, decoder, z, u)
    return z, residual


def make_obs_net(system: System, design: Design, config: Any, z: np.ndarray, u: np.ndarray,
                 residual: np.ndarray) -> ObsInjection:
    """A new float32 obs injection, normalised for the latents ``z`` and the targets ``residual``."""
    net = ObsInjection(design.nz, system.nu, config.hidden, config.proj, config.gain_hidden).to(torch.float32)
    # the gain MLP sees [z; l]: normalise z by its statistics, l is O(1); outputs are in residual units
    in_mean = np.r_[z.mean(0), np.zeros(config.proj)]
    in_std = np.r_[z.std(0), np.ones(config.proj)]
    u_std = max(float(u.std()), 1e-3)
    out_std = np.repeat(residual.std(0) / u_std, system.nu)
    net.gain_net.set_normalisation(in_mean, in_std, np.zeros(design.nz * system.nu), out_std)
    return net


def train_obs(system: System, design: Design, base: Model | None, config: ObsConfig, *, dt: float, seed: int,
              device: str, progress: bool, workdir: Path | None, resume: bool) -> Trained:
    """The training hook of the ``obs`` variant: HyperKKL_obs (Algorithm 2) on a frozen Phase-1 model."""
    base = check_phase2("obs", base, config, ObsConfig)
    dtype = torch.float32
    encoder, decoder = base_nets(base, dtype, device)
    p2 = phase2_data(system, config.data, dt, seed)
    x, y, u, xdot = (_flat(p2, k) for k in ("x", "y", "u", "xdot"))
    z, residual = obs_residuals(system, design, encoder, decoder, x, y, u, xdot, config.model_based_injection)
    scale = torch.as_tensor(residual.std(0) + 1e-8, dtype=dtype, device=device)
    net = make_obs_net(system, design, config, z, u, residual).to(device)
    dataset = Phase2Dataset(p2, {"z": z, "r": residual}, keys=("u", "w"), dtype=dtype, device=device)

    def loss_fn(batch: dict[str, Tensor], epoch: int) -> tuple[Tensor, dict[str, float]]:
        return (((net(batch["z"], batch["w"], batch["u"]) - batch["r"]) / scale) ** 2).mean(), {}

    baseline = float(((residual / (residual.std(0) + 1e-8)) ** 2).mean())
    result = fit(list(net.parameters()), loss_fn, dataset, config.loop, name="obs", seed=seed, progress=progress,
                 resume=resume, checkpoint=workdir / "obs.ckpt.npz" if workdir else None)
    net = net.cpu().double()
    arrays = {**base.arrays, **net.to_arrays()}
    maps = base.spec.architecture
    spec = ObsModelSpec(maps.encoder, maps.decoder, net.spec, bool(config.model_based_injection))
    training = {"config": config, "data": {"trajectories": int(p2.x.shape[0]), "samples": p2.n_samples,
                                           "dropped": len(p2.dropped)},
                "obs": result.summary(), "loss_without_injection": baseline}
    return Trained(arrays, spec, design, training, {"obs": result.history}, config.data.window,
                   base.spec.measurement_std, base.spec.domain)


def dyn_scales(system: System, base: Model, p2: kdata.Phase2Data, dtype: torch.dtype,
               device: str) -> tuple[Tensor, Tensor]:
    """The reconstruction and PDE scales of the dyn losses: the data's state std, the encoder's output std."""
    return (torch.as_tensor(p2.x.reshape(-1, system.nx).std(0), dtype=dtype, device=device),
            torch.tensor(np.array(base.arrays["encoder/out_std"]), dtype=dtype, device=device))


def make_dyn_loss(design: Design, nu_pde: float, encoder: MLP, decoder: MLP, hyper: LoRAHyperNet, factors_of: Any,
                  x_scale: Tensor, z_scale: Tensor) -> Any:
    """The HyperKKL_dyn loss ``loss(x, xdot, y, context, context_dot) -> (loss, parts)`` on flat rows.

    ``factors_of(context)`` gives the LoRA factors (``hyper`` for a window, ``hyper.factors_of_hidden``
    for a GRU state). The PDE residual takes the time derivative of the modulated encoder along the
    state and the context, ``dT/dt = dT/dx xdot + dT/dc cdot`` (one JVP), so that ``T(x(t), c(t))``
    follows ``A z + B y`` while the input moves the context; the decoder runs outside the JVP.
    Reconstruction and residual are scaled by ``x_scale`` and ``z_scale`` (:func:`dyn_scales`).
    """
    dtype, device = encoder.layers[0].weight.dtype, encoder.layers[0].weight.device
    n_enc = len(encoder.layers)
    A = torch.tensor(design.A, dtype=dtype, device=device)
    B = torch.tensor(design.B, dtype=dtype, device=device)

    def encode(x: Tensor, context: Tensor) -> tuple[Tensor, list]:
        factors = factors_of(context)
        return mlp_forward_lora(encoder, x, factors[:n_enc], hyper.scale), factors[n_enc:]

    def loss(x: Tensor, xdot: Tensor, y: Tensor, context: Tensor, context_dot: Tensor
             ) -> tuple[Tensor, dict[str, float]]:
        (z, decoder_factors), (dz, _) = torch.func.jvp(encode, (x, context), (xdot, context_dot))
        xhat = mlp_forward_lora(decoder, z, decoder_factors, hyper.scale)
        res = dz - z @ A.T - y @ B.T
        recon = (((xhat - x) / x_scale) ** 2).mean()
        pde = ((res / z_scale) ** 2).mean()
        return recon + nu_pde * pde, {"recon": recon.item(), "pde": pde.item()}

    return loss


def train_dyn(system: System, design: Design, base: Model | None, config: DynConfig, *, dt: float, seed: int,
              device: str, progress: bool, workdir: Path | None, resume: bool) -> Trained:
    """The training hook of the ``dyn`` variant: HyperKKL_dyn (Algorithm 3) on a frozen Phase-1 model."""
    base = check_phase2("dyn", base, config, DynConfig)
    dtype = torch.float32
    encoder, decoder = base_nets(base, dtype, device)
    p2 = phase2_data(system, config.data, dt, seed)
    targets = lora_target_shapes(encoder.spec, decoder.spec)
    hyper = LoRAHyperNet(targets, system.nu, config.hidden, config.embed, config.backbone, config.rank,
                         config.scale_init).to(dtype=dtype, device=device)
    dyn_loss = make_dyn_loss(design, config.nu_pde, encoder, decoder, hyper, hyper,
                             *dyn_scales(system, base, p2, dtype, device))

    def loss_fn(batch: dict[str, Tensor], epoch: int) -> tuple[Tensor, dict[str, float]]:
        wdot = (batch["w_next"] - batch["w"]) / dt
        return dyn_loss(batch["x"], batch["xdot"], batch["y"], batch["w"], wdot)

    result = fit(list(hyper.parameters()), loss_fn, Phase2Dataset(p2, dtype=dtype, device=device), config.loop,
                 name="dyn", seed=seed, progress=progress, resume=resume,
                 checkpoint=workdir / "dyn.ckpt.npz" if workdir else None)
    hyper = hyper.cpu().double()
    arrays = {**base.arrays, **hyper.to_arrays()}
    base_arch = base.spec.architecture
    spec = DynModelSpec(base_arch.encoder, base_arch.decoder, hyper.spec, system.nu)
    training = {"config": config, "data": {"trajectories": int(p2.x.shape[0]), "samples": p2.n_samples,
                                           "dropped": len(p2.dropped)}, "dyn": result.summary()}
    return Trained(arrays, spec, design, training, {"dyn": result.history}, config.data.window,
                   base.spec.measurement_std, base.spec.domain)


def train_curriculum(system: System, design: Design, base: Model | None, config: CurriculumConfig, *, dt: float,
                     seed: int, device: str, progress: bool, workdir: Path | None, resume: bool) -> Trained:
    """The training hook of the ``curriculum`` baseline: T and T* fine-tuned on staged driven data."""
    base = check_phase2("curriculum", base, config, CurriculumConfig)
    dtype = torch_dtype("float32")
    encoder, decoder = base_nets(base, dtype, device)
    A = torch.tensor(design.A, dtype=dtype, device=device)
    B = torch.tensor(design.B, dtype=dtype, device=device)
    z_scale = torch.tensor(base.arrays["encoder/out_std"], dtype=dtype, device=device)
    x_scale = torch.tensor(base.arrays["decoder/out_std"], dtype=dtype, device=device)
    rng = np.random.default_rng(seed + 7)
    histories, summaries = {}, {}
    for s, kinds in enumerate(config.stages):
        signals = [sig.in_box(sig.sample(kinds[j % len(kinds)], rng, "train", nu=system.nu), system.u_box)
                   for j in range(config.n_signals_per_stage * len(kinds))]
        lab = kdata.driven_labels(system, design, signals, config.n_traj, seed + 11 * s, t_keep=config.t_keep, dt=dt)
        # the PDE term keeps the autonomous field f(x, 0): a static map is fine-tuned, run as autonomous
        f0 = system.f_batch(lab.x)
        enc_data = ArrayDataset({"x": lab.x, "z": lab.z, "y": lab.y, "f": f0}, dtype=dtype, device=device)
        encoder.requires_grad_(True)

        def enc_loss(batch: dict[str, Tensor], epoch: int) -> tuple[Tensor, dict[str, float]]:
            z, res = pde_residual(encoder, batch["x"], batch["f"], batch["y"], A, B)
            mse = (((z - batch["z"]) / z_scale) ** 2).mean()
            pde = ((res / z_scale) ** 2).mean()
            return mse + config.nu_pde * pde, {"mse": mse.item(), "pde": pde.item()}

        enc_fit = fit(list(encoder.parameters()), enc_loss, enc_data, config.loop, name=f"curriculum/{s}/encoder",
                      seed=seed + s, progress=progress, resume=resume,
                      checkpoint=workdir / f"curriculum{s}_encoder.ckpt.npz" if workdir else None)
        encoder.requires_grad_(False)
        with torch.no_grad():
            z_all = encoder(torch.as_tensor(lab.x, dtype=dtype, device=device))
        decoder.requires_grad_(True)
        dec_data = ArrayDataset({"x": lab.x, "z": z_all.cpu().numpy()}, dtype=dtype, device=device)

        def dec_loss(batch: dict[str, Tensor], epoch: int) -> tuple[Tensor, dict[str, float]]:
            return (((decoder(batch["z"]) - batch["x"]) / x_scale) ** 2).mean(), {}

        dec_fit = fit(list(decoder.parameters()), dec_loss, dec_data, config.loop, name=f"curriculum/{s}/decoder",
                      seed=seed + s, progress=progress, resume=resume,
                      checkpoint=workdir / f"curriculum{s}_decoder.ckpt.npz" if workdir else None)
        decoder.requires_grad_(False)
        histories[f"stage{s}/encoder"] = enc_fit.history
        histories[f"stage{s}/decoder"] = dec_fit.history
        summaries[f"stage{s}"] = {"kinds": list(kinds), "samples": len(lab.x), "encoder": enc_fit.summary(),
                                  "decoder": dec_fit.summary()}
    encoder, decoder = encoder.cpu().double(), decoder.cpu().double()
    arrays = {**encoder.to_arrays(ENCODER), **decoder.to_arrays(DECODER)}
    with torch.no_grad():                           # the domain of the last (widest) stage's data
        domain = Domain.of(lab.x, encoder(torch.as_tensor(lab.x, dtype=torch.float64)).numpy())
    return Trained(arrays, MapsSpec(encoder.spec, decoder.spec), design, {"config": config, "stages": summaries},
                   histories, 1, base.spec.measurement_std, domain)


register("obs", train_obs, ObsConfig)
register("dyn", train_dyn, DynConfig)
register("curriculum", train_curriculum, CurriculumConfig)
