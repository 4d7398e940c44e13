"""Training side of kklcasadi (needs torch: ``pip install kklcasadi[train]``).

:func:`train_observer` trains one observer variant and writes its model directory
(``weights.npz`` + ``card.json``), readable without torch by :func:`kklcasadi.load_observer`.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

try:
    import torch
except ImportError as exc:                              # a deploy-only install: say how to get training
    raise ModuleNotFoundError("kklcasadi.train needs torch, which is not installed; install the training extra: "
                              "pip install 'kklcasadi[train]'", name="torch") from exc

from .. import provenance
from ..model import variants
from ..model.card import make_card
from ..model.files import derive_model, load_model, save_model
from ..plant import systems
from ..plant.design import Design
from ..plant.systems import System
from ..validation import Text, error, positive_int
from .config import (
    CurriculumConfig,
    DynConfig,
    DynStreamConfig,
    LoopConfig,
    ObsConfig,
    ObsStreamConfig,
    Phase1Config,
    Phase2DataConfig,
    config_field,
    default_config,
    has_field,
    with_epochs,
    with_field,
)
from .result import Trained

__all__ = ["train_observer", "default_config", "with_epochs", "config_field", "has_field", "with_field", "LoopConfig",
           "Phase1Config", "Phase2DataConfig", "ObsConfig", "DynConfig", "CurriculumConfig", "ObsStreamConfig",
           "DynStreamConfig", "Trained", "METHODS"]

#: Methods :func:`train_observer` makes (read from :mod:`kklcasadi.model.variants`).
METHODS = variants.trainable()


def _jsonable(value: Any) -> Any:
    if is_dataclass(value) and hasattr(value, "to_card"):          # a record of its own (the rig's envelope)
        return _jsonable(value.to_card())
    if is_dataclass(value):
        return {f.name: _jsonable(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def _base_reference(out_dir: Path, base: Any) -> dict:
    return {"path": os.path.relpath(base.path, out_dir.resolve()), "weights_sha256": base.card["weights_sha256"]}


def _load_base(base: str | Path | None, out: Path, plant: System, method: str) -> Any:
    """The model ``method`` builds on (default ``out/../autonomous`` when it needs one), checked."""
    variant = variants.get(method)
    if base is None and not variant.needs_base:
        return None
    base_dir = Path(base) if base is not None else out.parent / "autonomous"
    model = load_model(base_dir)
    if model.spec.system.name != plant.name:
        raise error("base", f"a model for system {plant.name!r}", f"{base_dir} (system {model.spec.system.name!r})")
    return model


def _history_plot(histories: dict[str, dict], path: Path, stamp: provenance.Stamp) -> None:
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
    fig.savefig(path, dpi=110, metadata=provenance.png_metadata(stamp))
    plt.close(fig)


def train_observer(system: System | str, method: str = "autonomous", out_dir: str | Path = "models/observer", *,
                   config: Any = None, base: str | Path | None = None, design: Design | None = None,
                   dt: float = 0.05, seed: int = 0, device: str = "cpu", resume: bool = False,
                   overwrite: bool = False, progress: bool = True, threads: int | None = None,
                   epochs: int | None = None) -> Path:
    """Train one observer variant and write its model directory.

    Parameters
    ----------
    system : System or str
        The plant (or a registered name). A plant with parameters (``bank`` only) is a family: each
        training run draws its parameters from the box, and the card records the nominal plant (the
        one the observer runs with) and, in ``training.runs.params``, the box and the draw.
    method : str
        A key of :data:`kklcasadi.model.variants.VARIANTS` (see :data:`METHODS`). ``autonomous``: Phase 1
        (with ``base``: keep the base's encoder and train only a new decoder, e.g. for another noise
        level). The others start from the Phase-1 model ``base``, default ``out_dir/../autonomous``,
        which is trained first when it does not exist yet; ``inject`` trains nothing more.
    out_dir : path
        The model directory to write.
    config : dataclass, optional
        :func:`default_config` of the method unless given.
    epochs : int, optional
        Set the epochs of every optimisation stage of ``config`` (and of a Phase 1 trained on the
        way), and nothing else (:func:`with_epochs`).
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
        raise error("system", "a kklcasadi.System or a registered name", type(system).__name__, kind=TypeError)
    if method not in METHODS:
        raise error("method", f"one of {list(METHODS)}", method)
    if device not in ("cpu", "cuda"):
        raise error("device", "'cpu' or 'cuda'", device)
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("device: 'cuda' was asked for but torch sees no CUDA device; use device='cpu'.")
    out = Path(out_dir)
    if out.is_file():
        raise error("out_dir", "a directory", str(out), "Give a directory path.")
    if (out / "card.json").exists() and not overwrite and not resume:
        raise FileExistsError(f"{out} already holds a model; pass overwrite=True (CLI: --overwrite) to replace it")
    variant = variants.get(method)
    if plant.n_params and method != "bank":
        raise error("system", f"a plant without parameters for method {method!r} (only 'bank' trains over a family "
                    "of plants)", Text(f"plant {plant.name!r} with parameters {list(plant.param_names)}"))
    if variant.needs_base and base is None and not (out.parent / "autonomous" / "card.json").exists():
        if progress:
            print(f"training the Phase-1 model {out.parent / 'autonomous'} first ({method} builds on it)")
        train_observer(plant, "autonomous", out.parent / "autonomous", design=design, dt=dt, seed=seed, device=device,
                       progress=progress, threads=threads, epochs=epochs)
    base_model = _load_base(base, out, plant, method)
    if variant.trainer is None:            # made from its base without training (inject)
        return derive_model(base_model.path, out, method, overwrite=overwrite)
    if config is None:
        config = default_config(plant.name, method)
    if epochs is not None:
        config = with_epochs(config, epochs)
    if threads is not None:
        torch.set_num_threads(positive_int(threads, "threads"))
    if base_model is not None:
        design = Design(base_model.A, base_model.B)
    design = design or (Design.paper(plant) if plant.paper_design else Design.default(plant))
    workdir = out / ".train"
    if progress:
        print(f"training {method} for {plant.name!r} at dt = {dt:g} s into {out}", flush=True)
    torch.manual_seed(seed)          # network initialisation; the stages reseed their own shuffles
    t0 = time.perf_counter()
    trained: Trained = variant.load_trainer()(plant, design, base_model, config, dt=dt, seed=seed, device=device,
                                              progress=progress, workdir=workdir, resume=resume)
    training = {**_jsonable(trained.training), "seed": seed, "wall_time_s": round(time.perf_counter() - t0, 1),
                "device": device}
    nominal = plant.at(plant.param_nominal) if plant.n_params else plant    # the plant the observer runs with
    card = make_card(nominal, trained.design, method, trained.spec, dt=dt, window=trained.window,
                     training=training, measurement_std=trained.measurement_std, domain=trained.domain,
                     base=None if base_model is None else _base_reference(out, base_model),
                     coverage=trained.coverage,
                     process_std=(config_field(config, "process_std") if trained.process_std is None
                                  else trained.process_std),
                     monitor=trained.monitor, fit_families=trained.fit_families)
    stamp = provenance.stamp(seeds={"training": seed})    # the command line that trained it, the commit, versions
    path = save_model(out, trained.arrays, {**card, provenance.KEY: stamp.to_json()}, overwrite=overwrite or resume)
    if trained.histories:
        (out / "history.json").write_text(json.dumps(provenance.json_record(_jsonable(trained.histories), stamp)))
        _history_plot(trained.histories, out / "history.png", stamp)
    return path
