"""Training side of kklcasadi (needs torch: ``pip install kklcasadi[train]``).

:func:`train_observer` trains one observer variant and writes its model directory
(``weights.npz`` + ``card.json``), readable without torch by :func:`kklcasadi.load_observer`.
"""

from __future__ import annotations

import json
import os
import time
from contextlib import contextmanager
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

try:
    import torch
except ImportError as exc:                              # a deploy-only install: say how to get training
    raise ModuleNotFoundError("kklcasadi.train needs torch, which is not installed; install the training extra: "
                              "pip install 'kklcasadi[train]'", name="torch") from exc

from .. import provenance
from ..model import variants
from ..model.card import make_card
from ..model.digest import read_json_object
from ..model.files import derive_model, load_model, save_model
from ..plant import systems
from ..plant.design import Design
from ..plant.systems import System
from ..validation import Text, error, positive_int
from ..writes import claim, write_file
from . import bank, phase1, phase2, stream  # noqa: F401  (each registers its trainers: .registry)
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
from .registry import trainer
from .result import Trained

__all__ = ["train_observer", "default_config", "with_epochs", "config_field", "has_field", "with_field", "LoopConfig",
           "Phase1Config", "Phase2DataConfig", "ObsConfig", "DynConfig", "CurriculumConfig", "ObsStreamConfig",
           "DynStreamConfig", "Trained", "METHODS", "RUN_RECORD", "TRAIN_THREADS"]

#: Methods :func:`train_observer` makes (read from :mod:`kklcasadi.model.variants`).
METHODS = variants.trainable()
#: torch CPU threads of a training unless told (``threads``). One: the networks are small (the ``bank`` decoder
#: 16-256-256-256-3 at batch 1024), and where the cores are shared torch's threads wait on each other at every
#: operation: the damped 3-state plant's decoder fit ran 5 958 samples/s with torch's default of 2 threads on the
#: 2 shared cores (load 5-6) and 41 335 with one (load 6), the whole one command 1541 s wall / 799 s CPU against
#: 273 s / 141 s (docs/notes/speed.md, "A first observer for a new plant"). A quiet machine with many cores may
#: gain from more (``--threads``).
TRAIN_THREADS = 1


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


def _history_plot(histories: dict[str, dict], stamp: provenance.Stamp) -> bytes:
    """PNG of the training histories: every recorded loss of every stage against the epoch."""
    import io

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
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110, metadata=provenance.png_metadata(stamp))
    plt.close(fig)
    return buffer.getvalue()


#: What a training's checkpoints belong to, in its checkpoints' directory (``OUT/.train``).
RUN_RECORD = "run.json"


def _checkpoints_of(workdir: Path, record: dict, resume: bool) -> None:
    """Bind the checkpoints in ``workdir`` to this training: with ``resume``, those of a training of the same plant
    (fingerprint), method, configuration, design, sample time, seed and base model only; without, none (old ones
    are removed, so that an interrupted run never resumes another's later stage)."""
    path = workdir / RUN_RECORD
    ours = json.loads(json.dumps(record))
    checkpoints = sorted(workdir.glob("*.ckpt.npz"))
    if resume and checkpoints:
        stored = read_json_object(path, "Train again without --resume.") if path.is_file() else None
        if stored is None:
            raise error("resume", f"checkpoints in {workdir} with the record of their training ({RUN_RECORD})",
                        Text("checkpoints without one (an older kklcasadi wrote them)"),
                        "Train again without --resume.")
        differ = [key for key in ours if stored.get(key) != ours[key]]
        if differ:
            names = {"plant": "plant (fingerprint)", "config": "configuration", "base": "base model"}
            raise error("resume", f"the checkpoints of this training in {workdir}",
                        Text(f"those of another: its {', '.join(names.get(k, k) for k in differ)} "
                             f"differ{'' if len(differ) > 1 else 's'}"),
                        "Resume with the settings it was started with, or train again without --resume (the "
                        "checkpoints are then replaced).")
    elif not resume:
        for checkpoint in checkpoints:
            checkpoint.unlink()
    write_file(path, json.dumps(ours, indent=1) + "\n", overwrite=True, argument="out_dir")


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
        Continue interrupted stages from their checkpoints in ``out_dir/.train``: only those of a training of the
        same plant (fingerprint), method, configuration, design, sample time, seed and base model; never a
        finished model (that takes ``overwrite``). Without it, old checkpoints there are removed.
    threads : int, optional
        CPU threads for torch while it trains (``torch.set_num_threads``; the count before is restored
        afterwards); default :data:`TRAIN_THREADS` (1: oversubscribed threads slowed the decoder fit 6.7x on
        2 shared cores).

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
    if (out / "card.json").exists() and not overwrite:
        raise FileExistsError(f"{out} already holds a model; pass overwrite=True (CLI: --overwrite) to replace it"
                              + (" (resume continues an unfinished training, not a finished model)" if resume else ""))
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
    if not variant.trains:            # made from its base without training (inject)
        return derive_model(base_model.path, out, method, overwrite=overwrite)
    if config is None:
        config = default_config(plant.name, method)
    if epochs is not None:
        config = with_epochs(config, epochs)
    threads = TRAIN_THREADS if threads is None else positive_int(threads, "threads")
    with _torch_threads(threads):
        return _train(plant, method, out, variant, base_model, config, design, dt=dt, seed=seed, device=device,
                      resume=resume, overwrite=overwrite, progress=progress)


