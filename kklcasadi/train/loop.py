"""The optimisation loop shared by every training stage.

Seeded mini-batches, Adam with gradient clipping, a validation split whose best epoch is kept,
a clear stop on a non-finite loss, a per-epoch progress bar, and a checkpoint after every epoch
(``.npz``, no pickle) from which an interrupted stage resumes.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Protocol

import numpy as np
import torch
from tqdm.auto import tqdm

from ..validation import Text, error, one_of
from .config import LoopConfig

__all__ = ["Dataset", "ArrayDataset", "FitResult", "fit", "torch_dtype"]

#: Whether this torch has the fused Adam's CPU kernel (torch 2.4 on).
FUSED_CPU_ADAM = tuple(int(part) for part in torch.__version__.split("+")[0].split(".")[:2]) >= (2, 4)

Tensor = torch.Tensor
LossFn = Callable[[Mapping[str, Tensor], int], tuple[Tensor, dict[str, float]]]


def torch_dtype(name: str) -> torch.dtype:
    """``"float32"`` or ``"float64"`` as a torch dtype."""
    return getattr(torch, one_of(name, "dtype", ("float32", "float64")))


class Dataset(Protocol):
    """Indexable training data: ``len(data)`` samples, ``data.get(index) -> {name: Tensor}``."""

    def __len__(self) -> int: ...

    def get(self, index: np.ndarray) -> dict[str, Tensor]: ...


class ArrayDataset:
    """Samples stored as equally long arrays, moved to ``device`` as ``dtype`` tensors."""

    def __init__(self, arrays: Mapping[str, np.ndarray], *, dtype: torch.dtype = torch.float64,
                 device: str | torch.device = "cpu") -> None:
        lengths = {k: len(v) for k, v in arrays.items()}
        if len(set(lengths.values())) != 1:
            raise error("arrays", "arrays with the same number of samples", Text(f"lengths {lengths}"))
        self.tensors = {k: torch.as_tensor(np.asarray(v), dtype=dtype, device=device) for k, v in arrays.items()}
        self.n = next(iter(lengths.values()))

    def __len__(self) -> int:
        return self.n

    def get(self, index: np.ndarray) -> dict[str, Tensor]:
        idx = torch.as_tensor(index, device=next(iter(self.tensors.values())).device)
        return {k: v[idx] for k, v in self.tensors.items()}


@dataclass(frozen=True)
class FitResult:
    """What a stage did: per-epoch history ``{name: [values]}``, best validation loss and epoch, wall time.

    ``best_val`` is scored on the epochs' validation samples (``LoopConfig.val_samples`` of the
    ``held_out``); ``val_all`` is the kept parameters' loss on all ``held_out`` samples, comparable
    across settings, scored once after the epochs in ``val_all_seconds`` (0 when the epochs scored
    all of them). ``seconds`` is the epochs' time (training and their validation), in which
    ``trained_samples`` were trained on.
    """

    history: dict
    best_val: float
    best_epoch: int
    seconds: float
    trained_samples: int
    held_out: int
    val_all: float
    val_all_seconds: float

    @property
    def samples_per_second(self) -> float:
        """Training samples per second of the epochs' time."""
        return self.trained_samples / self.seconds if self.seconds > 0 else math.nan

    def summary(self) -> dict:
        """The numbers recorded in a model card."""
        return {"epochs": len(self.history["val"]), "best_epoch": self.best_epoch, "best_val": self.best_val,
                "val_all": self.val_all, "final_train": self.history["train"][-1],
                "wall_time_s": round(self.seconds, 2), "samples_per_s": round(self.samples_per_second, 1),
                "trained_samples": self.trained_samples, "held_out": self.held_out,
                "val_all_s": round(self.val_all_seconds, 2)}


def _state_arrays(params: list[Tensor], opt: torch.optim.Optimizer, sched: object, best: list[Tensor],
                  meta: dict) -> dict[str, np.ndarray]:
    arrays = {f"param/{i}": p.detach().cpu().numpy() for i, p in enumerate(params)}
    arrays.update({f"best/{i}": b.cpu().numpy() for i, b in enumerate(best)})
    for i, p in enumerate(params):
        for key, value in opt.state.get(p, {}).items():
            arrays[f"opt/{i}/{key}"] = torch.as_tensor(value).detach().cpu().numpy()
    arrays["lr"] = np.array([g["lr"] for g in opt.param_groups])
    arrays["sched"] = np.frombuffer(json.dumps(_sched_state(sched)).encode(), dtype=np.uint8)
    for key, value in meta.items():
        arrays[f"meta/{key}"] = np.asarray(value)
    return arrays


