"""Training throughput (samples/s) per stage, and the cost of one default Phase-2 epoch (imports torch)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

from ...validation import Text, error
from . import Timing

__all__ = ["bench_training", "bench_phase2_epoch", "PHASE2_WINDOW_METHODS"]

#: The Phase-2 methods whose epoch :func:`bench_phase2_epoch` times (trained on windowed samples).
PHASE2_WINDOW_METHODS = ("obs", "dyn")


def bench_training(system: str = "duffing", *, device: str = "cpu", threads: Optional[int] = None) -> list[Timing]:
    """Training throughput (samples/s) of each stage with the default architectures, on a short run
    (``threads``: torch CPU threads, default :data:`kklcasadi.train.TRAIN_THREADS`)."""
    import tempfile
    from dataclasses import replace

    from ...model.files import load_model
    from ...train import TRAIN_THREADS, LoopConfig, Phase2DataConfig, default_config, train_observer

    loop = LoopConfig(epochs=1, batch_size=512, samples_per_epoch=4096, schedule="cosine")
    stages = []
    with tempfile.TemporaryDirectory() as tmp:
        base = f"{tmp}/autonomous"
        p1 = default_config(system, "autonomous", n_traj=40, n_pde=2000, encoder=replace(loop, batch_size=1024),
                            decoder=replace(loop, batch_size=1024))
        train_observer(system, "autonomous", base, config=p1, device=device, progress=False, threads=threads)
        training = load_model(base).card["training"]
        stages += [(f"phase 1 {k} (width {p1.width})", training[k]) for k in ("encoder", "decoder")]
        data = Phase2DataConfig(n_traj=4, n_signals=4, T=20.0)
        for method in ("obs", "dyn"):
            cfg = default_config(system, method, data=data, loop=loop)
            train_observer(system, method, f"{tmp}/{method}", config=cfg, base=base, device=device, progress=False,
                           threads=threads)
            stages.append((f"phase 2 {method} (window {data.window})",
                           load_model(f"{tmp}/{method}").card["training"][method]))
    out = [Timing(label, summary["wall_time_s"], summary["trained_samples"]) for label, summary in stages]
    for timing in out:
        print(f"{timing.label:<44s} {timing.rate:12.0f} samples/s ({device}, {threads or TRAIN_THREADS} threads)")
    return out


def bench_phase2_epoch(system: str, base: str | Path, *, methods: tuple = PHASE2_WINDOW_METHODS, data: Any = None,
                       device: str = "cpu", threads: Optional[int] = None) -> list[Timing]:
    """One epoch of each Phase-2 method at its default loop, scoring validation on all held-out samples
    (``val_samples=None``, the setting before the default subset) and on the default subset.

    Parameters
    ----------
    system : str
    base : path
        The Phase-1 model the methods start from (e.g. ``models/<system>/autonomous``).
    methods : tuple of str
        Among :data:`PHASE2_WINDOW_METHODS`.
    data : Phase2DataConfig, optional
        The training data (default: each method's default, as a full training run uses).
    device : {"cpu", "cuda"}
    threads : int, optional
        torch CPU threads (default :data:`kklcasadi.train.TRAIN_THREADS`).

    Returns
    -------
    list of Timing
        Per method the all-held-out epoch then the default one: the epoch's seconds (training and
        validation) and its training samples. The final scoring of the kept model on all held-out
        samples (once per run, not per epoch) is printed beside them.
    """
    import tempfile
    from dataclasses import replace

    from ...model.files import load_model
    from ...train import TRAIN_THREADS, default_config, train_observer

    unknown = [m for m in methods if m not in PHASE2_WINDOW_METHODS]
    if isinstance(methods, str) or not methods or unknown:
        raise error("methods", f"a non-empty tuple of {PHASE2_WINDOW_METHODS}", Text(repr(methods)))
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for method in methods:
            cfg = default_config(system, method, epochs=1)
            if data is not None:
                cfg = replace(cfg, data=data)
            runs = []
            for label, val_samples in (("all held-out", None), (f"{cfg.loop.val_samples}", cfg.loop.val_samples)):
                run = replace(cfg, loop=replace(cfg.loop, val_samples=val_samples))
                train_observer(system, method, f"{tmp}/{method}", config=run, base=base, device=device,
                               progress=False, threads=threads, overwrite=True)
                summary = load_model(f"{tmp}/{method}").card["training"][method]
                timing = Timing(f"{method} epoch, validation on {label}", summary["wall_time_s"],
                                summary["trained_samples"])
                runs.append((timing, summary["val_all_s"], summary["held_out"]))
            (before, _, held_out), (after, scoring, _) = runs
            epochs = default_config(system, method).loop.epochs
            print(f"{method}: {held_out} samples held out, {after.items} trained per epoch, "
                  f"{epochs} epochs by default ({device}, {threads or TRAIN_THREADS} threads)")
            for timing in (before, after):
                print(f"  {timing.label:<40s} {timing.seconds:8.2f} s/epoch {timing.rate:10.0f} samples/s"
                      f"  -> {epochs} epochs {timing.seconds * epochs / 60:6.1f} min")
            print(f"  ratio {before.seconds / after.seconds:.2f}x per epoch; the kept model is scored on all "
                  f"held-out samples once, in {scoring:.1f} s")
            out += [before, after]
    return out