@contextmanager
def _torch_threads(threads: int) -> Iterator[None]:
    """torch's CPU threads set to ``threads`` inside, restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _train(plant: System, method: str, out: Path, variant: Any, base_model: Any, config: Any, design: Design | None,
           *, dt: float, seed: int, device: str, resume: bool, overwrite: bool, progress: bool) -> Path:
    """:func:`train_observer` after its checks, with torch's threads set."""
    if base_model is not None:
        design = Design(base_model.A, base_model.B)
    design = design or (Design.paper(plant) if plant.paper_design else Design.default(plant))
    # the checkpoints' directory, held by this process while it trains: a second training to one --out stops at once
    with claim(out / ".train", "out_dir") as workdir:
        base_sha = None if base_model is None else base_model.card["weights_sha256"]
        _checkpoints_of(workdir, {"plant": plant.fingerprint, "method": method, "config": _jsonable(config),
                                  "design": {"A": design.A.tolist(), "B": design.B.tolist()}, "dt": float(dt),
                                  "seed": seed, "base": base_sha}, resume)
        if progress:
            print(f"training {method} for {plant.name!r} at dt = {dt:g} s into {out}", flush=True)
        torch.manual_seed(seed)          # network initialisation; the stages reseed their own shuffles
        t0 = time.perf_counter()
        trained: Trained = trainer(method).hook(plant, design, base_model, config, dt=dt, seed=seed, device=device,
                                                progress=progress, workdir=workdir, resume=resume)
        training = {**_jsonable(trained.training), "seed": seed, "wall_time_s": round(time.perf_counter() - t0, 1),
                    "device": device, "threads": torch.get_num_threads()}
        nominal = plant.at(plant.param_nominal) if plant.n_params else plant    # the plant the observer runs with
        card = make_card(nominal, trained.design, method, trained.spec, dt=dt, window=trained.window,
                         training=training, measurement_std=trained.measurement_std, domain=trained.domain,
                         base=None if base_model is None else _base_reference(out, base_model),
                         coverage=trained.coverage,
                         process_std=(config_field(config, "process_std") if trained.process_std is None
                                      else trained.process_std),
                         monitor=trained.monitor, fit_families=trained.fit_families)
        stamp = provenance.stamp(seeds={"training": seed})    # the command line that trained it, the commit, versions
        extra = {} if not trained.histories else {
            "history.json": json.dumps(provenance.json_record(_jsonable(trained.histories), stamp)).encode(),
            "history.png": _history_plot(trained.histories, stamp)}
        return save_model(out, trained.arrays, {**card, provenance.KEY: stamp.to_json()}, overwrite=overwrite,
                          extra=extra)