def _sched_state(sched: object) -> dict:
    return {k: v for k, v in sched.state_dict().items() if isinstance(v, (int, float, str, bool, type(None)))}


def _save_checkpoint(path: Path, arrays: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".npz")
    try:
        with os.fdopen(handle, "wb") as stream:
            np.savez(stream, **arrays)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _load_checkpoint(path: Path, params: list[Tensor], opt: torch.optim.Optimizer, sched: object,
                     best: list[Tensor]) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:      # said in one line, naming the file
        raise error(f"checkpoint {path}", "a checkpoint this training wrote (plain .npz)",
                    Text(f"a file numpy cannot read ({type(exc).__name__}: {exc})"), "Delete it to start afresh.") \
            from None
    n = sum(1 for k in arrays if k.startswith("param/"))
    if n != len(params):
        raise error(f"checkpoint {path}", f"{len(params)} parameter tensors (as this stage has)",
                    Text(f"{n} parameter tensors"), "Delete it to start afresh.")
    missing = [k for k in ("lr", "sched", "meta/epoch", "meta/best_val", "meta/best_epoch",
                           *(f"best/{i}" for i in range(n))) if k not in arrays]
    if missing:
        raise error(f"checkpoint {path}", "the arrays a checkpoint holds", Text(f"none named {missing[0]!r}"),
                    "Delete it to start afresh.")
    with torch.no_grad():
        for i, p in enumerate(params):
            if tuple(arrays[f"param/{i}"].shape) != tuple(p.shape):
                raise error(f"checkpoint {path}: 'param/{i}'", f"shape {tuple(p.shape)}",
                            Text(f"shape {arrays[f'param/{i}'].shape}"), "Delete it to start afresh.")
            p.copy_(torch.as_tensor(arrays[f"param/{i}"]))
            best[i].copy_(torch.as_tensor(arrays[f"best/{i}"]))
            state = {k.split("/")[2]: torch.as_tensor(v, device=p.device) for k, v in arrays.items()
                     if k.startswith(f"opt/{i}/")}
            if state:
                state["step"] = state["step"].cpu()
                opt.state[p] = state
    for group, lr in zip(opt.param_groups, arrays["lr"]):
        group["lr"] = float(lr)
    sched.load_state_dict({**sched.state_dict(), **json.loads(arrays["sched"].tobytes().decode())})
    return {k[5:]: v for k, v in arrays.items() if k.startswith("meta/")}


