"""Training side of kklcasadi (needs torch: ``pip install kklcasadi[train]``).

:func:`train_observer` trains one observer variant and writes its model directory
(``weights.npz`` + ``card.json``), readable without torch by :func:`kklcasadi.load_observer`.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, is_dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .. import __version__, systems
from ..design import Design
from ..modelfile import load_model, save_model
from ..observer import make_inject_model
from ..systems import System
from ..torch_nets import MLP
from .config import (CurriculumConfig, DynConfig, LoopConfig, ObsConfig, Phase1Config, Phase2DataConfig,
                     default_config)
from .phase1 import train_phase1

__all__ = ["train_observer", "default_config", "LoopConfig", "Phase1Config", "Phase2DataConfig", "ObsConfig",
           "DynConfig", "CurriculumConfig", "METHODS"]

#: Methods :func:`train_observer` accepts (``inject`` needs no training beyond Phase 1).
METHODS = ("autonomous", "obs", "dyn", "curriculum", "inject")


def _jsonable(value: Any) -> Any:
    if is_dataclass(value):
        return _jsonable(asdict(value))
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def _card(system: System, design: Design, method: str, dt: float, window: int, architecture: dict,
          training: dict, *, base: dict | None = None, measurement_std: float = 0.0, **extra: Any) -> dict:
    return {"method": method, "system": {"name": system.name, "nx": system.nx, "nu": system.nu, "ny": system.ny},
            "design": {"A": design.A.tolist(), "B": design.B.tolist()}, "dt": dt, "window": window,
            "architecture": architecture, "base": base, "noise": {"measurement_std": measurement_std},
            "training": _jsonable(training), **extra}


def _base_reference(out_dir: Path, base_dir: Path) -> dict:
    model = load_model(base_dir)
    return {"path": os.path.relpath(base_dir.resolve(), out_dir.resolve()),
            "weights_sha256": model.card["weights_sha256"]}


def _phase1_base(base: str | Path | None, out: Path, plant: System) -> tuple[Path, Any]:
    """The Phase-1 model a Phase-2 method starts from (default ``out/../autonomous``), checked."""
    base_dir = Path(base) if base is not None else out.parent / "autonomous"
    model = load_model(base_dir)
    if model.card["system"]["name"] != plant.name:
        raise ValueError(f"base model {base_dir} is for system {model.card['system']['name']!r}, not {plant.name!r}")
    return base_dir, model


def _history_plot(histories: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(histories), figsize=(5 * len(histories), 3.5), squeeze=False)
    for ax, (name, hist) in zip(axes[0], histories.items()):
        for key, values in hist.items():
            ax.semilogy(np.arange(1, len(values) + 1), values, label=key)
        ax.set_title(name)
        ax.set_xlabel("epoch")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def train_observer(system: System | str, method: str = "autonomous", out_dir: str | Path = "models/observer", *,
                   config: Any = None, base: str | Path | None = None, design: Design | None = None,
                   dt: float = 0.05, seed: int = 0, device: str = "cpu", resume: bool = False,
                   overwrite: bool = False, progress: bool = True, threads: int | None = None) -> Path:
    """Train one observer variant and write its model directory.

    Parameters
    ----------
    system : System or str
        The plant (or a registered name).
    method : {"autonomous", "obs", "dyn", "curriculum", "inject"}
        ``autonomous``: Phase 1 (with ``base``: keep the base's encoder and train only a new decoder,
        e.g. for another noise level). ``obs``/``dyn``/``curriculum``/``inject`` start from the
        Phase-1 model ``base`` (default ``out_dir/../autonomous``); ``inject`` only writes its card.
    out_dir : path
        The model directory to write.
    config : dataclass, optional
        :func:`default_config` of the method unless given.
    dt : float
        Sample period of the observer.
    device : {"cpu", "cuda"}
        ``"cuda"`` if available (training only; the model files are device-free float64).
    resume : bool
        Continue interrupted stages from their checkpoints in ``out_dir/.train``.
    threads : int, optional
        CPU threads for torch (``torch.set_num_threads``). On a shared or small machine use 1 per
        training process: oversubscribed threads slowed small matrix products 40x here.

    Returns
    -------
    Path
        ``out_dir``.
    """
    plant = systems.get(system) if isinstance(system, str) else system
    if not isinstance(plant, System):
        raise TypeError(f"system must be a kklcasadi.System or a registered name, got {type(system).__name__}")
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; known methods: {', '.join(METHODS)}")
    if device not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'cpu' or 'cuda', got {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("device='cuda' was asked for but torch sees no CUDA device; use device='cpu'")
    out = Path(out_dir)
    if out.is_file():
        raise ValueError(f"out_dir {out} is a file; give a directory")
    if (out / "card.json").exists() and not overwrite and not resume:
        raise FileExistsError(f"{out} already holds a model; pass overwrite=True (CLI: --overwrite) to replace it")
    if method == "inject":
        base_dir, _ = _phase1_base(base, out, plant)
        return make_inject_model(base_dir, out, overwrite=overwrite)
    design = design or Design.default(plant)
    if config is None:
        config = default_config(plant.name, "autonomous" if method == "autonomous" else method)
    if threads is not None:
        if not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads must be a positive integer, got {threads!r}")
        torch.set_num_threads(threads)
    workdir = out / ".train"
    torch.manual_seed(seed)          # network initialisation; the stages reseed their own shuffles
    t0 = time.perf_counter()
    if method == "autonomous":
        if not isinstance(config, Phase1Config):
            raise TypeError(f"config for 'autonomous' must be a Phase1Config, got {type(config).__name__}")
        encoder, base_ref = None, None
        if base is not None:       # keep the base's encoder, train a new decoder (e.g. for a noise level)
            base_model = load_model(base)
            design = Design(base_model.A, base_model.B)
            encoder = MLP.from_arrays(base_model.arrays, "encoder", base_model.card["architecture"]["encoder"])
            base_ref = _base_reference(out, Path(base))
        result = train_phase1(plant, design, config, dt=dt, seed=seed, device=device, progress=progress,
                              workdir=workdir, resume=resume, encoder=encoder)
        arrays = {**result.encoder.to_arrays("encoder"), **result.decoder.to_arrays("decoder")}
        fits = {"encoder": result.encoder_fit, "decoder": result.decoder_fit}
        histories = {k: f.history for k, f in fits.items() if f is not None}
        training = {"config": config, "seed": seed, "data": {"labelled": result.n_labelled, "pde": result.n_pde},
                    **{k: (f.summary() if f is not None else "kept from the base model") for k, f in fits.items()},
                    "wall_time_s": round(time.perf_counter() - t0, 1), "device": device}
        card = _card(plant, design, "autonomous", dt, 1,
                     {"encoder": result.encoder.architecture(), "decoder": result.decoder.architecture()},
                     training, base=base_ref, measurement_std=config.measurement_std)
    else:
        from .phase2 import train_method

        base_dir, base_model = _phase1_base(base, out, plant)
        design = Design(base_model.A, base_model.B)
        arrays, architecture, training, histories, extra = train_method(
            plant, design, base_model, method, config, dt=dt, seed=seed, device=device, progress=progress,
            workdir=workdir, resume=resume)
        training = {**training, "seed": seed, "wall_time_s": round(time.perf_counter() - t0, 1), "device": device}
        window = architecture.pop("_window", 1)
        card = _card(plant, design, method, dt, window, architecture, training,
                     base=_base_reference(out, base_dir),
                     measurement_std=base_model.card["noise"]["measurement_std"], **extra)
    path = save_model(out, arrays, card, overwrite=overwrite or resume)
    if histories:
        (workdir).mkdir(parents=True, exist_ok=True)
        (out / "history.json").write_text(json.dumps(_jsonable(histories)))
        _history_plot(histories, out / "history.png")
    return path