def fit(params: list[Tensor], loss_fn: LossFn, data: Dataset, config: LoopConfig, *, name: str, seed: int = 0,
        checkpoint: str | os.PathLike | None = None, resume: bool = False, progress: bool = True,
        val_loss_fn: LossFn | None = None) -> FitResult:
    """Minimise ``loss_fn`` over mini-batches of ``data`` with Adam; keep the best validation epoch.

    Parameters
    ----------
    params : list of Tensor
        The trained parameters (requires_grad).
    loss_fn : callable ``(batch, epoch) -> (loss, parts)``
        Scalar loss of a batch and a dict of float parts shown and recorded.
    data : Dataset
    config : LoopConfig
    name : str
        Stage name for progress bars, errors and the history.
    seed : int
        Seeds the split, the shuffles and torch.
    checkpoint : path, optional
        ``.npz`` written after each epoch; with ``resume=True`` an existing one is continued.
    val_loss_fn : callable, optional
        Validation loss (default ``loss_fn``), evaluated without parameter gradients.

    Returns
    -------
    FitResult
        After the call the parameters hold the best validation epoch.

    Raises
    ------
    FloatingPointError
        If a loss becomes NaN or infinite (the message names the stage, epoch and batch).
    """
    torch.manual_seed(seed)
    n = len(data)
    n_val = max(1, int(round(config.val_fraction * n)))
    if n - n_val < config.batch_size:
        raise error(f"{name}: data", f"at least batch_size = {config.batch_size} training samples",
                    Text(f"{n} samples, {n - n_val} of them for training"), "Generate more data or lower batch_size.")
    perm = np.random.default_rng(seed).permutation(n)
    val_idx, train_idx = perm[:n_val], perm[n_val:]
    # torch's fused Adam on the CPU: one kernel for all parameters (the per-tensor loop was 8 % of the bank decoder's
    # fit); not on CUDA, where its step counters would have to live on the device for the checkpoints, nor before
    # torch 2.4, which has no CPU kernel for it (setup.cfg allows 2.2)
    fused = FUSED_CPU_ADAM and all(p.device.type == "cpu" for p in params)
    opt = torch.optim.Adam(params, lr=config.lr, fused=fused or None)
    if config.schedule == "plateau":
        sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=5)
    else:
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=config.epochs, eta_min=config.lr * 0.01)
    best = [p.detach().clone() for p in params]
    history: dict[str, list[float]] = {"train": [], "val": []}
    best_val, best_epoch, start = math.inf, -1, 0
    ckpt = Path(checkpoint) if checkpoint is not None else None
    if resume and ckpt is not None and ckpt.exists():
        meta = _load_checkpoint(ckpt, params, opt, sched, best)
        start = int(meta["epoch"]) + 1
        best_val, best_epoch = float(meta["best_val"]), int(meta["best_epoch"])
        history = {k[8:]: list(v) for k, v in meta.items() if k.startswith("history/")}
    val_fn = val_loss_fn or loss_fn
    scored = val_idx if config.val_samples is None else val_idx[:config.val_samples]   # val_idx is shuffled
    per_epoch = min(config.samples_per_epoch or len(train_idx), len(train_idx))
    n_batches = per_epoch // config.batch_size
    t0 = time.perf_counter()
    seen = 0
    bar = tqdm(range(start, config.epochs), desc=name, disable=not progress, unit="epoch", leave=False)
    for epoch in bar:
        # each epoch's shuffle depends on (seed, epoch) only, so a resumed run repeats it exactly
        order = np.random.default_rng([seed, epoch]).permutation(train_idx)[:n_batches * config.batch_size]
        sums: dict[str, float] = {}
        for b in range(n_batches):
            batch = data.get(order[b * config.batch_size:(b + 1) * config.batch_size])
            loss, parts = loss_fn(batch, epoch)
            if not torch.isfinite(loss):
                _blame_the_data(name, batch)
                raise FloatingPointError(f"{name}: the loss became {loss.item()} at epoch {epoch}, batch {b}; "
                                         "lower the learning rate or check the data for outliers")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, config.clip)
            opt.step()
            for k, v in {"train": loss.item(), **parts}.items():
                sums[k] = sums.get(k, 0.0) + v
        seen += n_batches * config.batch_size
        val = _evaluate(val_fn, data, scored, config.batch_size, epoch)
        if not math.isfinite(val):
            _blame_the_data(name, data.get(scored))
            raise FloatingPointError(f"{name}: the validation loss became {val} at epoch {epoch}; "
                                     "lower the learning rate")
        record = {k: v / n_batches for k, v in sums.items()}
        record["val"] = val
        for k, v in record.items():
            history.setdefault(k, []).append(v)
        if val < best_val:
            best_val, best_epoch = val, epoch
            with torch.no_grad():
                for bst, p in zip(best, params):
                    bst.copy_(p)
        if config.schedule == "plateau":
            sched.step(val)
        else:
            sched.step()
        bar.set_postfix(train=f"{record['train']:.3e}", val=f"{val:.3e}", lr=f"{opt.param_groups[0]['lr']:.1e}")
        if ckpt is not None:
            meta = {"epoch": epoch, "best_val": best_val, "best_epoch": best_epoch,
                    **{f"history/{k}": np.asarray(v) for k, v in history.items()}}
            _save_checkpoint(ckpt, _state_arrays(params, opt, sched, best, meta))
    bar.close()
    with torch.no_grad():
        for bst, p in zip(best, params):
            p.copy_(bst)
    seconds = time.perf_counter() - t0
    val_all = best_val if len(scored) == len(val_idx) else _evaluate(val_fn, data, val_idx, config.batch_size,
                                                                      max(best_epoch, 0))
    return FitResult(history, best_val, best_epoch, seconds, seen, len(val_idx), val_all,
                     time.perf_counter() - t0 - seconds)


def _blame_the_data(name: str, batch: Mapping[str, Tensor]) -> None:
    """A loss that is not finite on data that hold NaN or inf is the data's fault (the plant's simulations), not the
    learning rate's: raise saying so."""
    bad = [key for key, value in batch.items() if torch.is_floating_point(value) and not torch.isfinite(value).all()]
    if bad:
        raise error(f"{name}: data", "finite training data", Text(f"NaN or inf in {', '.join(bad)}"),
                    "They come from simulating the plant: check that its f(x, u) and h(x) are finite over the X0 box "
                    "and the inputs (a square root or logarithm of a state that turns negative, a division by one "
                    "that reaches zero).")


def _evaluate(loss_fn: LossFn, data: Dataset, index: np.ndarray, batch_size: int, epoch: int) -> float:
    total, count = 0.0, 0
    size = max(batch_size, 4096)
    for start in range(0, len(index), size):
        chunk = index[start:start + size]
        with torch.no_grad():
            loss, _ = loss_fn(data.get(chunk), epoch)
        total += loss.item() * len(chunk)
        count += len(chunk)
    return total / count
